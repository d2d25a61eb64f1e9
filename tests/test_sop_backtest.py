"""``bms-estimator sop-backtest``: windows, JSON keys, exit codes, on a recording of a known ECM."""

from __future__ import annotations

import json

import numpy as np
import pytest

from bms_estimator.cli.__main__ import main
from bms_estimator.core.ecm import EcmParams, simulate_ecm
from bms_estimator.sop_backtest import find_pulses

Q = 3.0


def _recording(tmp_path, nmc_like_ocv, pulses: int = 12):
    """HPPC-like: 10 s pulses of 0.5-3C after 300 s rests, and a 1C discharge step every 4 pulses."""
    parts = [np.zeros(300)]
    for k in range(pulses):
        parts += [np.full(10, -(0.5 + 0.5 * (k % 4)) * Q), np.zeros(300)]
        if k % 4 == 3:
            parts += [np.full(600, -Q), np.zeros(300)]
    i = np.concatenate(parts)
    sim = simulate_ecm(i, 1.0, EcmParams.from_rc(0.03, [0.01, 0.02], [5.0, 100.0]), nmc_like_ocv.ocv, soc0=1.0,
                       capacity_ah=Q)
    data = tmp_path / "pulses.csv"
    np.savetxt(data, np.column_stack([np.arange(len(i), dtype=float), i, sim.voltage_v, np.full(len(i), 25.0)]),
               delimiter=",", header="time_s,current_a,voltage_v,temperature_c", comments="", fmt="%.6f")
    ocv = nmc_like_ocv.to_csv(tmp_path / "ocv.csv")
    return data, ocv, i


def test_pulses_are_found():
    i = np.concatenate([np.zeros(100), np.full(10, -3.0), np.zeros(100), np.full(200, -3.0), np.zeros(70),
                        np.full(5, 2.0), np.zeros(3)])
    assert find_pulses(i, 1.0, Q) == [(100, 110), (480, 485)]  # the 200 s step is no pulse


def test_backtest_on_a_known_ecm_scores_every_pulse_and_every_window(tmp_path, nmc_like_ocv, capsys):
    data, ocv, i = _recording(tmp_path, nmc_like_ocv)
    out = tmp_path / "bt.json"
    assert main(["sop-backtest", str(data), "--ocv", str(ocv), "--capacity-ah", str(Q), "--horizon-s", "10",
                 "--json", str(out)]) == 0
    r = json.loads(out.read_text())
    assert r["mode"] == "hppc" and r["windows"] == 12 == r["windows_loaded"]
    assert set(r["voltage_error_mv"]) == {"median", "p95"}
    assert 0.0 <= r["voltage_error_mv"]["median"] <= r["voltage_error_mv"]["p95"]
    # the data is the model's own: once identified, the 10 s prediction is within a few mV
    assert r["voltage_error_mv"]["median"] < 10.0
    assert r["limit_exceeded_pct"] == 0.0 and r["windows_within_limit"] == 12
    assert "12 hppc windows of 10 s" in capsys.readouterr().out
    # a drive cycle's windows: every 10 s of the file
    assert main(["sop-backtest", str(data), "--ocv", str(ocv), "--capacity-ah", str(Q), "--mode", "drive",
                 "--json", "-"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["mode"] == "drive" and d["windows"] == (len(i) - 1) // 10
    # a cut-off the cell does cross while the model allowed the current: counted as exceeded
    assert main(["sop-backtest", str(data), "--ocv", str(ocv), "--capacity-ah", str(Q), "--v-min", "3.9",
                 "--json", "-"]) == 0
    strict = json.loads(capsys.readouterr().out)
    assert strict["windows_within_limit"] < 12  # the limit shrank where the cell came close to 3.9 V


def test_bad_input_exit_codes(tmp_path, nmc_like_ocv, capsys):
    data, ocv, _ = _recording(tmp_path, nmc_like_ocv, pulses=4)
    base = ["sop-backtest", str(data), "--ocv", str(ocv), "--capacity-ah", str(Q)]
    assert main(base + ["--v-min", "4.3"]) == 2
    assert "--v-min" in capsys.readouterr().err
    assert main(base + ["--horizon-s", "100000"]) == 2
    assert main(["sop-backtest", str(tmp_path / "missing.csv"), "--ocv", str(ocv), "--capacity-ah", "3"]) == 3
    bad = tmp_path / "bad.csv"
    bad.write_text("time_s,current_a,voltage_v\n0,x,3.7\n")
    assert main(["sop-backtest", str(bad), "--ocv", str(ocv), "--capacity-ah", "3"]) == 3
    err = capsys.readouterr().err
    assert "Traceback" not in err and "bad.csv" in err


def test_a_long_run_says_at_its_start_that_it_takes_a_while(tmp_path, nmc_like_ocv, capsys, monkeypatch):
    """27 h of HPPC ran 2 min 18 s without a word; a run of LONG_RUN_SAMPLES or more now says so first."""
    import bms_estimator.cli.sop_backtest as cmd

    data, ocv, i = _recording(tmp_path, nmc_like_ocv, pulses=4)
    base = ["sop-backtest", str(data), "--ocv", str(ocv), "--capacity-ah", str(Q)]
    assert main(base) == 0
    assert "this takes minutes" not in capsys.readouterr().err  # a short file: no note
    monkeypatch.setattr(cmd, "LONG_RUN_SAMPLES", len(i))
    assert main(base) == 0
    err = capsys.readouterr().err
    assert f"bms-estimator sop-backtest: {len(i):,} samples" in err and "this takes minutes" in err


def test_sox_figures_without_the_data_set_writes_nothing(tmp_path):
    """On a clone without ../shared/data, scripts/sox_figures.py overwrote the committed SOX tables and figures
    with empty ones and exited 0. Now it says where it looked and writes nothing (exit 2)."""
    import subprocess
    import sys
    from pathlib import Path

    repo = Path(__file__).resolve().parents[1]
    out = tmp_path / "sox"
    res = subprocess.run([sys.executable, str(repo / "scripts" / "sox_figures.py"), "--data", str(tmp_path / "none"),
                          "--out", str(out)], capture_output=True, text=True, timeout=120)
    assert res.returncode == 2, res.stderr
    assert f"no Panasonic files under {tmp_path / 'none' / 'panasonic-18650pf'}" in res.stderr
    assert not (out / "sox_tables.md").exists() and not (out / "hppc_error.png").exists()
