"""``batch --sox``: the service's SOP/SOE/SOH per cell, carried across chained drives, in the summary.

Drives: slices of the shipped LG HG2 UDDS recording (one-cell CSV recordings, as ``batch``
reads them), cut where the cell is inside the resistance SOH's SOC band (0.3..0.8), so that
the resistance SOH is defined within a drive; the whole 4.4 h recording for the capacity SOH
(justified only once the capacity estimate's uncertainty has halved). That the per-cell SOX
outputs are the service's, bit for bit, is tests/fleet/test_fleet_equivalence.py; so are the
pack figures (``pack_outputs``, the pack payload's) checked there, here their summary and files.
"""

from __future__ import annotations

import csv
import dataclasses
import gzip
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest

from bms_estimator.core.sox import SoxEstimator
from bms_estimator.data import load_recording
from bms_estimator.fleet.batch import PACK_SUMMARY_COLUMNS, SOX_SUMMARY_COLUMNS, summary_rows
from bms_estimator.fleet.drive import _pack_summary, run_drive, run_drives, run_vehicle, service_for
from bms_estimator.fleet.estimate import carry_state, estimate_drive, rest_between_drives
from bms_estimator.fleet.samples import SampleArrays
from bms_estimator.service.state import load_state, resume_sox, save_state

from .fleet_helpers import write_batch_config
from .test_fleet_stack import _assert_same_table

ROOT = Path(__file__).parents[2]
SAMPLE = ROOT / "bms_estimator" / "samples" / "lg-hg2_25degC_udds_1s.csv.gz"
SLICES = ((3000, 5500), (5500, 8000))  # rows (seconds) of the recording: SOC about 0.75 -> 0.55


@pytest.fixture(scope="module")
def slices(tmp_path_factory):
    d = tmp_path_factory.mktemp("fleet-sox")
    lines = gzip.open(SAMPLE, "rt").read().splitlines()
    head, rows = lines[0], [r.split(",") for r in lines[1:]]
    logs = []
    for k, (a, b) in enumerate(SLICES):
        out = d / "car1" / f"drive{k}.csv"
        out.parent.mkdir(exist_ok=True)
        t0 = float(rows[a][0])
        out.write_text(head + "\n" + "\n".join(",".join([f"{float(r[0]) - t0:g}", *r[1:]]) for r in rows[a:b]) + "\n")
        logs.append(out)
    return d, logs, write_batch_config(d, 1, "fleet-sox")


@pytest.fixture(scope="module")
def first_drive(slices, tmp_path_factory):
    """run_drive of the first slice with the SOX part: (result, state, estimates), read by three tests."""
    d, logs, cfg = slices
    return run_drive(logs[0], str(cfg), tmp_path_factory.mktemp("first-drive"), "car1", sox=True)


def _column(parquet: str, key: str) -> np.ndarray:
    return pq.read_table(parquet).column(key).to_numpy()


def test_chained_drives_carry_the_soh_and_the_energy_across_drives(slices, first_drive, tmp_path):
    d, logs, cfg = slices
    chained = run_vehicle([str(p) for p in logs], str(cfg), tmp_path / "chained", "car1", sox=True)
    alone = run_vehicle([str(p) for p in logs], str(cfg), tmp_path / "alone", "car1", sox=True, chain=False)
    assert [r.status for r in chained + alone] == ["ok"] * 4
    # drive 2 alone commissions its R0 again: no resistance SOH for its first 600 s in the SOC band;
    # chained it has drive 1's commissioning R0 from its first sample on
    soh_alone = _column(alone[1].parquet, "soh_resistance")
    soh_chained = _column(chained[1].parquet, "soh_resistance")
    assert np.isnan(soh_alone[:600]).all() and np.isfinite(soh_alone[-1])  # finite from 750 s on
    assert np.isfinite(soh_chained).all()
    soh1 = chained[0].cells["soh_resistance_final"][0]
    assert 0.8 < soh1 < 1.2 and soh_chained[0] == pytest.approx(soh1, rel=0.01)
    # the counters go on: drive 2's Wh out starts where drive 1's ended; the summary has each drive's own
    out1 = _column(chained[0].parquet, "energy_discharged_wh")
    out2 = _column(chained[1].parquet, "energy_discharged_wh")
    assert out2[0] >= out1[-1] > 0
    assert chained[1].cells["energy_discharged_wh"][0] == pytest.approx(out2[-1] - out1[-1], rel=1e-9)
    # the energy of a drive does not depend on the state it starts from (up to the counter's rounding)
    assert chained[1].cells["energy_discharged_wh"] == pytest.approx(alone[1].cells["energy_discharged_wh"], rel=1e-9)
    assert 0 < chained[1].cells["energy_charged_wh"][0] < chained[1].cells["energy_discharged_wh"][0]
    # the carried state is the daemon's state file: saved and loaded, it resumes drive 2 the same
    _, state1, _ = first_drive
    assert any(k.startswith("sox.") for k in state1)
    save_state(tmp_path / "state.npz", state1, {"pack_id": "car1", "n_cells": 1})
    loaded = load_state(tmp_path / "state.npz", pack_id="car1", n_cells=1, max_age_s=None)
    _, _, est2 = run_drive(logs[1], str(cfg), tmp_path / "x", "car1", dict(loaded), sox=True)
    for key in est2.sox_keys + ("soc",):
        assert np.array_equal(est2.cells[key].reshape(-1), _column(chained[1].parquet, key), equal_nan=True), key


def test_the_carried_sox_state_is_rested_over_the_gap(slices, first_drive):
    d, logs, cfg = slices
    _, state, _ = first_drive
    svc = service_for(str(cfg), n_cells=1)
    samples = SampleArrays.from_recording(load_recording(logs[1]), 1.0)
    before = np.asarray(state["sox.mean_current_a"], dtype=float)
    assert np.all(np.abs(before) > 0)
    epoch = 1.7e9  # the drive's samples on epoch times: its logs carry absolute times
    shifted = dataclasses.replace(samples, t_s=samples.t_s + epoch)
    est = carry_state(svc._new_estimator, state)
    sox = resume_sox(svc._new_sox, state)
    gap, what = rest_between_drives(est, epoch - 1800.0, shifted, sox)
    assert gap == pytest.approx(1800.0) and "rested" in what
    tau = svc.cfg.estimator.sox_config.soe.mean_current_tau_s
    assert np.allclose(sox.mean_current_a, before * math.exp(-1800.0 / tau), rtol=1e-12)


def test_summary_has_the_soh_columns_finite_where_defined(slices, tmp_path):
    d, logs, cfg = slices
    res, state, est = run_drive(SAMPLE, str(cfg), tmp_path, "lg", sox=True)  # 4.4 h: the capacity is estimated
    assert res.status == "ok" and bool(state["capacity_estimated"][0])
    rows = summary_rows([res], sox=True)
    assert set(SOX_SUMMARY_COLUMNS) <= set(rows[0])
    row = rows[0]
    for key in SOX_SUMMARY_COLUMNS:
        assert math.isfinite(row[key]), key
    assert 0.8 < row["soh_capacity_final"] < 1.1 and 0 < row["soh_capacity_sigma_final"] < 0.1
    assert row["soh_capacity_final"] == pytest.approx(est.cells["capacity_ah"][-1, 0] / 3.0, rel=1e-12)
    assert 0.5 < row["soh_resistance_final"] < 1.5
    # undefined until the capacity is justified: NaN before, then finite to the end
    soh = est.cells["soh_capacity"][:, 0]
    first = int(np.flatnonzero(np.isfinite(soh))[0])
    assert first > 600 and np.isnan(soh[:first]).all() and np.isfinite(soh[first:]).all()
    # the energy left at the end of a drive to 6 % SOC is a small part of the 10.8 Wh cell; out > in
    assert 0 <= row["energy_left_wh_final"] < 1.5 and row["energy_discharged_wh"] > row["energy_charged_wh"] > 0
    # without sox: the summary's columns as before (on the shorter drive: the columns do not hang on its length)
    plain, _, _ = run_drive(logs[0], str(cfg), tmp_path, "car1", write=False)
    assert not set(SOX_SUMMARY_COLUMNS) & set(summary_rows([plain])[0])


def test_pack_summary_is_the_pack_series_finite_where_defined(slices, first_drive):
    d, logs, cfg = slices
    res, _, est = first_drive  # 2500 s in the resistance SOH's band
    rows = summary_rows([res], sox=True)
    assert len(rows) == 1 and tuple(rows[0])[-len(PACK_SUMMARY_COLUMNS):] == PACK_SUMMARY_COLUMNS
    row = rows[0]
    for key in PACK_SUMMARY_COLUMNS:
        # the capacity SOH is not justified within 42 min (as the cell's, NaN); every other figure is
        assert math.isfinite(row[key]) == (key != "pack_soh_capacity_min_final"), key
    # the finals are the pack series' last values, the least limit its minimum over the samples
    assert row["pack_energy_left_wh_final"] == est.pack["energy_left_wh"][-1] > 0
    assert row["pack_soh_resistance_max_final"] == est.pack["soh_resistance_max"][-1]
    for key in ("i_discharge_max_10s_a", "p_discharge_max_10s_w"):
        series = est.pack[key]
        assert np.isfinite(series).all() and row[f"pack_{key}_min"] == series.min() > 0
    # the current limit sits at the cell's discharge rating (25 degC: not derated) on this drive; the power
    # limit moves with the SOC: its least is not its last
    sop = service_for(str(cfg), n_cells=1).cfg.estimator.sox_config.sop
    power = est.pack["p_discharge_max_10s_w"]
    assert row["pack_p_discharge_max_10s_w_min"] < power[-1]
    assert row["pack_i_discharge_max_10s_a_min"] == sop.i_discharge_max_a * sop.n_parallel
    # one cell, one string: the pack's energy is the cell's; a fresh drive's counter is the drive's energy out
    assert row["pack_energy_discharged_wh"] == res.cells["energy_discharged_wh"][0]
    assert row["pack_energy_charged_wh"] == res.cells["energy_charged_wh"][0] > 0
    assert row["pack_energy_discharged_wh"] == pytest.approx(est.pack["energy_discharged_wh"][-1], rel=1e-12)
    table = pq.read_table(res.pack_parquet)
    assert res.pack_parquet.endswith("drive0.csv.pack.parquet") and table.num_rows == len(est)
    assert table.column_names == ["t_s", "current_a", *est.pack] and list(est.pack) == list(
        service_for(str(cfg), n_cells=1)._new_sox().pack_output_keys)


def test_pack_figures_are_nan_before_the_first_update(slices):
    d, logs, cfg = slices
    svc = service_for(str(cfg), n_cells=1)
    samples = SampleArrays.from_recording(load_recording(logs[0]), 1.0)
    late = np.ones(len(samples), dtype=bool)
    late[:50] = False  # no valid current for the first 50 samples: the service does not update there
    for current_valid in (late, np.zeros(len(samples), dtype=bool)):
        drive = dataclasses.replace(samples, current_valid=current_valid)
        est = estimate_drive(drive, svc._new_estimator(), sox=svc._new_sox())
        first = int(np.argmax(current_valid)) if current_valid.any() else len(est)
        for key, series in est.pack.items():
            assert np.isnan(series[:first]).all(), key
        assert np.isfinite(est.pack["i_discharge_max_10s_a"][first:]).all()
        figures = _pack_summary(est)
        if current_valid.any():
            assert math.isfinite(figures["pack_i_discharge_max_10s_a_min"])
            assert figures["pack_energy_discharged_wh"] > 0
        else:  # never updated: no figure, and no energy moved
            assert all(math.isnan(v) for k, v in figures.items() if "energy_d" not in k and "energy_c" not in k)
            assert figures["pack_energy_discharged_wh"] == figures["pack_energy_charged_wh"] == 0.0


def test_one_cell_sox_drives_stacked_write_what_run_drive_writes(slices, tmp_path):
    """batch --sox's task on single-cell recordings: the one-cell drives run stacked (fleet/stack.py), and
    each drive's Parquet, pack Parquet, summary and pack summary are those run_drive writes for it alone,
    no tolerance. (The stacked arithmetic itself: tests/fleet/test_fleet_stack.py.)"""
    d, logs, cfg = slices
    results = run_drives([(str(p), "car1") for p in logs], str(cfg), tmp_path / "group", sox=True)
    assert [r.counters.get("stacked_with") for r in results] == [2, 2]
    for log, res in zip(logs, results):
        solo, _, est = run_drive(log, str(cfg), tmp_path / "solo", "car1", sox=True)
        table = pq.read_table(res.parquet)
        _assert_same_table(table, pq.read_table(solo.parquet))
        assert set(est.sox_keys) <= set(table.column_names)
        _assert_same_table(pq.read_table(res.pack_parquet), pq.read_table(solo.pack_parquet))
        assert res.cells.keys() == solo.cells.keys()
        for key, values in solo.cells.items():
            assert np.array_equal(res.cells[key], values, equal_nan=True), key
        assert res.pack.keys() == solo.pack.keys() and len(res.pack) == len(PACK_SUMMARY_COLUMNS)
        for key, value in solo.pack.items():
            assert np.array_equal(res.pack[key], value, equal_nan=True), key


def test_cli_batch_sox_writes_the_soh_columns(slices, tmp_path):
    d, logs, cfg = slices
    out = tmp_path / "out"
    proc = subprocess.run([sys.executable, "-m", "bms_estimator.cli", "batch", str(d / "car1"), "--config", str(cfg),
                           "--out", str(out), "--chain", "--sox", "--workers", "1", "--no-progress"],
                          capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert proc.returncode == 0, proc.stderr[-2000:]
    with (out / "summary.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    assert [r["drive"] for r in rows] == ["drive0.csv", "drive1.csv"]
    for r in rows:
        for key in ("soh_resistance_final", "energy_left_wh_final", "energy_discharged_wh", "energy_charged_wh"):
            assert math.isfinite(float(r[key])), key
        assert r["soh_capacity_final"] in ("", "nan")  # not justified within these drives
    parquet = out / "drives" / "car1" / "drive1.csv.parquet"
    assert {"i_discharge_max_10s_a", "i_charge_max_10s_a", "energy_left_wh", "soh_capacity",
            "soh_resistance"} <= set(pq.read_table(parquet).column_names)
    # the pack figures: per drive in the summary, per sample beside each drive's Parquet
    for r in rows:
        for key in PACK_SUMMARY_COLUMNS:
            assert math.isfinite(float(r[key])) == (key != "pack_soh_capacity_min_final"), key
    pack = pq.read_table(out / "drives" / "car1" / "drive1.csv.pack.parquet")
    assert float(rows[1]["pack_energy_left_wh_final"]) == pack.column("energy_left_wh").to_numpy()[-1]
    assert {"t_s", "i_discharge_max_10s_a", "p_charge_max_2s_w", "energy_left_wh", "soh_capacity_min",
            "soh_resistance_max", "time_to_empty_s"} <= set(pack.column_names)
    assert sorted(p.name for p in (out / "drives" / "car1").glob("*.pack.parquet")) == [
        "drive0.csv.pack.parquet", "drive1.csv.pack.parquet"]
    assert pq.read_table(out / "summary.parquet").column_names[-len(PACK_SUMMARY_COLUMNS):] == list(
        PACK_SUMMARY_COLUMNS)


def test_output_keys_are_the_outputs_after_the_first_update(slices):
    svc = service_for(str(slices[2]), n_cells=3)
    est, sox = svc._new_estimator(), svc._new_sox()
    assert isinstance(sox, SoxEstimator) and sox.outputs == {} and sox.pack_outputs() == {}
    est.update(-1.0, np.full(3, 3.9), np.ones(3, bool), temperature_c=np.full(3, 25.0))
    sox.update(est, -1.0, np.full(3, 3.9), np.ones(3, bool))
    assert tuple(sox.outputs) == sox.output_keys
    # the pack's keys (batch's pack Parquet columns), in pack_outputs' order; its energy counts every cell
    assert tuple(sox.pack_outputs()) == sox.pack_output_keys and len(sox.pack_output_keys) == 3 * 4 + 7
    pack = sox.pack_outputs()
    assert pack["energy_discharged_wh"] == sox.pack_energy_wh(sox.outputs["energy_discharged_wh"]) > 0
    assert sox.pack_energy_wh(np.array([1.0, 2.0, 3.5])) == 6.5 * sox.config.sop.n_parallel
    assert "energy_charged_wh" in sox.state_dict() and "energy_charged_wh" not in sox.outputs
