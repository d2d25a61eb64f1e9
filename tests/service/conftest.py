"""Fixtures for the service tests: a real Mosquitto broker on a free loopback port.

Independent of tests/conftest.py. ``mosquitto`` is a started plain broker;
``broker_factory`` builds brokers with extra config (password file, TLS) that
a test can start, stop and restart on the same port.
"""

from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[2]
if str(REPO_ROOT) not in sys.path:  # the package may not be installed
    sys.path.insert(0, str(REPO_ROOT))
_HERE = str(Path(__file__).resolve().parent)
if _HERE not in sys.path:  # service_helpers, whatever pytest's import mode
    sys.path.insert(0, _HERE)

from service_helpers import free_port  # noqa: E402

MOSQUITTO = os.environ.get("MOSQUITTO", "/usr/sbin/mosquitto")


class Broker:
    """A mosquitto process with a generated config file."""

    def __init__(
        self,
        workdir: Path,
        port: int | None = None,
        extra_conf: str = "",
        *,
        anonymous: bool = True,
        persistence: bool = False,
    ) -> None:
        self.workdir = workdir
        self.workdir.mkdir(parents=True, exist_ok=True)
        self.host = "127.0.0.1"
        self.port = port or free_port()
        self.extra_conf = extra_conf
        self.anonymous = anonymous
        self.persistence = persistence
        self.conf = workdir / "mosquitto.conf"
        self.logfile = workdir / "mosquitto.log"
        self.proc: subprocess.Popen[bytes] | None = None

    def _write_conf(self) -> None:
        lines = [
            f"listener {self.port} 127.0.0.1",
            f"allow_anonymous {'true' if self.anonymous else 'false'}",
            f"persistence {'true' if self.persistence else 'false'}",
            f"log_dest file {self.logfile}",
            "log_type error",
            "log_type warning",
            "log_type notice",
            "log_type information",
        ]
        if self.persistence:
            lines.append(f"persistence_location {self.workdir}/")
        if hasattr(os, "geteuid") and os.geteuid() == 0:
            lines.append("user root")  # do not drop to 'mosquitto' (cannot read tmp files)
        self.conf.write_text("\n".join(lines) + "\n" + self.extra_conf + "\n")

    def start(self, timeout: float = 10.0) -> Broker:
        assert self.proc is None or self.proc.poll() is not None, "already running"
        self._write_conf()
        self.proc = subprocess.Popen(
            [MOSQUITTO, "-c", str(self.conf)],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
        )
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                err = self.proc.stderr.read().decode(errors="replace") if self.proc.stderr else ""
                log = self.logfile.read_text(errors="replace") if self.logfile.exists() else ""
                raise RuntimeError(f"mosquitto exited with {self.proc.returncode}: {err}\n{log}")
            try:
                with socket.create_connection((self.host, self.port), timeout=0.2):
                    return self
            except OSError:
                time.sleep(0.02)
        self.stop()
        raise RuntimeError(f"mosquitto did not accept connections on port {self.port} within {timeout}s")

    def stop(self) -> None:
        proc, self.proc = self.proc, None
        if proc is None or proc.poll() is not None:
            return
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout=5)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout=5)
        if proc.stderr:
            proc.stderr.close()

    @property
    def running(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def log_text(self) -> str:
        return self.logfile.read_text(errors="replace") if self.logfile.exists() else ""


def _require_mosquitto() -> None:
    if not (Path(MOSQUITTO).is_file() and os.access(MOSQUITTO, os.X_OK)):
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
