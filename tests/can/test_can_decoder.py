"""Mapping presets and FrameDecoder with the project's DBC and the foxBMS 2 DBC."""

from __future__ import annotations

import math
import tomllib

import can
import cantools
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from bms_estimator.can.decoder import EventKind, FrameDecoder
from bms_estimator.can.e2e import E2EStamper
from bms_estimator.can.mapping import (
    CanMapping,
    MappingError,
    load_mapping,
    mapping_to_dict,
    preset_names,
    preset_path,
)
from bms_estimator.can.sampler import SampleAssembler

from bmscan_helpers import (
    fox_current_frame,
    fox_voltage_frame,
    frame,
    own_current_frame,
    own_voltage_frame,
)


# ------------------------------------------------------------------ mapping
def test_presets_load_and_survive_a_dict_round_trip():
    assert {"bms_estimator", "foxbms"} <= set(preset_names())
    for name in ["default", "bms_estimator", "foxbms"]:
        m = load_mapping(name)
        assert isinstance(m, CanMapping)
        assert load_mapping(mapping_to_dict(m)) == m
        # the file itself is plain TOML
        assert tomllib.loads(preset_path(name).read_text())["current"]["signal"] == m.current.signal
    assert load_mapping(str(preset_path("foxbms"))) == load_mapping("foxbms")
    fox = load_mapping("foxbms")
    assert fox.current.scale == 0.001 and fox.current.sign == -1


@pytest.mark.parametrize(
    "patch,needle",
    [
        ({"current": {"message": "X", "signal": "Y", "bogus": 1}}, "bogus"),
        ({"cell_voltages": [{"message": "M"}]}, "exactly one of signal_pattern or table"),
        ({"cell_voltages": [{"message": "M", "signal_pattern": "V\\d+"}]}, "named groups"),
        ({"cell_voltages": [{"message": "M", "signal_pattern": "(?P<cell>"}]}, "regular expression"),
        ({"current": {"message": "X", "signal": "Y", "scale": 0}}, "non-zero"),
        ({"current": {"message": "X", "signal": "Y", "sign": 2}}, "sign"),
        ({"cell_voltages": []}, "cell_voltages"),
        # [valid_min, valid_max] must be a range: a single point would drop almost every value
        ({"current": {"message": "X", "signal": "Y", "valid_min": 5.0, "valid_max": 5.0}}, "valid_min must be < valid_max"),
        ({"cell_voltages": [{"message": "M", "table": [{"signals": {"V": -1}}]}]}, "negative cell index"),
        ({"cell_voltages": [{"message": "M", "signal_pattern": "(?P<cell>\\d)(?P<slot>\\d)"}]}, "exactly one of the named groups"),
        ({"cell_voltages": [{"message": "M", "signal_pattern": "V(?P<slot>\\d)", "mux_stride": -1}]}, "mux_stride"),
    ],
)
def test_mapping_validation_names_the_problem(patch, needle):
    base = mapping_to_dict(load_mapping("default"))
    base.update(patch)
    with pytest.raises(MappingError) as err:
        load_mapping(base)
    assert needle in str(err.value)


def test_unknown_preset_lists_the_presets():
    with pytest.raises(MappingError, match="foxbms"):
        load_mapping("no-such-preset")


@pytest.mark.parametrize(
    "patch,needle",
    [
        ({"current": {"message": "Nope", "signal": "PackCurrent"}}, "'Nope' not in the DBC"),
        ({"current": {"message": "PackMeasurement", "signal": "Nope"}}, "signal 'Nope'"),
        ({"current": {"message": "PackMeasurement", "signal": "PackCurrent", "invalid_if_nonzero": ["F"]}}, "flag 'F'"),
        ({"cell_voltages": [{"message": "CellVoltages", "signal_pattern": "Volt(?P<slot>\\d)"}]}, "matches no signal"),
        ({"cell_voltages": [{"message": "CellVoltages", "signal_pattern": "CellVoltage(?P<slot>\\d)"}]}, "mux_stride"),
        ({"cell_voltages": [{"message": "CellVoltages", "signal_pattern": "CellVoltage(?P<slot>\\d)",
                             "mux_stride": 1, "invalid_flag": "{signal}_bad"}]}, "CellVoltage0_bad"),
    ],
)
def test_mapping_that_does_not_fit_the_dbc(project_db, patch, needle):
    base = mapping_to_dict(load_mapping("default"))
    base.update(patch)
    with pytest.raises(MappingError) as err:
        FrameDecoder(project_db, base, 8)
    assert needle in str(err.value)


# ----------------------------------------------------------- project DBC
def test_project_dbc_frames_to_sample(project_db):
    n = 7
    dec = FrameDecoder(project_db, "default", n)
    assert dec.voltage_cells == set(range(n))
    sampler = SampleAssembler(n, period_s=1.0, staleness_s=2.0)
    volts = [3.0 + 0.1 * i for i in range(9)]
    frames = [own_current_frame(project_db, -12.5, t=9.95, voltage_v=401.2)]
    for t in (10.0, 10.5):
        frames.append(own_current_frame(project_db, -12.5, t=t, voltage_v=401.2))
        for base in (0, 3, 6):
            frames.append(own_voltage_frame(project_db, base, volts[base:base + 3], t=t + 0.01))
        frames.append(frame(project_db, "CellTemperatures",
                            {"CellIndexBase": 0, **{f"CellTemperature{j}": 20.0 + j for j in range(6)}}, t + 0.02))
    frames.append(own_current_frame(project_db, 0.0, t=11.0))
    samples = []
    for msg in frames:
        samples += sampler.feed_frame(dec.decode(msg), msg.timestamp)
    assert len(samples) == 1
    s = samples[0]
    assert s.t_s == 11.0
    assert s.current_a == pytest.approx(-12.5)  # positive = charge: a discharge stays negative
    np.testing.assert_allclose(s.cell_voltage_v, volts[:n], atol=1e-4)
    assert s.valid.all()
    np.testing.assert_allclose(s.cell_temperature_c[:6], [20, 21, 22, 23, 24, 25])
    assert math.isnan(s.cell_temperature_c[6])
    assert s.pack_voltage_v == pytest.approx(401.2)
    assert dec.counters.errors == 0


# ----------------------------------------------------------------- foxBMS
def test_foxbms_frames_to_sample(foxbms_db):
    n = 16
    dec = FrameDecoder(foxbms_db, "foxbms", n)
    assert dec.voltage_cells == set(range(n))
    sampler = SampleAssembler(n, period_s=1.0, staleness_s=6.0)
    mv = [3300 + 7 * i for i in range(n)]
    msgs = []
    t = 100.0
    msgs.append(fox_current_frame(foxbms_db, 25_000, t - 0.05))  # +25 A discharge in foxBMS convention
    for step in range(100):
        tc = t + 0.01 * step
        msgs.append(fox_current_frame(foxbms_db, 25_000, tc))
    for mux in range(4):
        msgs.append(fox_voltage_frame(foxbms_db, mux, mv[4 * mux:4 * mux + 4], t + 0.1 + 0.01 * mux,
                                      invalid=(2,) if mux == 1 else ()))
    msgs.append(frame(foxbms_db, "AFE_CellTemperatures",
                      {"AFE_CellTemperatures_Mux": 1,
                       **{f"CellTemperature_{c:03d}": 10 + c for c in range(6, 12)},
                       **{f"CellTemperature_{c:03d}_invalidFlag": 0 for c in range(6, 12)}}, t + 0.2))
    msgs.append(frame(foxbms_db, "CS_IsabellenhuetteIvtString0V1",
                      {"IVT_ID_Result_U1": 1, "IVT_Result_U1_System_Error": 0, "IVT_Result_U1_Measurement_Error": 0,
                       "IVT_Result_U1_Channel_Error": 0, "IVT_Result_U1_OCS": 0,
                       "IVT_Result_U1": 52_345}, t + 0.3))
    msgs.append(fox_current_frame(foxbms_db, 0, t + 1.0))
    msgs.sort(key=lambda m: m.timestamp)
    samples = []
    for m in msgs:
        samples += sampler.feed_frame(dec.decode(m), m.timestamp)
    assert len(samples) == 1
    s = samples[0]
    assert s.current_a == pytest.approx(-25.0)  # foxBMS discharge -> negative (charge-positive convention)
    expect = np.array(mv, dtype=float) / 1000.0
    ok = np.ones(n, bool)
    ok[6] = False  # CellVoltage_006_invalidFlag = 1
    np.testing.assert_allclose(s.cell_voltage_v[ok], expect[ok])
    assert math.isnan(s.cell_voltage_v[6])
    np.testing.assert_array_equal(s.valid, ok)
    np.testing.assert_allclose(s.cell_temperature_c[6:12], np.arange(16, 22))
    assert np.isnan(s.cell_temperature_c[:6]).all()
    assert s.pack_voltage_v == pytest.approx(52.345)
    assert dec.counters.flagged_invalid == 1


def test_foxbms_output_frames_by_configuration_only(foxbms_db):
    cfg = mapping_to_dict(load_mapping("foxbms"))
    cfg["cell_voltages"][0]["message"] = "f_CellVoltages"
    dec = FrameDecoder(foxbms_db, cfg, 8)
    values = {"f_CellVoltages_Mux": 1}
    for c in range(4, 8):
        values[f"CellVoltage_{c:03d}"] = 3000 + c
        values[f"CellVoltage_{c:03d}_invalidFlag"] = 0
    ev = dec.decode(frame(foxbms_db, "f_CellVoltages", values))
    assert [(e.kind, e.cell) for e in ev] == [(EventKind.CELL_VOLTAGE, c) for c in range(4, 8)]
    assert [e.value for e in ev] == pytest.approx([3.004, 3.005, 3.006, 3.007])


def test_explicit_table_form(foxbms_db):
    cfg = mapping_to_dict(load_mapping("foxbms"))
    cfg["cell_voltages"] = [{
        "message": "AFE_CellVoltages", "scale": 0.001,
        "table": [{"mux": 1, "signals": {"CellVoltage_004": 0, "CellVoltage_007": 1}}],
    }]
    dec = FrameDecoder(foxbms_db, cfg, 2)
    ev = dec.decode(fox_voltage_frame(foxbms_db, 1, [3100, 3200, 3300, 3400]))
    assert sorted((e.cell, round(e.value, 6)) for e in ev) == [(0, 3.1), (1, 3.4)]
    bad = dict(cfg, cell_voltages=[{"message": "AFE_CellVoltages",
                                     "table": [{"mux": 0, "signals": {"CellVoltage_004": 0}}]}])
    with pytest.raises(MappingError, match="not sent with mux 0"):
        FrameDecoder(foxbms_db, bad, 2)


def test_both_layouts_yield_the_same_arrays(project_db, foxbms_db):
    """Same physical values through both DBCs and presets: same sample."""
    n = 12
    rng = np.random.default_rng(3)
    mv = rng.integers(2800, 4200, n)
    samples = {}
    for name, db in (("default", project_db), ("foxbms", foxbms_db)):
        dec = FrameDecoder(db, name, n)
        smp = SampleAssembler(n, staleness_s=6.0)
        msgs = []
        for k in range(101):
            t = 50.0 + 0.01 * k
            msgs.append(own_current_frame(db, 3.25, t) if name == "default" else fox_current_frame(db, -3250, t))
        for j in range(n // 3 if name == "default" else n // 4):
            if name == "default":
                msgs.append(own_voltage_frame(db, 3 * j, [float(v) / 1000 for v in mv[3 * j:3 * j + 3]], 50.2))
            else:
                msgs.append(fox_voltage_frame(db, j, [int(v) for v in mv[4 * j:4 * j + 4]], 50.2))
        msgs.sort(key=lambda m: m.timestamp)
        out = []
        for m in msgs:
            out += smp.feed_frame(dec.decode(m), m.timestamp)
        assert len(out) == 1
        samples[name] = out[0]
    a, b = samples["default"], samples["foxbms"]
    np.testing.assert_allclose(a.cell_voltage_v, b.cell_voltage_v, atol=1e-9)
    np.testing.assert_allclose(a.cell_voltage_v, mv / 1000.0, atol=1e-9)
    assert a.current_a == pytest.approx(3.25) and b.current_a == pytest.approx(3.25)


# -------------------------------------------------------------- bad input
def test_bad_input_is_counted_not_raised(project_db):
    dec = FrameDecoder(project_db, "default", 30)
    c = dec.counters
    cv = project_db.get_message_by_name("CellVoltages")

    assert dec.decode(can.Message(arbitration_id=0x123, data=b"\0" * 8, is_extended_id=False)) == []
    assert c.unknown_id == 1
    status = project_db.get_message_by_name("EstimatorStatus")
    assert dec.decode(can.Message(arbitration_id=status.frame_id, is_extended_id=True, data=bytes(8))) == []
    assert c.unmapped == 1
    # same id but standard frame: a different identifier
    assert dec.decode(can.Message(arbitration_id=cv.frame_id & 0x7FF, is_extended_id=False, data=bytes(8))) == []
    assert c.unknown_id == 2

    good = own_voltage_frame(project_db, 0, [3.0, 3.1, 3.2])
    short = can.Message(arbitration_id=cv.frame_id, is_extended_id=True, data=good.data[:5])
    assert dec.decode(short) == [] and c.short_frame == 1
    one_byte_short = can.Message(arbitration_id=cv.frame_id, is_extended_id=True, data=good.data[:7])
    assert dec.decode(one_byte_short) == [] and c.short_frame == 2  # the DBC says 8 bytes

    bad_mux = can.Message(arbitration_id=cv.frame_id, is_extended_id=True,
                          data=(2500).to_bytes(2, "little") + good.data[2:])
    assert dec.decode(bad_mux) == [] and c.bad_mux == 1

    na = project_db.encode_message("CellVoltages", {"CellIndexBase": 3, "VoltageCounter": 0, "CellVoltage0": 65535,
                                                    "CellVoltage1": 36000, "CellVoltage2": 60000},
                                   scaling=False, strict=False)
    ev = dec.decode(can.Message(arbitration_id=cv.frame_id, is_extended_id=True, data=na))
    assert [(e.cell, round(e.value, 4)) for e in ev] == [(4, 3.6)]
    assert c.not_available == 1 and c.out_of_range == 1  # 6.0 V > valid_max 5.5 V

    assert dec.decode(own_current_frame(project_db, 6000.0)) != []  # pack voltage still fine
    assert c.out_of_range == 2  # 6000 A > 5000 A
    ev = dec.decode(own_current_frame(project_db, 10.0, invalid=True))
    assert [e.kind for e in ev] == [EventKind.PACK_VOLTAGE] and c.flagged_invalid == 1

    remote = can.Message(arbitration_id=cv.frame_id, is_extended_id=True, is_remote_frame=True, dlc=8)
    err = can.Message(arbitration_id=cv.frame_id, is_extended_id=True, is_error_frame=True, data=bytes(8))
    assert dec.decode(remote) == [] and dec.decode(err) == [] and c.ignored == 2
    assert dec.decode(good) and c.internal_error == 0
    assert c.errors == c.short_frame + c.bad_mux + c.not_available + c.out_of_range + c.flagged_invalid


def test_foxbms_bad_mux_and_sensor_error(foxbms_db):
    dec = FrameDecoder(foxbms_db, "foxbms", 16)
    m = foxbms_db.get_message_by_name("AFE_CellVoltages")
    assert dec.decode(can.Message(arbitration_id=m.frame_id, is_extended_id=False,
                                  data=bytes([200]) + bytes(7))) == []
    assert dec.counters.bad_mux == 1
    assert dec.decode(fox_current_frame(foxbms_db, 5000, error=True)) == []
    assert dec.counters.flagged_invalid == 1
    # a cell beyond the configured pack is simply not mapped
    assert dec.decode(fox_voltage_frame(foxbms_db, 10, [3000] * 4)) == []
    assert dec.counters.unmapped == 1


FLOAT_DBC = """VERSION ""
NS_ :
BS_:
BU_: X
BO_ 256 F: 8 X
 SG_ I : 0|32@1- (1,0) [-1E+38|1E+38] "A" X
 SG_ V : 32|32@1- (1,0) [-1E+38|1E+38] "V" X
SIG_VALTYPE_ 256 I : 1;
SIG_VALTYPE_ 256 V : 1;
"""


def test_nan_and_inf_from_float_signals():
    db = cantools.database.load_string(FLOAT_DBC, database_format="dbc", strict=True)
    mapping = {"current": {"message": "F", "signal": "I"},
               "cell_voltages": [{"message": "F", "table": [{"signals": {"V": 0}}]}]}
    dec = FrameDecoder(db, mapping, 1)
    for i, v in [(math.nan, 3.3), (math.inf, math.nan), (1.5, -math.inf)]:
        data = db.encode_message("F", {"I": i, "V": v}, strict=False)
        dec.decode(can.Message(arbitration_id=256, is_extended_id=False, data=data))
    assert dec.counters.non_finite == 4
    assert dec.counters.events == 2


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    which=st.integers(0, 20),
    data=st.binary(min_size=0, max_size=12),
    ext=st.booleans(),
    remote=st.booleans(),
)
def test_decode_never_raises_on_random_frames(project_db, which, data, ext, remote):
    dec = _random_decoder(project_db)
    ids = [m.frame_id for m in project_db.messages] + [0, 0x7FF, 0x1FFFFFFF]
    arb = ids[which % len(ids)] & (0x1FFFFFFF if ext else 0x7FF)
    msg = can.Message(arbitration_id=arb, is_extended_id=ext, data=data if not remote else None,
                      is_remote_frame=remote, dlc=min(len(data), 8), check=False)
    out = dec.decode(msg)
    assert isinstance(out, list)
    for e in out:
        assert math.isfinite(e.value)
    assert dec.counters.internal_error == 0


_DECODERS: dict = {}


def _random_decoder(db):
    if "d" not in _DECODERS:
        _DECODERS["d"] = FrameDecoder(db, "default", 64)
    return _DECODERS["d"]


@pytest.mark.parametrize("layout", ["project", "foxbms"])
def test_bit_fields_decode_as_cantools(request, layout):
    """The bit-field fast path gives the events and counters cantools' decode gives, frame by
    frame, on random payloads of every mapped message (defined and undefined multiplexer
    values, flags set and not, NotAvailable raws, signed values)."""
    db = request.getfixturevalue("project_db" if layout == "project" else "foxbms_db")
    mapping, n_cells = ("default", 64) if layout == "project" else ("foxbms", 16)
    fast = FrameDecoder(db, mapping, n_cells)
    slow = FrameDecoder(db, mapping, n_cells, bit_fields=False)
    stamper = E2EStamper(db, mapping)  # most frames pass the end-to-end checks, some fail them
    plans = list(fast._plans.values())
    assert plans and all(p.fields is not None for p in plans)  # the fast path is what is tested
    assert all(p.fields is None for p in slow._plans.values())
    rng = np.random.default_rng(15)
    for _ in range(6000):
        plan = plans[rng.integers(len(plans))]
        m = plan.message
        data = bytearray(rng.integers(0, 256, m.length, dtype=np.uint8).tobytes())
        if plan.mux_field is not None and rng.random() < 0.8:  # mostly a mux value the DBC defines
            big, shift, mask, _ = plan.mux_field
            muxes = sorted(plan.by_mux) if plan.by_mux and rng.random() < 0.7 else sorted(plan.fields)
            mux = muxes[rng.integers(len(muxes))]
            order = "big" if big else "little"
            x = int.from_bytes(data, order) & ~(mask << shift) | ((mux & mask) << shift)
            data = bytearray(x.to_bytes(m.length, order))
        if rng.random() < 0.3:  # flags and NotAvailable raws are mostly all-zero / all-one fields
            data = bytearray(b & (0x00 if rng.random() < 0.5 else 0xFF) if rng.random() < 0.3 else b for b in data)
        if rng.random() < 0.8:
            data = stamper.stamp(m.frame_id, bytes(data))
        msg = can.Message(arbitration_id=m.frame_id, is_extended_id=m.is_extended_frame, data=bytes(data))
        assert fast.decode(msg) == slow.decode(msg), (m.name, data.hex())
    assert fast.counters == slow.counters
    c = fast.counters
    assert c.events > 2000 and c.internal_error == 0
    assert c.bad_mux > 0 and c.flagged_invalid > 0 and c.out_of_range > 0 and c.unmapped > 0, c


# ------------------------------------------------- conversion and limits
def test_the_conversion_is_sign_scale_times_the_dbc_physical_value_plus_offset(project_db):
    """``si = sign * scale * (raw * dbc_scale + dbc_offset) + offset``: a sender that puts degF
    into the project DBC's temperatures (0.5 degC/bit, offset -40) is read with scale 5/9 and
    offset -160/9; 77 degF (raw 234) is 25 degC and 32 degF (raw 144) is 0 degC."""
    cfg = mapping_to_dict(load_mapping("default"))
    cfg["cell_temperatures"][0].update(scale=5.0 / 9.0, offset=-160.0 / 9.0)
    dec = FrameDecoder(project_db, cfg, 2)
    (t0,) = [s for s in dec.layout() if s.kind == EventKind.CELL_TEMPERATURE and s.cell == 0]
    assert t0.a == pytest.approx(0.5 * 5 / 9) and t0.b == pytest.approx(-40.0)
    msg = frame(project_db, "CellTemperatures",
                {"CellIndexBase": 0, **{f"CellTemperature{j}": 32.0 for j in range(6)}, "CellTemperature0": 77.0})
    ev = dec.decode(msg)
    assert [(e.cell, round(e.value, 9)) for e in ev] == [(0, 25.0), (1, 0.0)]


def test_values_on_the_valid_range_bounds_are_kept(project_db):
    """The value must lie IN ``[valid_min, valid_max]``: the preset's 0.5 V and 5.5 V (raw 5000 and
    55000 at 0.1 mV) and +-5000 A (raw +-5e6 at 1 mA) are kept, 0.1 mV beyond is dropped."""
    dec = FrameDecoder(project_db, "default", 3)
    ev = dec.decode(own_voltage_frame(project_db, 0, [0.5, 5.5, 5.5001], t=0.0))
    assert [(e.cell, e.value) for e in ev] == [(0, 0.5), (1, 5.5)]
    ev = dec.decode(own_voltage_frame(project_db, 0, [0.4999, 3.0, 3.0], t=0.1))
    assert [e.cell for e in ev] == [1, 2]
    assert dec.counters.out_of_range == 2
    for i in (5000.0, -5000.0):
        ev = dec.decode(own_current_frame(project_db, i))
        assert [(e.kind, e.value) for e in ev if e.kind == EventKind.CURRENT] == [(EventKind.CURRENT, i)]
    assert dec.counters.out_of_range == 2
    # a voltage group that names no limits takes the same 0.5 .. 5.5 V
    cfg = mapping_to_dict(load_mapping("default"))
    for key in ("valid_min", "valid_max"):
        cfg["cell_voltages"][0].pop(key)
    dec = FrameDecoder(project_db, cfg, 3)
    ev = dec.decode(own_voltage_frame(project_db, 0, [0.4999, 0.5, 5.5001], t=0.2))
    assert [(e.cell, e.value) for e in ev] == [(1, 0.5)]


@pytest.mark.parametrize("stride,offset,base,want", [
    (1, -1, 1, [(0, 3.0), (1, 3.1), (2, 3.2)]),  # CellIndexBase counts from 1
    (1, -1, 0, [(0, 3.1), (1, 3.2)]),  # slot 0 of base 0 would be cell -1: left out
    (3, 0, 2, [(6, 3.0), (7, 3.1), (8, 3.2)]),  # the multiplexer counts 3-cell groups
])
def test_slot_rule_cell_is_mux_times_stride_plus_slot_plus_offset(project_db, stride, offset, base, want):
    cfg = mapping_to_dict(load_mapping("default"))
    cfg["cell_voltages"][0].update(mux_stride=stride, index_offset=offset)
    dec = FrameDecoder(project_db, cfg, 9)
    ev = dec.decode(own_voltage_frame(project_db, base, [3.0, 3.1, 3.2]))
    assert [(e.cell, round(e.value, 6)) for e in ev] == want


def test_index_offset_shifts_the_cell_rule_and_the_table(foxbms_db):
    """A second string's mapping: ``cell = int(cell) + index_offset`` (CellVoltage_004..007 of mux 1
    are cells 20..23 with offset 16), and a table's cells shift the same way."""
    cfg = mapping_to_dict(load_mapping("foxbms"))
    cfg["cell_voltages"][0]["index_offset"] = 16
    dec = FrameDecoder(foxbms_db, cfg, 32)
    ev = dec.decode(fox_voltage_frame(foxbms_db, 1, [3100, 3200, 3300, 3400]))
    assert [(e.cell, round(e.value, 6)) for e in ev] == [(20, 3.1), (21, 3.2), (22, 3.3), (23, 3.4)]
    cfg["cell_voltages"] = [{"message": "AFE_CellVoltages", "scale": 0.001, "index_offset": 10,
                             "table": [{"mux": 1, "signals": {"CellVoltage_005": 0}}]}]
    dec = FrameDecoder(foxbms_db, cfg, 11)
    ev = dec.decode(fox_voltage_frame(foxbms_db, 1, [3100, 3200, 3300, 3400]))
    assert [(e.cell, round(e.value, 6)) for e in ev] == [(10, 3.2)]


MIXED_DBC = """VERSION ""
NS_ :
BS_:
BU_: X
BO_ 512 Mixed: 8 X
 SG_ Mux M : 0|8@1+ (1,0) [0|1] "" X
 SG_ Current : 8|16@1- (0.01,0) [-327.68|327.67] "A" X
 SG_ Status : 24|2@1+ (1,0) [0|3] "" X
 SG_ Volt0 m0 : 32|16@1+ (0.001,0) [0|65.535] "V" X
 SG_ Volt1 m1 : 32|16@1+ (0.001,0) [0|65.535] "V" X
"""


def test_a_multiplexed_frame_carries_its_common_signal_and_a_multi_bit_flag_drops_it():
    """A current sent with every multiplexer value next to multiplexed cell voltages: each frame gives
    both. ``invalid_if_nonzero``: ANY non-zero value of a 2-bit status drops the current (2 as well as 1)."""
    db = cantools.database.load_string(MIXED_DBC, database_format="dbc", strict=True)
    mapping = {"current": {"message": "Mixed", "signal": "Current", "invalid_if_nonzero": ["Status"]},
               "cell_voltages": [{"message": "Mixed", "table": [{"mux": 0, "signals": {"Volt0": 0}},
                                                                {"mux": 1, "signals": {"Volt1": 1}}]}]}
    dec = FrameDecoder(db, mapping, 2)

    def mixed(mux: int, status: int) -> list:
        data = db.encode_message("Mixed", {"Mux": mux, "Current": 12.34, "Status": status, f"Volt{mux}": 3.3 + mux / 10})
        return [(e.kind, e.cell, round(e.value, 6))
                for e in dec.decode(can.Message(arbitration_id=512, is_extended_id=False, data=data))]

    cur = [(EventKind.CURRENT, -1, 12.34)]
    assert mixed(0, 0) == cur + [(EventKind.CELL_VOLTAGE, 0, 3.3)]
    assert mixed(1, 0) == cur + [(EventKind.CELL_VOLTAGE, 1, 3.4)]
    assert mixed(1, 2) == [(EventKind.CELL_VOLTAGE, 1, 3.4)]
    assert mixed(0, 1) == [(EventKind.CELL_VOLTAGE, 0, 3.3)]
    assert dec.counters.flagged_invalid == 2


def test_a_cell_temperature_mapping_without_limits_keeps_minus_60_to_150_degc(foxbms_db):
    """A temperature group that names no ``valid_min``/``valid_max`` takes -60 .. 150 degC: the foxBMS
    DBC's signed 8-bit degC reach -128, and -61 degC (a sensor fault) is dropped, -60 degC kept."""
    cfg = mapping_to_dict(load_mapping("foxbms"))
    for key in ("valid_min", "valid_max"):
        cfg["cell_temperatures"][0].pop(key, None)
    dec = FrameDecoder(foxbms_db, cfg, 12)
    values = {"AFE_CellTemperatures_Mux": 1, **{f"CellTemperature_{c:03d}_invalidFlag": 0 for c in range(6, 12)},
              **{f"CellTemperature_{c:03d}": 20 for c in range(6, 12)},
              "CellTemperature_006": -61, "CellTemperature_007": -60, "CellTemperature_008": 127}
    ev = dec.decode(frame(foxbms_db, "AFE_CellTemperatures", values))
    assert [(e.cell, e.value) for e in ev] == [(7, -60.0), (8, 127.0), (9, 20.0), (10, 20.0), (11, 20.0)]
    assert dec.counters.out_of_range == 1
