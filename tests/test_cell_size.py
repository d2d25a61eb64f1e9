"""Nothing in the offline commands may assume an 18650's size: k cells in parallel (or a large-format cell)
are the same cell with current x k, capacity x k, resistances / k.  Here the shipped LG HG2 la92 sample
(Kollmeyer et al., CC BY 4.0) as a 57 Ah cell (current x 20, its OCV table's capacity x 20)."""

from __future__ import annotations

import csv
import gzip
import json
import re

import pytest

from bms_estimator.cli.__main__ import main
from bms_estimator.cli.fit import mohm
from bms_estimator.samples import drive_cycle, ocv_table


def scaled_cell(tmp_path, k: float, seconds: int | None = None):
    """The la92 sample and the LG table as a cell of k times the capacity: ``(data, table)``."""
    data, table = tmp_path / f"la92_x{k:g}.csv", tmp_path / f"ocv_x{k:g}.csv"
    with gzip.open(drive_cycle("lg-hg2", "la92"), "rt") as f:
        rows = list(csv.reader(f))
    head, body = rows[0], rows[1:] if seconds is None else rows[1:seconds + 1]
    ci = head.index("current_a")
    with open(data, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(head)
        w.writerows([*r[:ci], f"{k * float(r[ci]):.9g}", *r[ci + 1:]] for r in body)
    with open(ocv_table("lg-hg2"), newline="") as f:
        rows = list(csv.reader(f))
    qi = rows[0].index("capacity_ah")
    with open(table, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(rows[0])
        w.writerows([*r[:qi], f"{k * float(r[qi]):.9g}", *r[qi + 1:]] for r in rows[1:])
    return data, table


def test_mohm_keeps_three_significant_digits():
    assert [mohm(r) for r in (0.0203, 0.00647, 0.000325, 4.0e-5)] == ["20.3", "6.47", "0.325", "0.0400"]


def test_fit_prints_a_large_cells_resistances_to_three_digits(tmp_path, capsys):
    """A 57 Ah cell's fit printed "R0 1.0 mOhm, R1 0.3 mOhm ... R2 1.0 mOhm" (one fixed decimal: R1 8 % off)."""
    data, table = scaled_cell(tmp_path, 20.0, seconds=2400)
    out = tmp_path / "fit.json"
    assert main(["fit", str(data), "--ocv", str(table), "--capacity-ah", "60", "--json", str(out)]) == 0
    line = next(s for s in capsys.readouterr().out.splitlines() if " mOhm" in s)
    fit = json.loads(out.read_text())
    f = fit["median_soc_20_90"] if fit["median_soc_20_90"]["r0_ohm"] is not None else fit["final"]
    for name in ("R0", "R1", "R2"):
        printed = float(re.search(rf"{name} ([-0-9.]+) mOhm", line).group(1))
        assert printed == pytest.approx(1e3 * f[f"{name.lower()}_ohm"], rel=0.01), (name, line)


def test_sop_backtest_says_when_its_default_ratings_are_not_the_cells(tmp_path, capsys):
    """The rating defaults (20 A / 6 A) are an 18650's: on a 57 Ah cell every limit sat at 0.33 C and the
    back-test scored that cap, with nothing to say so.  Given ratings, or a cell near 3 Ah: no warning."""
    data, table = scaled_cell(tmp_path, 20.0, seconds=900)
    cell = ["--ocv", str(table), "--capacity-ah", "60"]
    assert main(["sop-backtest", str(data), *cell, "--json", str(tmp_path / "a.json")]) == 0
    err = capsys.readouterr().err
    assert "--i-discharge-max-a and --i-charge-max-a not given" in err and "0.33 C / 0.1 C of --capacity-ah 60" in err
    assert main(["sop-backtest", str(data), *cell, "--i-discharge-max-a", "400", "--i-charge-max-a", "120",
                 "--json", str(tmp_path / "b.json")]) == 0
    assert "not given" not in capsys.readouterr().err
    limits = json.loads((tmp_path / "b.json").read_text())["discharge_limit_a"]["model"]
    one, one_table = scaled_cell(tmp_path, 1.0, seconds=900)
    assert main(["sop-backtest", str(one), "--ocv", str(one_table), "--capacity-ah", "3",
                 "--json", str(tmp_path / "c.json")]) == 0
    assert "not given" not in capsys.readouterr().err
    # the limits of the 57 Ah cell are 20 x the 3 Ah cell's (its ratings 20 x too)
    small = json.loads((tmp_path / "c.json").read_text())["discharge_limit_a"]["model"]
    assert limits["median"] == pytest.approx(20.0 * small["median"], rel=1e-6)
