"""SOC from a 20 % initial error on every 25 degC drive cycle of both measured cells.

The issue's bound: after the first hour the SOC RMSE is at most 2 %, stating only the
nominal capacity.  The reference is coulomb counting from the known full start with the
file's measured capacity (``analysis.measured_capacity``), never the stated one.
"""

from concurrent.futures import ProcessPoolExecutor

import numpy as np
import pytest

from bms_estimator.analysis import measured_capacity, reference_soc, run_soc, soc_errors
from bms_estimator.core.ocv import OcvCurve
from bms_estimator.core.soc import SocConfig
from bms_estimator.data import load_recording
from tests.conftest import SHARED, needs_shared

CELLS = {"panasonic-18650pf": 2.9, "lg-hg2": 3.0}  # nominal capacities, Ah
SKIP = {"c20_ocv", "hppc", "hppc_steps"}


def _drive_cycles() -> list[tuple[str, str]]:
    if SHARED is None:
        return []
    return [(cell, p.name.split(".")[0]) for cell in CELLS for p in sorted((SHARED / cell / "25degC").glob("*.csv*"))
            if p.name.split(".")[0] not in SKIP]


def _after_1h(job: tuple[str, str]) -> tuple[str, dict[bool, float]]:
    """After-1h SOC RMSE of one file, with and without the hysteresis branch (one reference)."""
    cell, name = job
    d = SHARED / cell / "25degC"
    c20 = load_recording(next(d.glob("c20_ocv.csv*")), resample_s=None)
    ocv = OcvCurve.from_c20(c20.time_s, c20.current_a, c20.voltage_v)
    rec = load_recording(next(d.glob(f"{name}.csv*")))
    q_ref, _ = measured_capacity(rec.current_a, rec.voltage_v, rec.dt_s, ocv, CELLS[cell])
    ref = reference_soc(rec.current_a, rec.dt_s, q_ref)
    out = {}
    for hysteresis in (True, False):
        run = run_soc(rec.current_a, rec.voltage_v, ocv, CELLS[cell], 0.8, rec.dt_s, SocConfig(hysteresis=hysteresis))
        out[hysteresis] = soc_errors(run.soc, ref, rec.time_s - rec.time_s[0])["soc_rmse_pct_after_3600s"]
    return f"{cell}/{name}", out


@pytest.fixture(scope="module")
def after_1h() -> dict[bool, dict[str, float]]:
    with ProcessPoolExecutor(max_workers=2) as pool:
        res = list(pool.map(_after_1h, _drive_cycles()))
    return {h: {key: errs[h] for key, errs in res} for h in (True, False)}


@needs_shared
def test_soc_after_the_first_hour_within_2pct_on_every_drive_cycle(after_1h):
    got = after_1h[True]
    assert len(got) >= 14 and {k.split("/")[0] for k in got} == set(CELLS), got
    over = {k: round(v, 2) for k, v in got.items() if not v <= 2.0}
    assert not over, over


@needs_shared
def test_reading_the_discharge_branch_beats_the_mean_ocv_curve(after_1h):
    """Without the hysteresis column a discharging cell's c0 sits near -H, which compensation
    reads as a low SOC (measured when written: mean 1.05 % against 1.19 %, worst 1.93 % against 2.54 %)."""
    with_h, without = (np.array(list(after_1h[h].values())) for h in (True, False))
    assert with_h.mean() < without.mean(), (with_h, without)
    assert with_h.max() < without.max() - 0.3, (with_h, without)
