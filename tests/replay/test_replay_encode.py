"""encode-log: frame rates, cell 0 = measured, other cells = the truth JSON, charge, formats."""

from __future__ import annotations

import math
from collections import defaultdict
from dataclasses import replace
from pathlib import Path

import can
import numpy as np
import pytest
from replay_helpers import CELL, CYCLE, DURATION_S, N_CELLS, SEED

from bms_estimator.analysis import lookup_params
from bms_estimator.can.dbc import load_project_db
from bms_estimator.cli.__main__ import main
from bms_estimator.data import CellRecording, load_recording, save_recording
from bms_estimator.ocv_table import read_ocv_table
from bms_estimator.replay.encode_log import (
    CellSpread,
    build_pack,
    draw_cell_truths,
    frame_arrays,
    identify_cell_model,
    pack_voltages,
    parse_spread,
    truths_from_json,
)
from bms_estimator.samples import drive_cycle, ocv_table

V_STEP = 1e-4  # DBC cell voltage step, V
EPS = 1e-9


def _decode_log(path: Path) -> dict:
    """Decoded log: per message name, lists of (t, signals)."""
    db = load_project_db()
    out: dict[str, list] = defaultdict(list)
    ext = set()
    for msg in can.LogReader(str(path)):
        m = db.get_message_by_frame_id(msg.arbitration_id)
        ext.add(msg.is_extended_id)
        out[m.name].append((msg.timestamp, m.decode(bytes(msg.data), decode_choices=True)))
    out["_extended"] = ext
    return out


@pytest.fixture(scope="module")
def decoded(encoded):
    return _decode_log(encoded["log"])


@pytest.fixture(scope="module")
def measured():
    rec = load_recording(drive_cycle(CELL, CYCLE))
    n = DURATION_S
    return rec, rec.current_a[:n], rec.voltage_v[:n], rec.temperature_c[:n]


@pytest.fixture(scope="module")
def cell_voltages(decoded):
    """(t, cell) -> decoded voltage, as an array (600 s x 10 rounds, N cells)."""
    rounds = DURATION_S * 10
    v = np.full((rounds, N_CELLS), np.nan)
    t = np.full((rounds, N_CELLS), np.nan)
    for ts, sig in decoded["CellVoltages"]:
        r = int(math.floor(ts * 10 + 1e-9))
        for j in range(3):
            cell = sig["CellIndexBase"] + j
            if cell < N_CELLS:
                v[r, cell] = sig[f"CellVoltage{j}"]
                t[r, cell] = ts
    return t, v


def test_frame_rates_per_message_and_mux(decoded):
    assert decoded["_extended"] == {True}
    cur = np.array([t for t, _ in decoded["PackMeasurement"]])
    assert len(cur) == DURATION_S * 100
    np.testing.assert_allclose(np.diff(cur), 0.01, atol=1e-6)
    for name, per_frame, period in (("CellVoltages", 3, 0.1), ("CellTemperatures", 6, 1.0)):
        by_base = defaultdict(list)
        for t, sig in decoded[name]:
            by_base[sig["CellIndexBase"]].append(t)
        assert sorted(by_base) == list(range(0, N_CELLS, per_frame))  # every cell once per round
        for base, ts in by_base.items():
            assert len(ts) == round(DURATION_S / period)
            np.testing.assert_allclose(np.diff(ts), period, atol=1e-6)
        # the frames of one round are spread over the round, not sent in one burst
        firsts = sorted(ts[0] for ts in by_base.values())
        assert firsts[0] == 0.0 and 0 < firsts[-1] < period
    counters = [sig["MeasurementCounter"] for _, sig in decoded["PackMeasurement"][:20]]
    assert counters == [k % 16 for k in range(20)]
    for name, counter in (("CellVoltages", "VoltageCounter"), ("CellTemperatures", "TemperatureCounter")):
        runs = defaultdict(list)
        for _, sig in decoded[name]:
            runs[sig["CellIndexBase"]].append(sig[counter])
        assert all(c == [k % 16 for k in range(len(c))] for c in runs.values()), name  # per CellIndexBase


def test_encode_log_output_passes_the_default_end_to_end_checks(encoded):
    """Every frame encode-log writes is accepted by the service's default mapping: no CRC or
    counter failure, every frame decoded; and a frame with one flipped bit is not."""
    from bms_estimator.can.decoder import FrameDecoder

    dec = FrameDecoder(load_project_db(), "default", N_CELLS)
    msgs = list(can.LogReader(str(encoded["log"])))
    for msg in msgs:
        dec.decode(msg)
    c = dec.counters
    assert (c.e2e_crc, c.e2e_counter, c.errors) == (0, 0, 0)
    assert c.decoded == c.frames == len(msgs)
    first = msgs[0]  # a PackMeasurement frame (current first at equal times)
    assert first.arbitration_id == load_project_db().get_message_by_name("PackMeasurement").frame_id
    data = bytearray(first.data)
    data[1] ^= 0x04  # 1.024 A more current: the CRC no longer matches
    fresh = FrameDecoder(load_project_db(), "default", N_CELLS)
    assert fresh.decode(can.Message(arbitration_id=first.arbitration_id, is_extended_id=True, data=bytes(data))) == []
    assert fresh.counters.e2e_crc == 1 and fresh.decode(first) != []


def test_cell0_is_the_measured_voltage_and_padding_is_not_available(decoded, cell_voltages, measured):
    t, v = cell_voltages
    _, _, v_meas, temp = measured
    k = np.floor(t[:, 0] + EPS).astype(int)  # the sample each frame carries
    assert np.all(np.abs(v[:, 0] - v_meas[k]) <= V_STEP / 2 + EPS)
    # the slot after the last cell carries NotAvailable (8 cells: CellVoltage2 of base 6)
    assert all(str(sig["CellVoltage2"]) == "NotAvailable" for _, sig in decoded["CellVoltages"]
               if sig["CellIndexBase"] == 6)
    # every cell gets the measured temperature (0.5 degC steps), padding slots NotAvailable
    for ts, sig in decoded["CellTemperatures"]:
        kk = int(math.floor(ts + EPS))
        for j in range(6):
            value = sig[f"CellTemperature{j}"]
            if sig["CellIndexBase"] + j < N_CELLS:
                assert abs(value - temp[kk]) <= 0.25 + EPS
            else:
                assert str(value) == "NotAvailable"


def test_current_charge_is_preserved(decoded, measured):
    _, i_meas, _, _ = measured
    cur = np.array([sig["PackCurrent"] for _, sig in decoded["PackMeasurement"]])
    assert np.all(np.abs(cur.reshape(DURATION_S, 100) - i_meas[:, None]) <= 1e-3 + EPS)  # held, dithered 1 mA
    per_second = cur.reshape(DURATION_S, 100).sum(axis=1) * 0.01  # A*s of each 1 s sample
    q_cum = np.cumsum(per_second)
    np.testing.assert_allclose(q_cum, np.cumsum(i_meas), atol=1e-5 + 1e-9)  # within one raw step, never drifting
    np.testing.assert_allclose(per_second, i_meas, atol=2e-5)
    # pack voltage = sum of the cells (1 mV steps)
    _, sig0 = decoded["PackMeasurement"][150]
    volts = {}
    for ts, sig in decoded["CellVoltages"]:
        if 1.0 <= ts < 2.0:
            for j in range(3):
                if sig["CellIndexBase"] + j < N_CELLS:
                    volts[sig["CellIndexBase"] + j] = sig[f"CellVoltage{j}"]
    assert abs(sig0["PackVoltage"] - sum(volts.values())) <= 5e-4 + N_CELLS * V_STEP / 2


def test_other_cells_are_what_the_truth_json_says(encoded, cell_voltages, measured):
    truth = encoded["truth"]
    t, v = cell_voltages
    rec, i_meas, v_meas, _ = measured
    assert truth["n_cells"] == N_CELLS and truth["seed"] == SEED
    assert truth["reference"]["capacity_source"] == "online SOC estimator"  # Panasonic ends under load
    cells = truth["cells"]
    q_ref = truth["reference"]["capacity_ah"]
    assert cells[0]["measured"] and all(cells[0][f"{k}_factor"] == 1.0 for k in ("capacity", "r0", "r1", "tau1"))
    for c in cells[1:]:
        assert not c["measured"]
        assert c["capacity_ah"] == pytest.approx(q_ref * c["capacity_factor"])
        assert c["r0_factor"] != 1.0 and c["tau2_factor"] != 1.0
        assert c["voltage_rms_diff_to_cell0_mv"] > 0.1
    # rebuild the pack from the JSON alone (model re-identified with the JSON's reference capacity)
    ocv = read_ocv_table(ocv_table(CELL))
    model = identify_cell_model(rec, ocv, 2.9, reference_capacity_ah=q_ref)
    model = replace(model, soc=model.soc[:DURATION_S], residual_v=model.residual_v[:DURATION_S])
    expect = pack_voltages(i_meas, v_meas, model, truths_from_json(truth))
    k = np.floor(t + EPS).astype(int)
    got_expect = np.take_along_axis(expect, k, axis=0)
    assert np.all(np.abs(v - got_expect) <= V_STEP / 2 + 1e-7)
    # physics: the ohmic jump at current steps differs from cell 0 by (f_R0 - 1) * R0
    vs = v[::10]  # one value per 1 s sample
    di = np.diff(i_meas)
    steps = np.abs(di) > 0.3  # this cycle's 1 s means change by up to ~2 A per second
    assert steps.sum() > 100
    r0_path = float(np.mean(lookup_params(model.soc_table, model.soc)["r0_ohm"]))  # R0 where the file is
    slopes, expected = [], []
    for j in range(1, N_CELLS):
        dv = np.diff(vs[:, j] - vs[:, 0])
        slopes.append(np.sum(dv[steps] * di[steps]) / np.sum(di[steps] ** 2))
        expected.append((cells[j]["r0_factor"] - 1.0) * r0_path)
    slopes, expected = np.array(slopes), np.array(expected)
    assert np.corrcoef(slopes, expected)[0, 1] > 0.9
    assert np.max(np.abs(slopes - expected)) < 0.3e-3  # ohm; the injected differences are up to ~1.5 mOhm


def test_asc_and_blf_carry_the_same_frames(encoded):
    ref = [(m.timestamp, m.arbitration_id, bytes(m.data)) for m in can.LogReader(str(encoded["log"]))]
    q = encoded["truth"]["reference"]["capacity_ah"]
    for suffix in (".asc", ".blf"):
        out = encoded["dir"] / f"pack{suffix}"
        rc = main(["encode-log", str(drive_cycle(CELL, CYCLE)), "--cells", str(N_CELLS), "-o", str(out),
                   "--seed", str(SEED), "--duration-s", str(DURATION_S), "--reference-capacity-ah", repr(q),
                   "--no-progress"])
        assert rc == 0
        assert Path(str(out) + ".truth.json").is_file()
        got = [(m.timestamp, m.arbitration_id, bytes(m.data)) for m in can.LogReader(str(out))]
        assert len(got) == len(ref)
        assert [g[1:] for g in got] == [r[1:] for r in ref]
        np.testing.assert_allclose([g[0] for g in got], [r[0] for r in ref], atol=1e-6)


def test_zero_spread_makes_every_cell_the_measured_one():
    rec = load_recording(drive_cycle("lg-hg2", "udds"))
    ocv = read_ocv_table(ocv_table("lg-hg2"))
    tr = build_pack(rec, 4, ocv, 3.0, spread=CellSpread().scaled(0.0), reference_capacity_ah=2.7, duration_s=300)
    np.testing.assert_allclose(tr.cell_voltage_v, np.repeat(rec.voltage_v[:300, None], 4, axis=1), atol=1e-9)
    fa = frame_arrays(tr, t0_s=100.0)
    assert len(fa) == 300 * (100 + 10 * 2 + 1)
    assert fa.timestamps[0] == 100.0
    first = next(fa.iter_messages())
    assert first.timestamp == 100.0 and first.is_extended_id and len(first.data) == 8


def test_spread_is_seeded_and_documented():
    a = draw_cell_truths(5, 3.0, 1.0, CellSpread(), seed=1)
    assert a == draw_cell_truths(5, 3.0, 1.0, CellSpread(), seed=1)
    assert a != draw_cell_truths(5, 3.0, 1.0, CellSpread(), seed=2)
    # the documented rule: z = clip(standard_normal((n-1, 7)), -3, 3), factor = 1 + sigma z
    z = np.clip(np.random.default_rng(1).standard_normal((4, 7)), -3, 3)
    assert [t.r0_factor for t in a[1:]] == pytest.approx(1 + 0.05 * z[:, 1])
    assert [t.capacity_ah for t in a[1:]] == pytest.approx(3.0 * (1 + 0.02 * z[:, 0]))
    assert parse_spread("0") == CellSpread().scaled(0)
    assert parse_spread("capacity=0.03,rc=0.1").tau2 == 0.1
    assert parse_spread("capacity=0.03,rc=0.1").capacity == 0.03
    for bad in ("r9=0.1", "r0=abc", "r0=0.5", "capacity"):
        with pytest.raises(ValueError):
            parse_spread(bad)


def test_missing_ocv_for_an_unknown_cell_is_a_clear_error(tmp_path, capsys):
    rec = load_recording(drive_cycle("lg-hg2", "udds"))
    src = save_recording(CellRecording(rec.time_s[:100], rec.current_a[:100], rec.voltage_v[:100]),
                         tmp_path / "mycell.csv")
    rc = main(["encode-log", str(src), "--cells", "4", "-o", str(tmp_path / "x.log"), "--no-progress"])
    err = capsys.readouterr().err
    assert rc == 2 and "--ocv" in err and "--capacity-ah" in err
    rc = main(["encode-log", str(src), "--cells", "4", "-o", str(tmp_path / "x.csv"), "--no-progress"])
    assert rc == 2 and ".log" in capsys.readouterr().err


def test_a_missing_input_is_said_before_the_options_it_would_need(tmp_path, capsys):
    """'encode-log nonexist.csv' asked for --ocv and --capacity-ah (exit 2) before saying the file is not there."""
    missing = tmp_path / "nonexist.csv"
    rc = main(["encode-log", str(missing), "--cells", "2", "-o", str(tmp_path / "x.log"), "--no-progress"])
    assert (rc, capsys.readouterr().err) == (3, f"bms-estimator encode-log: error: {missing}: No such file or directory\n")
    rc = main(["encode-log", str(tmp_path), "--cells", "2", "-o", str(tmp_path / "x.log"), "--no-progress"])
    assert (rc, capsys.readouterr().err) == (3, f"bms-estimator encode-log: error: {tmp_path}: Is a directory\n")
    assert not (tmp_path / "x.log").exists()


def test_a_recording_in_milliamps_is_refused_not_encoded(tmp_path, capsys):
    """A current in mA was encoded as a pack 'with model RMSE 515808 mV' and exit 0."""
    rec = load_recording(drive_cycle("lg-hg2", "udds"))
    src = save_recording(CellRecording(rec.time_s, rec.current_a * 1000, rec.voltage_v), tmp_path / "lg-hg2_mA.csv")
    out = tmp_path / "x.log"
    assert main(["encode-log", str(src), "--cells", "2", "-o", str(out), "--no-progress"]) == 3
    err = capsys.readouterr().err
    assert "lg-hg2_mA.csv: its coulomb count spans" in err and "times the shipped cell's capacity = 3 Ah" in err, err
    assert not out.exists()


def test_cells_out_of_range_and_a_file_it_cannot_encode_have_their_exit_codes(tmp_path, capsys):
    """--cells 0 with an unshipped cell was answered with 'give --ocv and --capacity-ah' (the count was checked
    after the file); a 3-sample file or one with a logging gap gave exit 2, as if the command line were wrong,
    the gap's step as 'np.float64(300000001.0)'."""
    rec = load_recording(drive_cycle("lg-hg2", "udds"))
    src = save_recording(CellRecording(rec.time_s[:100], rec.current_a[:100], rec.voltage_v[:100]),
                         tmp_path / "mycell.csv")
    out = tmp_path / "x.log"
    for cells in ("0", "-3", "100000"):
        assert main(["encode-log", str(src), "--cells", cells, "-o", str(out), "--no-progress"]) == 2
        assert f"--cells must be 1..2000 (the DBC's multiplexer range), got {cells}" in capsys.readouterr().err
    cell = ["--ocv", str(ocv_table("lg-hg2")), "--capacity-ah", "3", "--cells", "2", "-o", str(out), "--no-progress"]
    short = save_recording(CellRecording(rec.time_s[:3], rec.current_a[:3], rec.voltage_v[:3]), tmp_path / "s.csv")
    assert main(["encode-log", str(short), *cell]) == 3
    assert "s.csv: only 3 samples; encode-log needs at least 10" in capsys.readouterr().err
    t = rec.time_s[:100].copy()
    t[50:] += 3e8
    gap = save_recording(CellRecording(t, rec.current_a[:100], rec.voltage_v[:100]), tmp_path / "gap.csv")
    assert main(["encode-log", str(gap), *cell]) == 3
    # a 1 s file's hole is read as a 0.1 s file's is (data.py, "Resampling" 5.): this one is refused on loading
    assert ("its longest logging gap ends at line 52 (49 -> 3e+08 s): is time_s in seconds? split the recording "
            "at the gap" in capsys.readouterr().err)
    assert not out.exists()
