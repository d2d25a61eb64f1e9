"""Fixtures of the end-to-end tests: a Mosquitto broker and encoded pack logs (``bms-estimator encode-log``)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[2]
for p in (REPO_ROOT, Path(__file__).resolve().parent):
    if str(p) not in sys.path:  # the package may not be installed; helpers by module name
        sys.path.insert(0, str(p))

from e2e_helpers import CELL, CYCLE, MOSQUITTO, Broker, mosquitto_available  # noqa: E402

from bms_estimator.cli.__main__ import main  # noqa: E402
from bms_estimator.samples import drive_cycle  # noqa: E402


def encode(out: Path, cells: int, duration_s: float, seed: int = 0, data: Path | None = None,
           *extra: str) -> dict:
    rc = main(["encode-log", str(data or drive_cycle(CELL, CYCLE)), "--cells", str(cells), "-o", str(out),
               "--seed", str(seed), "--duration-s", str(duration_s), "--no-progress", *extra])
    assert rc == 0
    return {"log": out, "truth": json.loads(Path(str(out) + ".truth.json").read_text())}


@pytest.fixture(scope="session")
def pack_log(tmp_path_factory) -> dict:
    """The first hour of LG HG2 LA92 as the CAN log of a 16-cell pack (seed 0)."""
    return encode(tmp_path_factory.mktemp("e2e-pack") / "pack16.log", 16, 3600)


@pytest.fixture(scope="session")
def short_log(tmp_path_factory) -> dict:
    """30 s of the same cycle from its 30th second (its first 30 s hold one current: nothing to identify), 16
    cells: short enough to replay in real time."""
    from bms_estimator.data import CellRecording, load_recording, save_recording

    d = tmp_path_factory.mktemp("e2e-short")
    rec = load_recording(drive_cycle(CELL, CYCLE))
    k = slice(30, 61)
    part = save_recording(CellRecording(rec.time_s[k] - rec.time_s[30], rec.current_a[k], rec.voltage_v[k],
                                        rec.temperature_c[k], "part"), d / f"{CELL}_{CYCLE}_from_30s.csv")
    return encode(d / "short16.log", 16, 30, 0, part, "--reference-capacity-ah", "2.8")


@pytest.fixture(scope="session")
def mosquitto(tmp_path_factory):
    if not mosquitto_available():
        pytest.skip(f"mosquitto broker not found at {MOSQUITTO} (apt-get install mosquitto, or set $MOSQUITTO)")
    b = Broker(tmp_path_factory.mktemp("e2e-broker")).start()
    yield b
    b.stop()
