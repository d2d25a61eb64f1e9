"""``bms-estimator sop-backtest``: windows, JSON keys, exit codes, on a recording of a known ECM."""

from __future__ import annotations

import json

import numpy as np
import pytest

from bms_estimator.cli.__main__ import main
from bms_estimator.core.ecm import EcmParams, simulate_ecm
from bms_estimator.data import CellRecording, load_recording, save_recording
from bms_estimator.ocv_table import write_ocv_table
from bms_estimator.sop_backtest import find_pulses, run_backtest

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
    ocv = write_ocv_table(nmc_like_ocv, tmp_path / "ocv.csv")
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


def test_a_drive_cycle_whose_rests_carry_sensor_noise_is_back_tested_as_a_drive_cycle(tmp_path, nmc_like_ocv, capsys):
    """20 mA of current-sensor noise on a 2.5 Ah cell (C/125) crosses the C/50 rest threshold now and then:
    single samples after a rest, not pulses a window can score.  The default mode takes the file for the
    drive cycle it is (before: ten such samples in its final 30 min rest made it an HPPC file, refused with
    "no pulse of the recording is as long as the horizon", exit 2)."""
    q = 2.5
    rng = np.random.default_rng(3)
    levels = np.repeat(rng.uniform(-2.0, 0.5, 200), 30) * q  # a drive: 30 s levels for 100 min
    i = np.concatenate([levels - (levels.mean() + 0.6 * q * 3600 / levels.size), np.zeros(1800)])
    v = simulate_ecm(i, 1.0, EcmParams.from_rc(0.02, [0.01, 0.015], [12.0, 250.0]), nmc_like_ocv.ocv, soc0=0.9,
                     capacity_ah=q, output="mean").voltage_v
    i_meas = i + 0.02 * rng.standard_normal(i.size)
    assert len(find_pulses(i_meas, 1.0, q)) >= 3  # the noise's runs after a rest
    data = tmp_path / "drive.csv"
    np.savetxt(data, np.column_stack([np.arange(i.size, dtype=float), i_meas, v + 2e-3 * rng.standard_normal(i.size),
                                      np.full(i.size, 25.0)]),
               delimiter=",", header="time_s,current_a,voltage_v,temperature_c", comments="", fmt="%.6f")
    ocv = write_ocv_table(nmc_like_ocv, tmp_path / "ocv.csv")
    base = ["sop-backtest", str(data), "--ocv", str(ocv), "--capacity-ah", str(q), "--initial-soc", "0.9"]
    assert main(base + ["--json", "-"]) == 0
    r = json.loads(capsys.readouterr().out)
    assert r["mode"] == "drive" and r["windows"] == (i.size - 1) // 10
    assert main(base + ["--mode", "hppc"]) == 2  # asked for pulses, it has none to score: said so
    assert "no pulse of the recording is as long as the horizon" in capsys.readouterr().err


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


# --- logging gaps: the logger off while the cell was discharged (the Panasonic HPPC files' SOC steps)

GAP_AT_S, GAP_S = 1540.0, 3600.0  # the logger is off over [GAP_AT_S, GAP_AT_S + GAP_S)


def _gap_recording(tmp_path, ocv_curve, *, step_s: float = 0.5, hole: bool = True):
    """Pulses at full, then 1 h without samples in which the cell is discharged 10 % SOC (0.3C for
    20 min, then 40 min at rest), then pulses again; logged every ``step_s`` (written to CSV, loaded
    by load_recording).  Returns (recording, the true SOC at a time: a function)."""
    def pulses():
        out = [np.zeros(300)]
        for c in (0.5, 1.0, 2.0, 1.0):
            out += [np.full(10, -c * Q), np.zeros(300)]
        return np.concatenate(out)

    before = pulses()
    before = np.r_[before, np.zeros(int(GAP_AT_S) - before.size)]
    hidden = np.r_[np.full(1200, -0.3 * Q), np.zeros(2400)]  # 0.3C x 1200 s = 10 % of Q
    i_1s = np.concatenate([before, hidden, pulses()])
    rep = int(round(1.0 / step_s))
    i = np.repeat(i_1s, rep)
    t = np.arange(i.size) * step_s
    sim = simulate_ecm(i, step_s, EcmParams.from_rc(0.03, [0.01, 0.02], [5.0, 100.0]), ocv_curve.ocv, soc0=1.0,
                       capacity_ah=Q)
    keep = ~((t >= GAP_AT_S) & (t < GAP_AT_S + GAP_S)) if hole else np.ones(t.size, dtype=bool)
    path = save_recording(CellRecording(t[keep], i[keep], sim.voltage_v[keep], np.full(keep.sum(), 25.0), "gap"),
                          tmp_path / f"gap_{step_s:g}_{hole}.csv")
    rec = load_recording(path, resample_s=1.0)
    return rec, lambda t_s: float(sim.soc[int(round(t_s / step_s))])


def _run(rec, ocv_curve, **kw):
    return run_backtest(rec.current_a, rec.voltage_v, rec.temperature_c, rec.dt_s, ocv_curve, Q, horizon_s=10.0,
                        initial_soc=1.0, mode="drive", time_s=rec.time_s, unlogged=rec.filled, **kw)


def test_a_logging_gap_is_rested_over_and_no_window_spans_it(tmp_path, nmc_like_ocv):
    """The estimator rests over the hour without samples, as the service does at a time jump, and reads the
    SOC from the OCV at the first sample after it: the hidden 10 % discharge is caught.  Fed the gap as
    load_recording fills it (current held at zero, voltage interpolated), the SOC misses part of it."""
    rec, soc_at = _gap_recording(tmp_path, nmc_like_ocv)
    assert rec.dt_s == 1.0 and np.count_nonzero(rec.filled) == GAP_S  # the hole's bins, marked
    assert np.all(rec.filled[int(GAP_AT_S):int(GAP_AT_S + GAP_S)])
    rested = _run(rec, nmc_like_ocv)
    fed = _run(rec, nmc_like_ocv, rest_over_gaps=False)
    assert rested.logging_gaps == 1 and rested.rested_s == GAP_S
    assert fed.logging_gaps == 0 and fed.windows_across_gaps == 0
    # no scored window starts in the gap, ends in it, or starts at its first sample after it
    s = rested.start_s
    assert not np.any((s > GAP_AT_S - 10.0) & (s <= GAP_AT_S + GAP_S))
    n_gap = np.count_nonzero((fed.start_s > GAP_AT_S - 10.0) & (fed.start_s <= GAP_AT_S + GAP_S))
    assert rested.windows_across_gaps == n_gap and len(s) == len(fed.start_s) - n_gap
    # the SOC at the first window after the gap, against the truth there
    after = lambda res: int(np.flatnonzero(res.start_s > GAP_AT_S + GAP_S)[0])  # noqa: E731
    k_r, k_f = after(rested), after(fed)
    truth = soc_at(rested.start_s[k_r])  # (the grid's time: the file starts at 0)
    assert truth == pytest.approx(1.0 - 0.1 - (0.5 + 1.0 + 2.0 + 1.0) * 10 / 3600, abs=1e-9)
    assert abs(rested.soc[k_r] - truth) < 0.01
    # fed the filled hole (zero current, the voltage interpolated across it), its hour of rest-level samples
    # is read as a park with the gateway awake (core.soc, update) on a voltage nobody measured: 0.5 % off
    # (6.1 % before that reading, the hidden discharge missed), resting over it 0.003 %
    fed_err = fed.soc[k_f] - soc_at(fed.start_s[k_f])
    assert abs(rested.soc[k_r] - truth) < abs(fed_err) < 0.03
    # before the gap the two runs are the same run
    pre = s < GAP_AT_S - 10.0
    np.testing.assert_array_equal(rested.v_pred[pre], fed.v_pred[: np.count_nonzero(pre)])
    # the energy to the end counts the file's own charge only: the same both ways
    np.testing.assert_array_equal(rested.energy_to_end_wh[pre], fed.energy_to_end_wh[: np.count_nonzero(pre)])


def test_a_time_jump_of_a_file_at_its_own_step_is_rested_over_too(tmp_path, nmc_like_ocv):
    """Logged at 1 s, its time axis jumping by the hour: put on the 1 s grid as the same drive logged finer is
    (data.py, "Resampling" 5.), the hour's bins marked unlogged, and rested over the same."""
    rec, soc_at = _gap_recording(tmp_path, nmc_like_ocv, step_s=1.0)
    assert np.count_nonzero(rec.filled) == GAP_S and np.all(rec.filled[int(GAP_AT_S):int(GAP_AT_S + GAP_S)])
    assert np.max(np.diff(rec.time_s)) == 1.0
    res = _run(rec, nmc_like_ocv)
    assert res.logging_gaps == 1 and res.rested_s == GAP_S
    t = rec.time_s[np.round(res.start_s / rec.dt_s).astype(int)]  # (start_s counts samples of dt_s)
    assert not np.any((t > GAP_AT_S - 10.0) & (t <= GAP_AT_S + GAP_S))
    k = int(np.flatnonzero(t > GAP_AT_S + GAP_S)[0])
    assert abs(res.soc[k] - soc_at(t[k])) < 0.01
    assert soc_at(t[k]) < 0.9


def test_without_gaps_the_option_changes_nothing(tmp_path, nmc_like_ocv):
    rec, _ = _gap_recording(tmp_path, nmc_like_ocv, hole=False)
    assert rec.gaps_filled == 0 and not rec.filled.any()
    a, b = _run(rec, nmc_like_ocv), _run(rec, nmc_like_ocv, rest_over_gaps=False)
    assert a.logging_gaps == 0 and a.windows_across_gaps == 0
    for name in ("start_s", "soc", "v_pred", "v_meas", "i_dis_a", "i_chg_a", "energy_left_wh", "energy_to_end_wh",
                 "exceeded"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))


def test_cli_no_rest_over_gaps(tmp_path, nmc_like_ocv, capsys):
    with pytest.raises(SystemExit):
        main(["sop-backtest", "--help"])
    assert "--no-rest-over-gaps" in capsys.readouterr().out
    rec, _ = _gap_recording(tmp_path, nmc_like_ocv)
    ocv = write_ocv_table(nmc_like_ocv, tmp_path / "ocv.csv")
    base = ["sop-backtest", str(tmp_path / "gap_0.5_True.csv"), "--ocv", str(ocv), "--capacity-ah", str(Q),
            "--mode", "drive", "--json", "-"]
    assert main(base) == 0
    rested = json.loads(capsys.readouterr().out)
    assert main(base + ["--no-rest-over-gaps"]) == 0
    fed = json.loads(capsys.readouterr().out)
    assert rested["logging_gaps"] == {"rested": 1, "rested_s": GAP_S, "windows_not_scored": 361}
    assert fed["logging_gaps"]["rested"] == 0 and fed["windows"] == rested["windows"] + 361
