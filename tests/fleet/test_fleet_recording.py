"""A single-cell recording in the project's CSV layout as a batch drive: a one-cell pack, one sample per 1 s bin."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from bms_estimator.core.soc import SocEstimator
from bms_estimator.fleet.drive import run_drive
from bms_estimator.ocv_table import read_ocv_table

SAMPLES = Path(__file__).parents[2] / "bms_estimator" / "samples"


def _config(tmp_path: Path) -> Path:
    cfg = tmp_path / "config.toml"
    cfg.write_text(f'[pack]\nn_cells = 8\ncapacity_ah = 3.0\nocv_csv = "{SAMPLES / "lg-hg2_25degC_ocv.csv"}"\n'
                   '[can]\ninterface = "virtual"\n[mqtt]\nenabled = false\n')
    return cfg


def test_recording_is_a_one_cell_drive(tmp_path):
    rng = np.random.default_rng(0)
    k = 240
    t = np.arange(k, dtype=float)
    i = np.repeat(rng.uniform(-3, 0.5, k // 20), 20)
    v = 4.0 + 0.02 * i - 0.0004 * t
    temp = 24.0 + 0.01 * t
    csv = tmp_path / "car" / "cell.csv"
    csv.parent.mkdir()
    csv.write_text("time_s,current_a,voltage_v,temperature_c\n"
                   + "".join(f"{a!r},{b!r},{c!r},{d!r}\n" for a, b, c, d in zip(t.tolist(), i.tolist(), v.tolist(), temp.tolist())))
    res, _, est = run_drive(csv, str(_config(tmp_path)), tmp_path / "out", "car")
    assert res.status == "ok", res.error
    assert est.cells["soc"].shape == (k, 1) and np.array_equal(est.t_s, t + 1.0)
    ref = SocEstimator(1, read_ocv_table(SAMPLES / "lg-hg2_25degC_ocv.csv"), 3.0, 1.0)
    soc = []
    for a, b, c in zip(i, v, temp):
        ref.update(a, np.array([b]), np.array([True]), temperature_c=np.array([c]))
        soc.append(ref.soc[0])
    assert np.array_equal(est.cells["soc"][:, 0], soc)
    assert np.array_equal(est.cells["temperature_c"][:, 0], temp)


def test_recording_with_another_step_is_reported(tmp_path):
    csv = tmp_path / "c.csv"
    csv.write_text("time_s,current_a,voltage_v\n0,1,3.7\n2,1,3.7\n4,1,3.7\n")
    res, _, _ = run_drive(csv, str(_config(tmp_path)), tmp_path / "out", "car")
    assert res.status == "skipped" and "sample period" in res.error
    assert "c.csv: the recording's step (2..2 s, median 2 s after averaging to the period)" in res.error


def test_recording_in_milliamps_is_reported_not_estimated(tmp_path):
    """A cell's current in mA spans 1000 times pack.capacity_ah: the drive is skipped with the reason, where it
    was estimated to nonsense before (the shipped LG UDDS sample, Kollmeyer, CC BY 4.0, its current x 1000)."""
    import gzip

    lines = gzip.open(SAMPLES / "lg-hg2_25degC_udds_1s.csv.gz", "rt").read().splitlines()
    rows = [line.split(",") for line in lines[1:]]
    csv = tmp_path / "car" / "milliamp.csv"
    csv.parent.mkdir()
    csv.write_text(lines[0] + "\n" + "".join(f"{r[0]},{float(r[1]) * 1000!r},{r[2]},{r[3]}\n" for r in rows))
    res, _, _ = run_drive(csv, str(_config(tmp_path)), tmp_path / "out", "car")
    assert res.status == "skipped"
    assert "milliamp.csv: its coulomb count spans" in res.error and "times pack.capacity_ah = 3 Ah" in res.error


def test_diagnose_names_a_cause_per_cell(tmp_path):
    """--diagnose: diagnose's named cause in the summary (40 min of the shipped LG UDDS sample, Kollmeyer, CC BY 4.0)."""
    import gzip

    from bms_estimator.diagnose import CAUSES

    lines = gzip.open(SAMPLES / "lg-hg2_25degC_udds_1s.csv.gz", "rt").read().splitlines()
    csv = tmp_path / "car" / "udds40.csv"
    csv.parent.mkdir()
    csv.write_text("\n".join(lines[:2401]) + "\n")
    res, _, _ = run_drive(csv, str(_config(tmp_path)), tmp_path / "out", "car", diagnose=True)
    assert res.status == "ok", res.error
    assert len(res.cells["cause"]) == 1 and res.cells["cause"][0] in (*CAUSES, "none")
    short = tmp_path / "car" / "short.csv"
    short.write_text("\n".join(lines[:601]) + "\n")  # 10 min: below diagnose's 30 min minimum here
    res, _, _ = run_drive(short, str(_config(tmp_path)), tmp_path / "out", "car", diagnose=True)
    assert res.status == "ok" and res.cells["cause"] == [""]
