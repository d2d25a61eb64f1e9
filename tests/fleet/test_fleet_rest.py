"""``batch --chain`` across the time between two drives: rested over when both logs carry absolute (epoch)
times, carried as before (and said) when they do not; a drive with a time jump inside is rested over too."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from bms_estimator.fleet.batch import summary_rows
from bms_estimator.fleet.drive import run_drive, run_vehicle
from bms_estimator.replay.encode_log import encode_log

from .fleet_helpers import write_batch_config

N_CELLS = 2
SAMPLE = Path(__file__).parents[2] / "bms_estimator" / "samples" / "lg-hg2_25degC_udds_1s.csv.gz"
EPOCH = 1.7e9
DURATION_S = 300.0
PARKED_S = 7200.0


def _logs(d: Path, t0s: list[float], suffix: str = ".log") -> list[Path]:
    logs = []
    for k, t0 in enumerate(t0s):
        out = d / f"drive{k}{suffix}"
        encode_log(SAMPLE, out, N_CELLS, initial_soc=0.9 if k == 0 else 0.8, duration_s=DURATION_S,
                   reference_capacity_ah=3.0, seed=k, t0_s=t0)
        logs.append(out)
    return logs


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    d = tmp_path_factory.mktemp("fleet-rest")
    return d, write_batch_config(d, N_CELLS, "fleet-rest")


def test_two_chained_logs_two_hours_apart_are_rested_over(setup):
    d, cfg = setup
    logs = _logs(d / "epoch", [EPOCH, EPOCH + DURATION_S + PARKED_S])
    results = run_vehicle([str(p) for p in logs], str(cfg), d / "out-epoch", "car1")
    assert [r.status for r in results] == ["ok", "ok"]
    assert results[0].rested_s is None and results[0].chain == ""  # nothing carried into the first
    # the second drive's first period starts PARKED_S after the first's last sample ended (to the frame grid)
    assert results[1].rested_s == pytest.approx(PARKED_S, abs=2.0)
    assert "rested" in results[1].chain
    rows = summary_rows(results)
    assert {r["chain"] for r in rows if r["drive"] == logs[1].name} == {results[1].chain}
    # the carried state did rest: the first SOC of drive 2 differs from the one carried without the rest
    _, state, _ = run_drive(logs[0], str(cfg), d / "x", "car1")
    _, _, unrested = run_drive(logs[1], str(cfg), d / "x", "car1", state)  # no previous end given: no rest
    _, _, rested = run_drive(logs[1], str(cfg), d / "x", "car1", state, previous_end_s=float(EPOCH + DURATION_S))
    assert not np.array_equal(rested.cells["soc"][0], unrested.cells["soc"][0])


def test_logs_without_absolute_times_are_carried_without_a_rest_and_say_so(setup):
    d, cfg = setup
    logs = _logs(d / "relative", [0.0, DURATION_S + PARKED_S])  # times from 0: no epoch stamps
    results = run_vehicle([str(p) for p in logs], str(cfg), d / "out-rel", "car1")
    assert [r.status for r in results] == ["ok", "ok"]
    assert results[1].rested_s is None and "no absolute times" in results[1].chain
    rows = summary_rows(results)
    assert all("no absolute times" in r["chain"] for r in rows if r["drive"] == logs[1].name)


def test_a_time_jump_inside_one_drive_is_rested_over_and_the_drive_runs_alone(setup, tmp_path):
    """Two logs' frames in one file 2 h apart: one drive with a time jump, as the service would see it."""
    d, cfg = setup
    a, b = _logs(tmp_path, [EPOCH, EPOCH + DURATION_S + PARKED_S])
    joined = tmp_path / "joined.log"
    joined.write_text(a.read_text() + b.read_text())
    res, _, est = run_drive(joined, str(cfg), tmp_path / "out", "car1")
    assert res.status == "ok" and res.counters["time_jumps"] == 1
    from bms_estimator.fleet.drive import run_drives

    stacked = run_drives([(str(joined), "car1"), (str(a), "car2")], str(cfg), tmp_path / "out2", write=False)
    assert [r.status for r in stacked] == ["ok", "ok"]
    assert stacked[0].counters["stacked_with"] == 1  # run one by one: the stack cannot rest one drive alone
