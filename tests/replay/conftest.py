"""Fixtures for the replay tests: one encoded short log (shared) and a Mosquitto broker."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[2]
for p in (REPO_ROOT, REPO_ROOT / "tests" / "service", Path(__file__).resolve().parent):
    if str(p) not in sys.path:  # the package may not be installed; helpers by module name
        sys.path.insert(0, str(p))

from replay_helpers import CELL, CYCLE, DURATION_S, MOSQUITTO, N_CELLS, SEED, Broker, mosquitto_available  # noqa: E402

from bms_estimator.cli.__main__ import main  # noqa: E402
from bms_estimator.samples import drive_cycle  # noqa: E402


@pytest.fixture(scope="session")
def encoded(tmp_path_factory) -> dict:
    """``bms-estimator encode-log`` run once with the defaults (OCV and capacity from the file name)."""
    d = tmp_path_factory.mktemp("encoded")
    out = d / "pack.log"
    rc = main(["encode-log", str(drive_cycle(CELL, CYCLE)), "--cells", str(N_CELLS), "-o", str(out),
               "--seed", str(SEED), "--duration-s", str(DURATION_S), "--no-progress"])
    assert rc == 0
    truth = json.loads(Path(str(out) + ".truth.json").read_text())
    return {"dir": d, "log": out, "truth": truth}


@pytest.fixture
def mosquitto(tmp_path):
    if not mosquitto_available():
        pytest.skip(f"mosquitto broker not found at {MOSQUITTO} (apt-get install mosquitto, or set $MOSQUITTO)")
    b = Broker(tmp_path).start()
    yield b
    b.stop()
