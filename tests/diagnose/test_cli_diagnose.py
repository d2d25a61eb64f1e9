"""``bms-estimator diagnose`` on a shipped sample: JSON, report folder, bad input."""

from __future__ import annotations

import json

from bms_estimator.cli.__main__ import main
from bms_estimator.diagnose import CAUSES
from bms_estimator.samples import drive_cycle, ocv_table


def test_diagnose_command_writes_json_and_report(tmp_path, capsys):
    out, rep = tmp_path / "d.json", tmp_path / "report"
    rc = main(["diagnose", str(drive_cycle("lg-hg2", "la92")), "--ocv", str(ocv_table("lg-hg2")),
               "--capacity-ah", "3.0", "--json", str(out), "--report", str(rep), "--soc-min", "0.1"])
    assert rc == 0
    d = json.loads(out.read_text())
    assert d["cause"] in CAUSES + ("none",)
    assert {c["cause"] for c in d["candidates"]} == set(CAUSES)
    assert d["extended_rmse_mv"] <= d["baseline_rmse_mv"]
    assert d["lif"]["sim_rmse_mv"] > 0  # the LIF identification ran (warm start)
    for f in ("report.md", "residual.png", "voltage.png", "candidates.png"):
        assert (rep / f).stat().st_size > 1000
    text = (rep / "report.md").read_text()
    assert f"**Cause: `{d['cause']}`**" in text
    assert "cause:" in capsys.readouterr().out


def test_diagnose_rejects_an_unknown_cause(capsys):
    rc = main(["diagnose", str(drive_cycle("lg-hg2", "la92")), "--ocv", str(ocv_table("lg-hg2")),
               "--capacity-ah", "3.0", "--causes", "hysteresis,gremlins"])
    assert rc == 2
    assert "gremlins" in capsys.readouterr().err


def test_diagnose_refuses_an_empty_list_of_causes(capsys):
    """'--causes ""' fitted the baseline alone and named its cause 'none', exit 0."""
    rc = main(["diagnose", str(drive_cycle("lg-hg2", "la92")), "--ocv", str(ocv_table("lg-hg2")),
               "--capacity-ah", "3.0", "--causes", ""])
    assert rc == 2
    assert "--causes '' names no cause; choose from hysteresis" in capsys.readouterr().err
