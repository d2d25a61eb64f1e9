"""Fixtures for the service tests: a real Mosquitto broker on a free loopback port.

Independent of tests/conftest.py. ``mosquitto`` is a started plain broker;
``broker_factory`` builds brokers with extra config (password file, TLS) that
a test can start, stop and restart on the same port.
"""

from __future__ import annotations

import shutil
import sys
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[2]
if str(REPO_ROOT) not in sys.path:  # the package may not be installed
    sys.path.insert(0, str(REPO_ROOT))
_HERE = str(Path(__file__).resolve().parent)
if _HERE not in sys.path:  # service_helpers, whatever pytest's import mode
    sys.path.insert(0, _HERE)

from service_helpers import MOSQUITTO, Broker, mosquitto_available  # noqa: E402

def _require_mosquitto() -> None:
    if not mosquitto_available():
        pytest.skip(
            f"mosquitto broker not found at {MOSQUITTO} (apt-get install mosquitto, "
            "or set $MOSQUITTO); the MQTT tests need a real broker"
        )


@pytest.fixture
def broker_factory(tmp_path: Path) -> Iterator[Callable[..., Broker]]:
    """``make(extra_conf="", port=None, start=True, anonymous=True, persistence=False) -> Broker``.

    Every broker made is stopped after the test.
    """
    _require_mosquitto()
    brokers: list[Broker] = []

    def make(
        extra_conf: str = "",
        port: int | None = None,
        start: bool = True,
        anonymous: bool = True,
        persistence: bool = False,
    ) -> Broker:
        b = Broker(
            tmp_path / f"broker{len(brokers)}",
            port=port,
            extra_conf=extra_conf,
            anonymous=anonymous,
            persistence=persistence,
        )
        brokers.append(b)
        if start:
            b.start()
        return b

    yield make
    for b in brokers:
        b.stop()


@pytest.fixture
def mosquitto(broker_factory: Callable[..., Broker]) -> Broker:
    """A started anonymous broker on a free 127.0.0.1 port."""
    return broker_factory()


@pytest.fixture
def mosquitto_passwd() -> str:
    path = shutil.which("mosquitto_passwd") or "/usr/bin/mosquitto_passwd"
    if not Path(path).exists():
        pytest.skip("mosquitto_passwd not found (it ships with the mosquitto package)")
    return path
