"""A stated capacity far from the cell's in the batch: the summary's capacity_at_bound_final says the capacity
ended at its bound, and the last lines say how many cell-drives and why (the first 3000 s of the shipped
Panasonic 18650PF cycle_1 sample, Kollmeyer, Mendeley Data, CC BY 4.0, a 2.9 Ah cell)."""

from __future__ import annotations

import csv
import gzip
from pathlib import Path

import pytest

from bms_estimator.cli.__main__ import main
from bms_estimator.fleet.batch import summary_rows
from bms_estimator.fleet.drive import run_drive

SAMPLES = Path(__file__).parents[2] / "bms_estimator" / "samples"
SECONDS = 3000


def _config(tmp_path: Path, capacity_ah: float) -> Path:
    cfg = tmp_path / f"config_{capacity_ah:g}.toml"
    cfg.write_text(f'[pack]\nn_cells = 1\ncapacity_ah = {capacity_ah}\n'
                   f'ocv_csv = "{SAMPLES / "panasonic-18650pf_25degC_ocv.csv"}"\n'
                   '[can]\ninterface = "virtual"\n[mqtt]\nenabled = false\n')
    return cfg


@pytest.fixture(scope="module")
def drive(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("bound")
    lines = gzip.open(SAMPLES / "panasonic-18650pf_25degC_cycle_1_1s.csv.gz", "rt").read().splitlines()
    csv_path = d / "car" / "cycle1_3000s.csv"
    csv_path.parent.mkdir()
    csv_path.write_text("\n".join(lines[:SECONDS + 1]) + "\n")
    return csv_path


def test_right_capacity_ends_inside_the_bounds(drive, tmp_path):
    res, _, _ = run_drive(drive, str(_config(tmp_path, 2.9)), tmp_path / "out", "car")
    assert res.status == "ok", res.error
    (row,) = summary_rows([res])
    assert row["capacity_at_bound_final"] == 0 and 2.6 < row["capacity_ah_final"] < 3.2


def test_the_example_configs_50_ah_ends_at_the_low_bound_and_is_reported(drive, tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["batch", str(drive), "--config", str(_config(tmp_path, 50.0)), "--out", str(out), "--workers", "1",
                 "--no-progress"]) == 0
    text = capsys.readouterr().out
    with (out / "summary.csv").open() as fh:
        (row,) = list(csv.DictReader(fh))
    assert row["status"] == "ok" and row["capacity_at_bound_final"] == "-1"
    assert float(row["capacity_ah_final"]) == pytest.approx(0.6 * 50.0)  # clipped at its low bound
    assert ("warning: 1 cell-drive(s) ended with the capacity estimate at a bound (capacity_at_bound_final in "
            "summary.csv), e.g. cycle1_3000s.csv cell 0 at 30.000 Ah: the stated pack.capacity_ah is likely wrong") in text
