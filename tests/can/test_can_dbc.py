"""The project's DBC: loads strictly, resolution good enough, every output frame round-trips."""

from __future__ import annotations

import math
import os
from pathlib import Path

import cantools
import numpy as np
import pytest

from bms_estimator.can.dbc import project_dbc_path
from bms_estimator.can.encoder import UNIT_FROM_SI, StateEncoder

REPO_ROOT = Path(__file__).resolve().parents[2]

OUTPUTS = ["CellStateA", "CellStateB", "PackSummary", "PackElectrical", "EstimatorStatus", "EstimatorCounters"]
INPUTS = ["PackMeasurement", "CellVoltages", "CellTemperatures"]

# (message, signal, smallest typical value in SI units, SI -> DBC unit factor comes from the DBC's unit)
TYPICAL = [
    ("CellStateA", "Soc", 5.0),  # % (SOC is handed over in percent here)
    ("CellStateA", "R0", 1e-3),  # ohm
    ("CellStateA", "R1", 1e-3),
    ("CellStateB", "R2", 1e-3),
    ("CellStateB", "C1", 100.0),  # F
    ("CellStateB", "C2", 1000.0),
    ("CellStateA", "C0", 10e-3),  # V, |c0|
    ("CellVoltages", "CellVoltage0", 2.5),  # V
    ("PackMeasurement", "PackCurrent", 1.0),  # A
    ("PackSummary", "SocMean", 5.0),
]
# the largest typical value must fit (SI)
TYPICAL_MAX = [
    ("CellStateA", "Soc", 100.0),
    ("CellStateA", "R0", 50e-3),
    ("CellStateA", "R1", 50e-3),
    ("CellStateB", "R2", 50e-3),
    ("CellStateB", "C1", 10_000.0),
    ("CellStateB", "C2", 100_000.0),
    ("CellStateA", "C0", 0.5),
    ("CellVoltages", "CellVoltage0", 5.0),
]


def test_loads_in_strict_mode_from_both_places():
    path = project_dbc_path()
    assert path.is_file()
    db = cantools.database.load_file(str(path), strict=True)
    repo_copy = cantools.database.load_file(str(REPO_ROOT / "dbc" / "bms_estimator.dbc"), strict=True)
    assert [m.name for m in db.messages] == [m.name for m in repo_copy.messages]
    link = REPO_ROOT / "bms_estimator" / "dbc" / "bms_estimator.dbc"
    assert link.is_symlink() and os.readlink(link) == "../../dbc/bms_estimator.dbc"


def test_frames_are_classic_8_byte_extended(project_db):
    for name in INPUTS + OUTPUTS:
        m = project_db.get_message_by_name(name)
        assert m.length == 8, name
        assert m.is_extended_frame, name
        assert 0x1B5E0000 <= m.frame_id <= 0x1B5E01FF, name
        assert m.comment, f"{name} has no CM_ comment"
        assert m.cycle_time, f"{name} has no GenMsgCycleTime"
        for s in m.signals:
            assert s.comment or s.is_multiplexer, f"{name}.{s.name} has no CM_ comment"
    # inputs win arbitration against outputs
    assert max(project_db.get_message_by_name(n).frame_id for n in INPUTS) < min(
        project_db.get_message_by_name(n).frame_id for n in OUTPUTS
    )


def test_multiplexers_cover_2000_cells(project_db):
    for name in ["CellVoltages", "CellTemperatures", "CellStateA", "CellStateB"]:
        m = project_db.get_message_by_name(name)
        for s in m.signals:
            if not s.is_multiplexer and s.name not in ("VoltageCounter", "TemperatureCounter"):
                assert set(range(2000)) <= set(s.multiplexer_ids), f"{name}.{s.name}"
        mux = next(s for s in m.signals if s.is_multiplexer)
        assert (1 << mux.length) > 1999  # CellIndexBase's 12 bits (inputs) still reach cell 1999


def test_every_input_frame_has_an_alive_counter_and_pack_measurement_a_crc(project_db):
    """The end-to-end signals of issue 16, sent with every frame (not multiplexed); the CRC byte-aligned."""
    for name, counter in [("PackMeasurement", "MeasurementCounter"), ("CellVoltages", "VoltageCounter"),
                          ("CellTemperatures", "TemperatureCounter")]:
        sig = project_db.get_message_by_name(name).get_signal_by_name(counter)
        assert (sig.length, sig.is_signed, sig.multiplexer_ids) == (4, False, None), name
    crc = project_db.get_message_by_name("PackMeasurement").get_signal_by_name("MeasurementCrc")
    assert (crc.start, crc.length) == (56, 8)
    cur = project_db.get_message_by_name("PackMeasurement").get_signal_by_name("PackCurrent")
    assert (cur.length, cur.minimum, cur.maximum) == (24, -8388.607, 8388.607)  # the output's range


@pytest.mark.parametrize("message,signal,typical", TYPICAL)
def test_quantisation_below_one_percent(project_db, message, signal, typical):
    sig = project_db.get_message_by_name(message).get_signal_by_name(signal)
    step_si = sig.scale / UNIT_FROM_SI[sig.unit or ""]
    assert step_si / typical < 0.01, f"{message}.{signal}: step {step_si} vs typical {typical}"


@pytest.mark.parametrize("message,signal,high", TYPICAL_MAX)
def test_typical_range_fits(project_db, message, signal, high):
    sig = project_db.get_message_by_name(message).get_signal_by_name(signal)
    f = UNIT_FROM_SI[sig.unit or ""]
    assert sig.maximum / f >= high
    if signal == "C0":
        assert sig.minimum / f <= -high


def test_not_available_values_lie_outside_the_range(project_db):
    for m in project_db.messages:
        for s in m.signals:
            for raw, name in (s.choices or {}).items():
                if str(name) == "NotAvailable":
                    phys = raw * s.scale + s.offset
                    assert not (s.minimum <= phys <= s.maximum), f"{m.name}.{s.name}"


def _close(a, b, step):
    return abs(a - b) <= step / 2 + 1e-9


def test_cell_frames_round_trip(project_db):
    enc = StateEncoder(project_db)
    idx = np.array([0, 1, 2, 1999])
    soc = np.array([0.0, 0.5, 0.9999, 1.0])
    r0 = np.array([1e-3, 12.3456e-3, 50e-3, 0.0])
    r1 = np.array([2e-3, 5e-3, 49.9e-3, 65e-3])
    c1 = np.array([100.0, 2345.6, 10_000.0, 13_000.0])
    r2 = np.array([1e-3, 7.777e-3, 50e-3, 131e-3])
    c2 = np.array([1000.0, 45_678.0, 100_000.0, 131_000.0])
    c0 = np.array([-0.5, -0.0123, 0.0, 0.5])
    msgs = enc.encode_cells(idx, soc, r0, r1, c1, r2, c2, c0)
    assert len(msgs) == 2 * len(idx)
    a_id = project_db.get_message_by_name("CellStateA").frame_id
    b_id = project_db.get_message_by_name("CellStateB").frame_id
    got: dict[int, dict] = {}
    for m in msgs:
        assert m.is_extended_id and len(m.data) == 8
        d = project_db.decode_message(m.arbitration_id, m.data, decode_choices=False)
        got.setdefault(d["CellIndex"], {}).update(d)
        assert m.arbitration_id in (a_id, b_id)
    sig = {s.name: s for n in ("CellStateA", "CellStateB") for s in project_db.get_message_by_name(n).signals}
    for j, ci in enumerate(idx):
        d = got[int(ci)]
        assert _close(d["Soc"], soc[j] * 100, sig["Soc"].scale)
        assert _close(d["R0"], r0[j] * 1e3, sig["R0"].scale)
        assert _close(d["R1"], r1[j] * 1e3, sig["R1"].scale)
        assert _close(d["C1"], c1[j], sig["C1"].scale)
        assert _close(d["R2"], r2[j] * 1e3, sig["R2"].scale)
        assert _close(d["C2"], c2[j], sig["C2"].scale)
        assert _close(d["C0"], c0[j] * 1e3, sig["C0"].scale)


def test_pack_and_status_frames_round_trip(project_db):
    enc = StateEncoder(project_db)
    soc = np.array([0.40, 0.35, np.nan, 0.80, 0.55])
    valid = np.array([True, True, True, True, False])
    msgs = enc.encode_pack_summary(soc, current_a=-123.456, pack_voltage_v=398.76, valid=valid,
                                   cell_index=np.array([10, 11, 12, 13, 14]))
    dec = {project_db.get_message_by_frame_id(m.arbitration_id).name: project_db.decode_message(
        m.arbitration_id, m.data, decode_choices=False) for m in msgs}
    s = dec["PackSummary"]
    assert _close(s["SocMin"], 35.0, 0.025) and s["SocMinCell"] == 11
    assert _close(s["SocMax"], 80.0, 0.025) and s["SocMaxCell"] == 13
    assert _close(s["SocMean"], (40 + 35 + 80) / 3, 0.025)
    e = dec["PackElectrical"]
    assert _close(e["PackCurrent"], -123.456, 0.001)
    assert _close(e["PackVoltage"], 398.76, 0.01)
    assert e["CellsValid"] == 3
    # the rolling counter advances
    again = enc.encode_pack_summary(soc)
    c2 = project_db.decode_message(again[0].arbitration_id, again[0].data)["SummaryCounter"]
    assert c2 == (s["SummaryCounter"] + 1) % 16

    counters = {"uptime_s": 86_400, "samples": 86_399, "decode_errors": 12, "rejections": 3,
                "stale_cells": 2, "time_jumps": 1, "backward_frames": 300, "estimator_state": "Degraded"}
    st = {project_db.get_message_by_frame_id(m.arbitration_id).name: project_db.decode_message(
        m.arbitration_id, m.data) for m in enc.encode_status(counters)}
    assert st["EstimatorStatus"] == {"UptimeS": 86_400, "Samples": 86_399}
    c = st["EstimatorCounters"]
    assert (c["DecodeErrors"], c["Rejections"], c["StaleCells"], c["TimeJumps"]) == (12, 3, 2, 1)
    assert c["BackwardFrames"] == 255  # saturated
    assert str(c["EstimatorState"]) == "Degraded"


def test_input_frames_round_trip(project_db):
    for name, values in [
        ("PackMeasurement", {"PackCurrent": -250.125, "PackVoltage": 812.345, "MeasurementCounter": 7,
                             "CurrentInvalid": 0, "VoltageInvalid": 1, "MeasurementCrc": 0xA5}),
        ("PackMeasurement", {"PackCurrent": -8388.607, "PackVoltage": 16777.214, "MeasurementCounter": 15,
                             "CurrentInvalid": 1, "VoltageInvalid": 0, "MeasurementCrc": 255}),
        ("CellVoltages", {"CellIndexBase": 1998, "VoltageCounter": 15, "CellVoltage0": 3.1234, "CellVoltage1": 0.0,
                          "CellVoltage2": 6.5534}),
        ("CellTemperatures", {"CellIndexBase": 6, "TemperatureCounter": 9,
                              **{f"CellTemperature{j}": -40 + 25.5 * j for j in range(6)}}),
    ]:
        data = project_db.encode_message(name, values)
        back = project_db.decode_message(name, data, decode_choices=False)
        for k, v in values.items():
            assert math.isclose(back[k], v, abs_tol=1e-9), (name, k)
