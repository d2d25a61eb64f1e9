"""A capacity at its bound in the batch: the summary's capacity_at_bound_final says the capacity ended at its
bound, and the last lines say how many cell-drives and why; a stated capacity far from the OCV table's is
refused before any drive runs (the first 3000 s of the shipped Panasonic 18650PF cycle_1 sample, Kollmeyer,
Mendeley Data, CC BY 4.0, a 2.9 Ah cell)."""

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


def _config(tmp_path: Path, capacity_ah: float, core: str = "") -> Path:
    cfg = tmp_path / f"config_{capacity_ah:g}.toml"
    cfg.write_text(f'[pack]\nn_cells = 1\ncapacity_ah = {capacity_ah}\n'
                   f'ocv_csv = "{SAMPLES / "panasonic-18650pf_25degC_ocv.csv"}"\n'
                   '[can]\ninterface = "virtual"\n[mqtt]\nenabled = false\n'
                   + (f"[estimator.core]\n{core}\n" if core else ""))
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


def test_a_capacity_ended_at_its_bound_is_reported(drive, tmp_path, capsys):
    """A low bound above the table's 2.997 Ah (``capacity_bounds = [1.05, 1.4]`` x 2.9 Ah): the capacity is
    clipped up to it and stays, as one learnt down to its bound over hours would."""
    out = tmp_path / "out"
    cfg = _config(tmp_path, 2.9, "capacity_bounds = [1.05, 1.4]")
    assert main(["batch", str(drive), "--config", str(cfg), "--out", str(out), "--workers", "1", "--no-progress"]) == 0
    text = capsys.readouterr().out
    with (out / "summary.csv").open() as fh:
        (row,) = list(csv.DictReader(fh))
    assert row["status"] == "ok" and row["capacity_at_bound_final"] == "-1"
    q = float(row["capacity_ah_final"])
    assert 1.05 * 2.9 <= q <= 1.05 * 2.9 * 1.01, q  # clipped up to its low bound, within the flag's 1 %
    assert ("warning: 1 cell-drive(s) ended with the capacity estimate at a bound (capacity_at_bound_final in "
            f"summary.csv), e.g. cycle1_3000s.csv cell 0 at {q:.3f} Ah: the stated pack.capacity_ah is likely wrong") in text


def test_the_example_configs_50_ah_on_a_2_9_ah_cells_table_is_said(drive, tmp_path, capsys):
    """deploy/config.example.toml's 50 Ah with this cell's table: before, the drive ran to a capacity clipped at
    30 Ah (0.6 x 50, from the table's 2.997 Ah) and a plausible-looking SOC; now it counts with the stated 50 Ah
    and the batch says at start that the two capacities disagree."""
    out = tmp_path / "out"
    assert main(["batch", str(drive), "--config", str(_config(tmp_path, 50.0)), "--out", str(out),
                 "--workers", "1", "--no-progress"]) == 0
    captured = capsys.readouterr()
    assert "pack.capacity_ah 50 Ah is 16.7 times the C/20 capacity 2.997 Ah of pack.ocv_csv" in captured.out + captured.err
    with (out / "summary.csv").open() as fh:
        (row,) = list(csv.DictReader(fh))
    assert row["status"] == "ok" and 40.0 < float(row["capacity_ah_final"]) <= 50.0


def test_c0_voltage_line_flags_a_stated_capacity_5x_the_cells_in_the_batch(tmp_path, capsys):
    """The c0 SOC method, an LG HG2 table without capacity_ah and pack.capacity_ah 14 for the 2.8 Ah cell (the
    shipped 25 degC udds sample, Kollmeyer et al., CC BY 4.0): the summary flags the cell-drive, gives the
    capacity the voltage line reads, and the last line names the drive, the cell and that figure."""
    lines = (SAMPLES / "lg-hg2_25degC_ocv.csv").read_text().splitlines()
    cols = lines[0].split(",")
    keep = [k for k, c in enumerate(cols) if c != "capacity_ah"]
    table = tmp_path / "lg_no_capacity.csv"
    table.write_text("\n".join(",".join(r.split(",")[k] for k in keep) for r in lines) + "\n")
    drive = tmp_path / "car" / "udds.csv.gz"
    drive.parent.mkdir()
    drive.write_bytes((SAMPLES / "lg-hg2_25degC_udds_1s.csv.gz").read_bytes())
    cfg = tmp_path / "c0.toml"
    cfg.write_text(f'[pack]\nn_cells = 1\ncapacity_ah = 14\nocv_csv = "{table}"\n[can]\ninterface = "virtual"\n'
                   '[mqtt]\nenabled = false\n[estimator.core]\nsoc_method = "c0"\n')
    out = tmp_path / "out"
    assert main(["batch", str(drive), "--config", str(cfg), "--out", str(out), "--workers", "1", "--no-progress"]) == 0
    text = capsys.readouterr().out
    with (out / "summary.csv").open() as fh:
        (row,) = list(csv.DictReader(fh))
    assert row["status"] == "ok" and row["capacity_at_bound_final"] == "-1", row
    q_v = float(row["capacity_voltage_ah_final"])
    assert 2.4 < q_v < 3.0, q_v
    assert (f"e.g. udds.csv.gz cell 0 at 14.000 Ah, its voltage saying {q_v:.3f} Ah: the stated pack.capacity_ah "
            "is likely wrong") in text, text
