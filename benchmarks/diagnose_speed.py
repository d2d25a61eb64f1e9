"""Wall time of ``bms-estimator diagnose`` on the 4.4 h LG UDDS sample (goal: under 60 s)."""

from __future__ import annotations

import time

__all__ = ["bench_diagnose_s"]


def bench_diagnose_s() -> float:
    """Wall time [s] of ``diagnose`` (defaults: LIF warm start, pair stage) on a 4.4 h drive cycle.

    The shipped LG HG2 UDDS sample (15966 s at 1 s, 25 degC), stated capacity 3.0 Ah,
    cross-validated.  For ``bms-estimator bench``; a figure, not a test.
    """
    from bms_estimator import samples
    from bms_estimator.data import load_recording
    from bms_estimator.diagnose import Series, diagnose
    from bms_estimator.ocv_table import read_ocv_table

    rec = load_recording(samples.drive_cycle("lg-hg2", "udds"))
    ocv = read_ocv_table(samples.ocv_table("lg-hg2"))
    data = Series.from_recording(rec, ocv, 3.0)
    t0 = time.perf_counter()
    diagnose(data)
    return time.perf_counter() - t0
