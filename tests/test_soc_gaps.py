"""``soc`` and the SOC matrix over a recording's logging gaps: rested over as the service rests over a time jump.

A synthetic cell (a known 2-RC model) drives for 20 min, parks for 2 h while the logger is off (a hole
in ``time_s``), then drives again for 25 min; logged at 0.5 s and resampled to 1 s by ``load_recording``, the hole's
bins are the recording's ``filled`` ones.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from bms_estimator.analysis import run_soc
from bms_estimator.cli.__main__ import build_parser, main
from bms_estimator.cli.common import load_ocv, soc_config
from bms_estimator.core.ecm import EcmParams, simulate_ecm
from bms_estimator.core.soc import SocConfig, SocEstimator
from bms_estimator.data import CellRecording, load_recording, save_recording
from bms_estimator.gaps import logging_gaps, recording_rest_plan, rest_plan
from bms_estimator.ocv_table import read_ocv_table, write_ocv_table
from bms_estimator.soc_matrix import run_group, start_point

Q = 3.0
STEP_S = 0.5  # logged at 0.5 s: load_recording resamples to 1 s and marks the hole's bins
DRIVE_S = (1200, 1500)  # the two drives' seconds
PARK_AT_S = DRIVE_S[0] + 600.0  # the logger goes off (the drive ended 10 min before: the current held into the hole is zero)
PARK_S = 7200.0  # the 2 h park it does not log
START_SOC = 0.85  # the estimator's start (the cell is full): 15 % off


def _drive(seconds: int, seed: int) -> np.ndarray:
    """1 s levels of a drive: 20-60 s steps of -2C..+0.5C, mostly discharge."""
    rng = np.random.default_rng(seed)
    out = []
    while sum(map(len, out)) < seconds:
        out.append(np.full(int(rng.integers(20, 60)), rng.uniform(-2.0, 0.5) * Q))
    return np.concatenate(out)[:seconds]


@pytest.fixture
def gap_file(tmp_path, nmc_like_ocv):
    """(CSV path, OCV CSV path, truth SOC at a time of the 1 s grid)."""
    i_1s = np.concatenate([_drive(DRIVE_S[0], 1), np.zeros(600), np.zeros(int(PARK_S)), np.zeros(300),
                           _drive(DRIVE_S[1], 2)])
    rep = int(round(1.0 / STEP_S))
    i = np.repeat(i_1s, rep)
    t = np.arange(i.size) * STEP_S
    sim = simulate_ecm(i, STEP_S, EcmParams.from_rc(0.03, [0.01, 0.02], [5.0, 150.0]), nmc_like_ocv.ocv, soc0=1.0,
                       capacity_ah=Q)
    keep = ~((t >= PARK_AT_S) & (t < PARK_AT_S + PARK_S))
    path = save_recording(CellRecording(t[keep], i[keep], sim.voltage_v[keep], np.full(keep.sum(), 25.0), "gap"),
                          tmp_path / "gap.csv")
    return path, write_ocv_table(nmc_like_ocv, tmp_path / "ocv.csv"), lambda t_s: float(sim.soc[int(round(t_s / STEP_S))])


def _soc_args(path, ocv, *extra):
    return ["soc", str(path), "--ocv", str(ocv), "--capacity-ah", str(Q), "--reference-capacity-ah", str(Q),
            "--start-soc", str(START_SOC), *extra]


def test_the_rest_plan_rests_over_what_the_sampler_would_not_bridge():
    unlogged = np.zeros(40, dtype=bool)
    unlogged[5:8] = True  # 3 s: bridged (fed as filled)
    unlogged[20:30] = True  # 10 s: a time jump
    assert logging_gaps(unlogged, 1.0) == [(20, 30)]
    plan = rest_plan(40, 1.0, unlogged=unlogged)
    assert plan.fed[5:8].all() and not plan.fed[20:30].any() and plan.fed[30:].all()
    assert np.flatnonzero(plan.rest_before_s).tolist() == [30] and plan.rest_before_s[30] == 10.0
    assert (plan.gaps, plan.rested_s, plan.not_fed) == (1, 10.0, 10)
    assert plan.first_fed(22) == 30 and plan.first_fed(3) == 3
    # a file at its own step (not resampled): a jump of its time axis is rested over the same way
    t = np.r_[np.arange(10.0), 100.0 + np.arange(10.0)]
    jump = rest_plan(20, 1.0, time_s=t)
    assert jump.fed.all() and jump.rest_before_s[10] == 90.0 and jump.gaps == 1
    assert rest_plan(20, 1.0, time_s=t, rest_over_gaps=False).gaps == 0
    off = rest_plan(40, 1.0, unlogged=unlogged, rest_over_gaps=False)
    assert off.fed.all() and off.gaps == 0
    with pytest.raises(ValueError, match="unlogged has shape"):
        rest_plan(41, 1.0, unlogged=unlogged)


def test_a_coarse_log_bridges_what_the_service_at_its_period_bridges():
    """The service's sampler bridges max(5 s, 2 periods): a 10 s log's one missing record (10 s unlogged) was
    rested over as parked, and the LG la92 drive logged at 10 s with 15 % of its records missing ran its
    capacity estimate to 2.48 Ah (2.83 Ah fed, 2.82 Ah the 0.1 s file's)."""
    unlogged = np.zeros(40, dtype=bool)
    unlogged[5] = True  # one record missing: 10 s, bridged
    unlogged[10:12] = True  # two: 20 s, bridged
    unlogged[20:23] = True  # three: 30 s, a time jump
    plan = rest_plan(40, 10.0, unlogged=unlogged)
    assert plan.fed[:20].all() and not plan.fed[20:23].any() and plan.fed[23:].all()
    assert np.flatnonzero(plan.rest_before_s).tolist() == [23] and plan.rest_before_s[23] == 30.0
    t = np.r_[np.arange(10.0), 13.0 + np.arange(10.0)] * 10.0  # a jump of 30 s in a 10 s time axis: rested
    assert rest_plan(20, 10.0, time_s=t).rest_before_s[10] == 30.0
    t = np.r_[np.arange(10.0), 12.0 + np.arange(10.0)] * 10.0  # of 20 s: bridged
    assert rest_plan(20, 10.0, time_s=t).gaps == 0
    assert rest_plan(40, 1.0, unlogged=unlogged).gaps == 0  # at 1 s, 5 s as before: 1-3 s runs bridged


def test_soc_rests_over_a_logging_gap_as_the_service_does(gap_file, tmp_path, capsys):
    """The 2 h park the file does not log is rested over: the trace keeps every row of the file's time base
    (fed = 0 in the gap, the estimate held), the run is a SocEstimator fed the logged samples with an explicit
    rest(2 h) before the first after the gap, and the SOC there is read from the relaxed voltage."""
    path, ocv_csv, soc_at = gap_file
    rec = load_recording(path, resample_s=1.0)
    k_a, k_b = int(PARK_AT_S), int(PARK_AT_S + PARK_S)  # the hole's bins [k_a, k_b)
    assert rec.dt_s == 1.0 and np.flatnonzero(rec.filled).tolist() == list(range(k_a, k_b))
    trace, out = tmp_path / "rested.csv", tmp_path / "rested.json"
    assert main(_soc_args(path, ocv_csv, "--trace", str(trace), "--json", str(out))) == 0
    assert "rested over 1 logging gaps (2.0 h without samples" in capsys.readouterr().out
    r = json.loads(out.read_text())
    assert r["logging_gaps"] == {"rested": 1, "rested_s": PARK_S, "samples_not_fed": PARK_S,
                                 "reference_held_ah": 0.0}  # the drive ended 10 min before: nothing held
    rows = np.genfromtxt(trace, delimiter=",", names=True)
    assert rows.dtype.names[-1] == "fed"
    np.testing.assert_array_equal(rows["time_s"], rec.time_s)  # every row of the file's time base
    assert np.flatnonzero(rows["fed"] == 0).tolist() == list(range(k_a, k_b))
    assert np.all(rows["soc"][k_a:k_b] == rows["soc"][k_a - 1])  # held

    # the same run by hand: the estimator the command builds, fed the logged samples, rest(2 h) before the next
    args = build_parser().parse_args(_soc_args(path, ocv_csv))
    est = SocEstimator(1, load_ocv(args.ocv, rec, capacity_ah=Q), Q, 1.0, initial_soc=START_SOC,
                       config=soc_config(args).with_(soc_method=args.soc_method))
    by_hand = np.full(len(rec), np.nan)
    for k in range(len(rec)):
        if rec.filled[k]:
            continue
        if k == k_b:
            est.rest(PARK_S)
        est.update(rec.current_a[k], np.array([rec.voltage_v[k]]), temperature_c=np.array([rec.temperature_c[k]]))
        by_hand[k] = est.soc[0]
    fed = ~rec.filled
    np.testing.assert_allclose(rows["soc"][fed], by_hand[fed], rtol=0, atol=2e-6)  # (the trace's 6 digits)

    # the SOC right after the gap: read from the relaxed voltage (the cell at rest), where the truth is
    truth = soc_at(k_b)
    # (measured: 0.69 % off when the logger stopped, held through the gap; 0.001 % after it)
    assert abs(rows["soc"][k_a - 1] - truth) > 0.005 and rows["soc"][k_b - 1] == rows["soc"][k_a - 1]
    assert abs(rows["soc"][k_b] - truth) < 0.001, (rows["soc"][k_b], truth)

    # --no-rest-over-gaps: the gap fed as samples, as before: the run of the estimator over every sample
    old_trace, old_out = tmp_path / "fed.csv", tmp_path / "fed.json"
    assert main(_soc_args(path, ocv_csv, "--no-rest-over-gaps", "--trace", str(old_trace), "--json",
                          str(old_out))) == 0
    old = np.genfromtxt(old_trace, delimiter=",", names=True)
    assert (old["fed"] == 1).all() and json.loads(old_out.read_text())["logging_gaps"]["rested"] == 0
    ocv = load_ocv(args.ocv, rec, capacity_ah=Q)
    before = run_soc(rec.current_a, rec.voltage_v, ocv, Q, START_SOC, 1.0,
                     soc_config(args).with_(soc_method=args.soc_method), temperature_c=rec.temperature_c)
    np.testing.assert_allclose(old["soc"], before.soc, rtol=0, atol=2e-6)
    # the two agree up to the gap and part there (by more than the trace's digits)
    np.testing.assert_array_equal(old["soc"][:k_a], rows["soc"][:k_a])
    assert np.max(np.abs(old["soc"][k_b:] - rows["soc"][k_b:])) > 1e-3


def test_a_start_inside_a_gap_begins_at_the_next_logged_sample(gap_file, tmp_path, capsys):
    path, ocv_csv, _ = gap_file
    out = tmp_path / "late.json"
    assert main(_soc_args(path, ocv_csv, "--start-s", str(PARK_AT_S + 100.0), "--json", str(out))) == 0
    err = capsys.readouterr().err
    assert "lies in a logging gap" in err and f"{PARK_AT_S + PARK_S:.0f} s" in err
    r = json.loads(out.read_text())
    assert r["start_s"] == PARK_AT_S + PARK_S  # (start_soc: the estimate after that first sample)
    assert r["logging_gaps"] == {"rested": 0, "rested_s": 0.0, "samples_not_fed": 0,
                                 "reference_held_ah": 0.0}  # nothing left to rest over


def test_the_matrix_rests_a_recordings_starts_over_its_gaps(gap_file):
    """run_group's cells of a recording with a gap: not fed inside it, rested before the sample after it,
    as soc's run; a mid-file start inside the gap moves to the next logged sample; a file without gaps in the
    same group runs as before."""
    path, ocv_csv, _ = gap_file
    rec = load_recording(path, resample_s=1.0)
    plain = CellRecording(np.arange(len(rec), dtype=float), rec.current_a, rec.voltage_v, rec.temperature_c, "plain")
    ocv = load_ocv(ocv_csv, rec)
    cfg = SocConfig()
    plan = recording_rest_plan(rec)
    base = np.linspace(1.0, 0.3, len(rec))
    k_mid, s_mid = start_point("at40-5", base, plan.fed)  # 40 % of the file lies in the gap
    assert not plan.fed[int(0.4 * len(rec))] and k_mid == int(PARK_AT_S + PARK_S)
    assert s_mid == pytest.approx(base[k_mid] - 0.05)
    starts = [(0, START_SOC), (k_mid, s_mid), (0, START_SOC)]
    run = run_group([rec, rec, plain], starts, ocv, Q, cfg)
    for c, (k0, s0) in enumerate(starts[:2]):
        alone = run_soc(rec.current_a, rec.voltage_v, ocv, Q, s0, 1.0, cfg, temperature_c=rec.temperature_c,
                        start_index=k0, rest_s=plan.rest_before_s, fed=plan.fed)
        np.testing.assert_allclose(run.soc[:, c], alone.soc, rtol=0, atol=1e-9)
    fed_alone = run_soc(plain.current_a, plain.voltage_v, ocv, Q, START_SOC, 1.0, cfg,
                        temperature_c=plain.temperature_c)
    np.testing.assert_allclose(run.soc[:, 2], fed_alone.soc, rtol=0, atol=1e-9)
    # without rest_over_gaps the recording's gap is fed: its full start is then the plain file's run
    old = run_group([rec, plain], [(0, START_SOC), (0, START_SOC)], ocv, Q, cfg, rest_over_gaps=False)
    np.testing.assert_allclose(old.soc[:, 0], old.soc[:, 1], rtol=0, atol=1e-9)
    assert np.max(np.abs(old.soc[:, 0] - run.soc[:, 0])) > 1e-3
    with pytest.raises(ValueError, match="lies in a logging gap"):
        run_group([rec], [(int(PARK_AT_S) + 5, 0.5)], ocv, Q, cfg)


def _one_drive_two_steps(tmp_path):
    """The same 75 min drive (2-RC cell, the LG HG2 sample's table) logged at 0.1 s and at 1 s (its bin means):
    holes of 3 s at 1000 s and 60 s at 2000 s with current flowing, 60 s at 3000 s at rest; a final 15 min rest."""
    from bms_estimator.samples import ocv_table

    ocv = read_ocv_table(ocv_table("lg-hg2"))
    dt, n = 0.1, 45000
    t = np.arange(n) * dt
    i = np.repeat(np.random.default_rng(3).uniform(-3.5, 1.5, n // 100 + 1), 100)[:n]
    i[((t >= 2990) & (t < 3080)) | (t >= 3600)] = 0.0
    sim = simulate_ecm(i, dt, EcmParams.from_rc(0.03, [0.01, 0.015], [10.0, 200.0]), ocv.ocv, soc0=1.0,
                       capacity_ah=2.8, output="mean")
    v = sim.voltage_v - ocv.hysteresis(sim.soc)
    keep = ~(((t >= 1000) & (t < 1003)) | ((t >= 2000) & (t < 2060)) | ((t >= 3000) & (t < 3060)))
    fine = tmp_path / "drive_0p1s.csv"
    save_recording(CellRecording(time_s=t[keep], current_a=i[keep], voltage_v=v[keep],
                                 temperature_c=np.full(keep.sum(), 25.0)), fine)
    r = load_recording(fine)
    coarse = tmp_path / "drive_1s.csv"
    save_recording(CellRecording(time_s=r.time_s[~r.filled], current_a=r.current_a[~r.filled],
                                 voltage_v=r.voltage_v[~r.filled], temperature_c=r.temperature_c[~r.filled]), coarse)
    return fine, coarse, str(ocv_table("lg-hg2"))


def test_a_01_s_and_a_1_s_log_of_one_drive_count_its_gaps_alike(tmp_path, capsys):
    """The 1 s log's holes were steps of its time axis: its reference skipped the holes' held charge (Q_ref
    2.7596 against 2.7877 Ah: the reference up to 0.14 % SOC apart), its 3 s hole was not fed (the 0.1 s log
    feeds it as the sampler's stale samples), its trace had 123 rows fewer, the SOC was up to 0.31 % apart and
    the RMSE from 30 min 0.113 against 0.108 %. Now it is put on the grid as the 0.1 s log is: the same rows,
    fed flags and rests, the reference within 0.0002 % and the SOC within 0.0004 % (the 1 s file's 5-decimal
    rounding); and both say once that the reference cannot know the 60 s gap's charge (-0.25 % SOC held; the
    gap at rest holds none and is not named)."""
    fine, coarse, table = _one_drive_two_steps(tmp_path)
    runs, errs = {}, {}
    for f in (fine, coarse):
        trace, out = tmp_path / f"{f.stem}.trace.csv", tmp_path / f"{f.stem}.json"
        assert main(["soc", str(f), "--ocv", table, "--capacity-ah", "2.8", "--trace", str(trace),
                     "--json", str(out)]) == 0
        errs[f] = capsys.readouterr().err
        runs[f] = (np.genfromtxt(trace, delimiter=",", names=True), json.loads(out.read_text()))
    (a, ja), (b, jb) = runs[fine], runs[coarse]
    assert a.size == b.size == 4500
    for col in ("time_s", "fed"):
        np.testing.assert_array_equal(a[col], b[col], err_msg=col)
    for col in ("soc_reference", "soc_counted"):  # the trace's 6 digits, the 1 s file's 5-decimal current
        np.testing.assert_allclose(a[col], b[col], rtol=0, atol=1e-5, err_msg=col)
    np.testing.assert_allclose(a["soc"], b["soc"], rtol=0, atol=2e-5)
    assert ja["logging_gaps"] == jb["logging_gaps"]
    assert ja["logging_gaps"]["rested"] == 2 and ja["logging_gaps"]["samples_not_fed"] == 120
    assert ja["capacity_ah_reference"] == pytest.approx(jb["capacity_ah_reference"], rel=2e-5)  # before: 2.5e-4 apart
    for f, err in errs.items():
        assert err.count("warning:") == 1, err
        assert (f"{f.name}: the reference cannot know the charge inside 1 logging gap(s) the estimator rests over"
                in err and "over the 60 s gap at 2000 s" in err), err
    assert errs[fine].replace(fine.name, "") == errs[coarse].replace(coarse.name, "")
