"""StateEncoder: clamping and NotAvailable policy, never an exception (hypothesis)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bms_estimator.can.dbc import load_project_db
from bms_estimator.can.encoder import UNIT_FROM_SI, StateEncoder

DB = load_project_db()  # module level: hypothesis prints its arguments, and a fixture DB is huge

ENC = StateEncoder(DB)
any_float = st.floats(allow_nan=True, allow_infinity=True, allow_subnormal=True)
# SI value, column name, DBC signal, message, SI->signal factor beyond the unit (SOC fraction -> %)
COLUMNS = [
    ("soc", "Soc", "CellStateA", 100.0),
    ("r0", "R0", "CellStateA", 1.0),
    ("r1", "R1", "CellStateA", 1.0),
    ("c1", "C1", "CellStateB", 1.0),
    ("r2", "R2", "CellStateB", 1.0),
    ("c2", "C2", "CellStateB", 1.0),
    ("c0", "C0", "CellStateA", 1.0),
]


@pytest.fixture(scope="module")
def project_db():
    return DB


@pytest.fixture(scope="module")
def enc():
    return StateEncoder(DB)


def _expect(sig, si_value: float, extra: float):
    """What the frame must carry for an SI input: ('na',) or the clamped physical value."""
    if math.isnan(si_value):
        return ("na",)
    phys = si_value * extra * UNIT_FROM_SI[sig.unit or ""]
    if math.isnan(phys):  # inf * 0 cannot happen (factors are non-zero) but be safe
        return ("na",)
    return ("value", min(max(phys, sig.minimum), sig.maximum))


@settings(max_examples=300, deadline=None)
@given(
    idx=st.lists(st.one_of(st.integers(-5, 2100), any_float), min_size=1, max_size=6),
    values=st.lists(any_float, min_size=7, max_size=7),
)
def test_encode_cells_never_raises_and_clamps(idx, values):
    project_db, enc = DB, ENC
    msgs = enc.encode_cells(idx, *values)
    usable = [i for i in idx if math.isfinite(i) and i == int(i) and 0 <= i <= 1999]
    assert len(msgs) == 2 * len(usable)
    for m in msgs:
        assert len(m.data) == 8 and m.is_extended_id
    msg_a = project_db.get_message_by_name("CellStateA")
    msg_b = project_db.get_message_by_name("CellStateB")
    for k, m in enumerate(msgs):
        message = msg_a if k % 2 == 0 else msg_b
        assert m.arbitration_id == message.frame_id
        raw = project_db.decode_message(m.arbitration_id, m.data, decode_choices=False, scaling=False)
        phys = project_db.decode_message(m.arbitration_id, m.data, decode_choices=False)
        assert raw["CellIndex"] == int(usable[k // 2])
        for (col, sname, mname, extra), v in zip(COLUMNS, values):
            if mname != message.name:
                continue
            sig = message.get_signal_by_name(sname)
            want = _expect(sig, v, extra)
            na = [r for r, n in sig.choices.items() if str(n) == "NotAvailable"]
            if want[0] == "na":
                assert raw[sname] == na[0], (sname, v)
            else:
                assert raw[sname] != na[0]
                tol = 1e-9 * max(1.0, abs(sig.maximum), abs(sig.minimum))
                assert sig.minimum - tol <= phys[sname] <= sig.maximum + tol
                assert abs(phys[sname] - want[1]) <= sig.scale / 2 + 1e-9 * max(1.0, abs(want[1])), (sname, v)


def test_inf_clamps_to_the_limits(project_db, enc):
    msgs = enc.encode_cells([0, 1], [math.inf, -math.inf], [math.inf, -math.inf], 0.0, [1e300, -1e300],
                            0.0, 0.0, [math.inf, -math.inf])
    d = [project_db.decode_message(m.arbitration_id, m.data) for m in msgs]
    assert d[0]["Soc"] == pytest.approx(102.35) and d[2]["Soc"] == 0.0
    assert d[0]["R0"] == pytest.approx(65.52) and d[2]["R0"] == 0.0
    assert d[0]["C0"] == pytest.approx(655.32) and d[2]["C0"] == pytest.approx(-655.32)
    assert d[1]["C1"] == pytest.approx(13106.8) and d[3]["C1"] == 0.0


def test_scalars_broadcast_and_bad_shapes_become_not_available(project_db, enc):
    msgs = enc.encode_cells(np.arange(3), 0.5, [1e-3, 2e-3], 0.0, None, "x", 1000.0, 0.0)
    d = [project_db.decode_message(m.arbitration_id, m.data) for m in msgs]
    assert [x["Soc"] for x in d[0::2]] == [50.0] * 3
    assert all(x["R0"] == "NotAvailable" for x in d[0::2])  # 2 values for 3 cells
    assert all(x["C1"] == "NotAvailable" and x["R2"] == "NotAvailable" for x in d[1::2])
    assert enc.encode_cells([], 0.5, 0, 0, 0, 0, 0, 0) == []


@settings(max_examples=200, deadline=None)
@given(
    soc=st.lists(any_float, max_size=6),
    current=any_float,
    voltage=any_float,
    valid=st.one_of(st.none(), st.lists(st.booleans(), max_size=6)),
)
def test_pack_summary_never_raises(soc, current, voltage, valid):
    project_db, enc = DB, ENC
    msgs = enc.encode_pack_summary(soc, current, voltage, valid=valid)
    assert len(msgs) == 2
    s = project_db.decode_message(msgs[0].arbitration_id, msgs[0].data)
    finite = [x for x in soc if not math.isnan(x)]
    if valid is not None and len(valid) == len(soc):
        finite = [x for x, ok in zip(soc, valid) if ok and not math.isnan(x)]
    if not finite:
        assert s["SocMin"] == "NotAvailable" and s["SocMinCell"] == "NotAvailable"
    else:
        assert s["SocMin"] != "NotAvailable"
        assert 0 <= s["SocMin"] <= s["SocMax"] <= 102.35 + 1e-9


@settings(max_examples=100, deadline=None)
@given(counters=st.dictionaries(
    st.sampled_from(["uptime_s", "samples", "decode_errors", "rejections", "stale_cells", "time_jumps",
                     "backward_frames", "estimator_state", "unrelated"]),
    st.one_of(any_float, st.integers(-10**20, 10**20), st.text(max_size=8), st.none()),
))
def test_status_never_raises(counters):
    msgs = ENC.encode_status(counters)
    assert len(msgs) == 2
    for m in msgs:
        DB.decode_message(m.arbitration_id, m.data)


def test_status_from_a_dataclass(project_db, enc):
    from dataclasses import dataclass

    @dataclass
    class C:
        uptime_s: float = 12.7
        samples: int = 12
        decode_errors: int = 70_000
        estimator_state: int = 1

    d = {}
    for m in enc.encode_status(C()):
        d.update(project_db.decode_message(m.arbitration_id, m.data, decode_choices=False))
    assert d["UptimeS"] == 13 and d["Samples"] == 12 and d["DecodeErrors"] == 65535 and d["EstimatorState"] == 1
    assert d["Rejections"] == 0


def test_a_status_signal_without_a_counter_is_refused(tmp_path):
    """Status counters reach the CAN frame by an explicit table (service/schema.py); a DBC whose
    status signal was renamed is refused with its name instead of silently encoding 0."""
    import pytest

    from bms_estimator.can.dbc import load_db, project_dbc_path
    from bms_estimator.service.config import ConfigError, ServiceConfig
    from bms_estimator.service.daemon import Service

    text = project_dbc_path().read_text()
    assert " SG_ Samples : " in text
    renamed = tmp_path / "renamed.dbc"
    renamed.write_text(text.replace(" SG_ Samples : ", " SG_ SampleCount : "))
    with pytest.raises(KeyError, match="EstimatorStatus.SampleCount"):
        StateEncoder(load_db(renamed))
    cfg = ServiceConfig(can={"dbc": str(renamed), "interface": "virtual", "channel": "x"},
                        state={"path": str(tmp_path / "s.npz")}, health={"enabled": False})
    with pytest.raises(ConfigError) as exc:
        Service(cfg)
    assert any(p.startswith("can.dbc: status signal(s) EstimatorStatus.SampleCount carry no known counter")
               for p in exc.value.problems), exc.value.problems


@settings(max_examples=200, deadline=None)
@given(
    idx=st.lists(st.one_of(st.integers(-5, 2100), any_float), min_size=1, max_size=8),
    values=st.lists(st.one_of(any_float, st.floats(-1e6, 1e6)), min_size=7, max_size=7),
)
def test_vectorised_cell_frames_are_the_bytes_cantools_builds(idx, values):
    """The numpy packer and cantools frame by frame give the same frames, byte for byte
    (NaN -> NotAvailable, clamping, signed C0, skipped indices)."""
    vec = StateEncoder(DB)
    ref = StateEncoder(DB)
    ref._packers = {name: None for name in ref._packers}  # force cantools, frame by frame
    got, want = vec.encode_cells(idx, *values, timestamp=2.0), ref.encode_cells(idx, *values, timestamp=2.0)
    assert [(m.arbitration_id, m.is_extended_id, bytes(m.data), m.timestamp) for m in got] == \
        [(m.arbitration_id, m.is_extended_id, bytes(m.data), m.timestamp) for m in want]
    assert vec.skipped_cells == ref.skipped_cells


def test_a_big_endian_cell_message_keeps_cantools(tmp_path):
    """A DBC whose cell frames have a Motorola signal is not packed by numpy (it would be wrong)."""
    text = (Path(__file__).resolve().parents[2] / "dbc" / "bms_estimator.dbc").read_text()
    text = text.replace(" SG_ R2 m0 : 32|16@1+", " SG_ R2 m0 : 39|16@0+")
    path = tmp_path / "be.dbc"
    path.write_text(text)
    from bms_estimator.can.dbc import load_db

    db = load_db(path)
    enc = StateEncoder(db)
    assert enc._packers["CellStateB"] is None
    frames = enc.encode_cells([0, 1], 0.5, 0.01, 0.01, 1000.0, 0.004, 5000.0, 0.0)
    decoded = db.get_message_by_name("CellStateB").decode(frames[3].data)
    assert decoded["CellIndex"] == 1 and decoded["R2"] == pytest.approx(4.0, abs=0.002)


def test_only_whole_cell_indices_within_the_multiplexer_are_sent(project_db):
    """CellIndex is 0 .. 1999: -1 (which the 11-bit field would carry as 2047), 2000, 0.5 and NaN are
    skipped and counted; 0 and 1999 are sent, each as its CellStateA + CellStateB pair."""
    enc = StateEncoder(project_db)
    msgs = enc.encode_cells([-1, 0, 1999, 2000, 0.5, math.nan], 0.5, 1e-3, 1e-3, 1000.0, 1e-3, 1000.0, 0.0)
    cells = [project_db.decode_message(m.arbitration_id, m.data)["CellIndex"] for m in msgs]
    assert cells == [0, 0, 1999, 1999]
    assert enc.skipped_cells == 4


def test_soc_in_percent_is_sent_as_is(project_db):
    """``soc_unit="percent"``: 50 is 50 % (raw 2000 at 0.025 %), not 5000 % clamped to 102.35 %."""
    enc = StateEncoder(project_db)
    (a, _) = enc.encode_cells([3], 50.0, 1e-3, 1e-3, 1000.0, 1e-3, 1000.0, 0.0, soc_unit="percent")
    assert project_db.decode_message(a.arbitration_id, a.data)["Soc"] == 50.0
    summary, _ = enc.encode_pack_summary([40.0, 60.0], soc_unit="percent")
    d = project_db.decode_message(summary.arbitration_id, summary.data)
    assert (d["SocMin"], d["SocMean"], d["SocMax"]) == (40.0, 50.0, 60.0)


def test_summary_counter_counts_through_all_sixteen_values(project_db):
    """SummaryCounter is 4 bits: 0, 1, ..., 15, then 0 again (a receiver's alive check expects 15 before 0)."""
    enc = StateEncoder(project_db)
    seen = []
    for _ in range(17):
        summary, _ = enc.encode_pack_summary([0.5])
        seen.append(project_db.decode_message(summary.arbitration_id, summary.data)["SummaryCounter"])
    assert seen == list(range(16)) + [0]


def test_cells_valid_is_the_count_it_is_given(project_db):
    """PackElectrical.CellsValid: ``cells_valid`` when given (the snapshot's cells with fresh inputs:
    two of three here, all three with a SOC), else the cells the statistics used."""
    enc = StateEncoder(project_db)
    _, el = enc.encode_pack_summary([0.4, 0.5, 0.6], -3.5, 11.1, cells_valid=2)
    d = project_db.decode_message(el.arbitration_id, el.data)
    assert (d["CellsValid"], d["PackCurrent"], d["PackVoltage"]) == (2, -3.5, 11.1)
    _, el = enc.encode_pack_summary([0.4, math.nan, 0.6])
    assert project_db.decode_message(el.arbitration_id, el.data)["CellsValid"] == 2


def test_soh_fractions_are_sent_in_percent(project_db):
    """PackHealth's SOH signals are in % (0.1 % steps): a fraction 0.953 is sent as 95.3 %."""
    enc = StateEncoder(project_db)
    frames = enc.encode_pack_sox({"soh_capacity_min": 0.953, "soh_resistance_max": 1.25, "capacity_ah_mean": 2.9})
    (health,) = [m for m in frames if m.arbitration_id == project_db.get_message_by_name("PackHealth").frame_id]
    d = project_db.decode_message(health.arbitration_id, health.data)
    assert d["SohCapacity"] == pytest.approx(95.3) and d["SohResistance"] == pytest.approx(125.0)
    assert d["CapacityMean"] == pytest.approx(2.9, abs=0.01)


def test_a_negative_value_below_the_top_of_the_frame_is_masked_to_its_bits(tmp_path):
    """The packer masks each raw value to its length (two's complement for a signed one): on a DBC
    whose signed C0 sits right after CellIndex (bits 11..25) instead of at the top of the word, -100 mV
    must leave Soc, R0 and R1 above it intact, byte for byte as cantools builds the frame."""
    text = (Path(__file__).resolve().parents[2] / "dbc" / "bms_estimator.dbc").read_text()
    for old, new in ((" SG_ Soc m0 : 11|12@1+", " SG_ Soc m0 : 26|12@1+"), (" SG_ R0 m0 : 23|13@1+", " SG_ R0 m0 : 38|13@1+"),
                     (" SG_ R1 m0 : 36|13@1+", " SG_ R1 m0 : 51|13@1+"), (" SG_ C0 m0 : 49|15@1-", " SG_ C0 m0 : 11|15@1-")):
        assert old in text
        text = text.replace(old, new)
    path = tmp_path / "c0_low.dbc"
    path.write_text(text)
    from bms_estimator.can.dbc import load_db

    db = load_db(path)
    vec, ref = StateEncoder(db), StateEncoder(db)
    ref._packers = {name: None for name in ref._packers}  # cantools, frame by frame
    assert vec._packers["CellStateA"] is not None
    args = ([0, 7], [0.5, 0.25], 0.01, 0.02, 1000.0, 0.004, 5000.0, [-0.1, 0.05])
    got, want = vec.encode_cells(*args), ref.encode_cells(*args)
    assert [bytes(m.data) for m in got] == [bytes(m.data) for m in want]
    d = db.decode_message(got[0].arbitration_id, got[0].data)
    assert (d["CellIndex"], d["Soc"], d["C0"]) == (0, 50.0, pytest.approx(-100.0))
    assert d["R0"] == pytest.approx(10.0, abs=0.008) and d["R1"] == pytest.approx(20.0, abs=0.008)


def test_a_large_cells_value_beyond_a_signal_is_counted_and_logged_once():
    """A 57 Ah cell (the LG HG2's identified model with current x 20: R1 0.33 mOhm, C1 30,400 F, C2 83,600 F)
    sent C1 as 13106.8 F, the DBC's end, with nothing to say so; CapacityMean ends at 65.534 Ah (a 100 Ah
    cell).  The frames still carry the range's end (the value policy), and the clamp is counted and logged
    once per signal."""
    from structlog.testing import capture_logs

    enc = StateEncoder(DB)
    with capture_logs() as logs:
        for _ in range(3):
            frames = enc.encode_cells([0, 1], 0.5, 1.0e-3, 3.3e-4, [30400.0, 2000.0], 1.0e-3, 83600.0, 0.0)
        enc.encode_pack_sox({"capacity_ah_mean": 100.0})
    c1 = DB.decode_message(frames[1].arbitration_id, frames[1].data)["C1"]
    assert c1 == pytest.approx(13106.8)  # still clamped, as documented
    assert enc.clamped_values == 3 + 1
    clamped = [e for e in logs if e["event"].startswith("can.encode.clamped")]
    assert [(e["signal"], e["log_level"]) for e in clamped] == [("C1", "warning"), ("CapacityMean", "warning")]
    assert clamped[0]["value"] == pytest.approx(30400.0) and clamped[0]["range"] == "0..13106.8"
    # an 18650's model is within every range: nothing counted
    quiet = StateEncoder(DB)
    quiet.encode_cells([0], 0.5, 0.0203, 0.0065, 1518.0, 0.0192, 4179.0, 0.005)
    assert quiet.clamped_values == 0


def test_a_time_to_empty_of_68_h_and_more_is_the_dbcs_own_value_not_a_clamp_to_warn_about():
    """``TimeToEmpty``/``TimeToFull`` end at 4094 min, which the DBC defines as "not discharging or 68 h and
    more": a pack at rest or idling (an 18650 pack of the example configuration, 5,815 min at its mean
    current after a drive) sends 4094 as meant. The clamp warning added for cells the DBC's ranges were not
    made for fired at every such start ("a cell the DBC was not scaled for? can.dbc takes one that is"), a
    false alarm pointing at a DBC change that leaves those two signals as they are. They saturate silently;
    a value really beyond its range is still counted and logged."""
    from structlog.testing import capture_logs

    enc = StateEncoder(DB)
    with capture_logs() as logs:
        (frame,) = [m for m in enc.encode_pack_sox({"time_to_empty_s": 5814.6 * 60.0, "time_to_full_s": 1e7})
                    if m.arbitration_id == DB.get_message_by_name("PackEnergy").frame_id]
    d = DB.decode_message(frame.arbitration_id, frame.data)
    assert d["TimeToEmpty"] == 4094 and d["TimeToFull"] == 4094
    assert enc.clamped_values == 0 and not [e for e in logs if e["event"].startswith("can.encode.clamped")]
    with capture_logs() as logs:
        enc.encode_pack_sox({"capacity_ah_mean": 100.0})
    assert enc.clamped_values == 1 and [e["signal"] for e in logs] == ["CapacityMean"]


def test_the_large_cell_dbc_is_the_project_dbc_with_a_large_cells_scalings():
    """``can.dbc = "large-cell"`` is the project DBC frame for frame and bit for bit (a receiver switches by its
    scalings alone); only R0, R1, R2, C1, C2 and CapacityMean differ, and there only in factor and range."""
    from bms_estimator.can.dbc import load_db

    large = load_db("large-cell")
    assert [(m.name, m.frame_id, m.length) for m in large.messages] == \
        [(m.name, m.frame_id, m.length) for m in DB.messages]
    scaled = set()
    for m in DB.messages:
        for sig in m.signals:
            other = large.get_message_by_name(m.name).get_signal_by_name(sig.name)
            assert (other.start, other.length, other.is_signed, other.byte_order, other.unit, other.offset) == \
                (sig.start, sig.length, sig.is_signed, sig.byte_order, sig.unit, sig.offset)
            assert other.choices == sig.choices  # the same NotAvailable raw values
            if (other.scale, other.maximum) != (sig.scale, sig.maximum):
                scaled.add(sig.name)
                raw_top = round(sig.maximum / sig.scale)
                assert round(other.maximum / other.scale) == raw_top  # the same raw range, another step
    assert scaled == {"R0", "R1", "R2", "C1", "C2", "CapacityMean"}


def test_a_large_cell_goes_out_unclamped_and_fine_on_the_large_cell_dbc():
    """A 57 Ah cell (the LG HG2 model with current x 20: R0 1.0145 mOhm, R1 0.33 mOhm, C1 30,400 F, R2 0.96 mOhm,
    C2 83,600 F; 56 Ah capacity) was clamped (C1) or coarse (R1 in 8 uOhm steps, 2.4 %) on the project DBC; on the
    large-cell one every value is within one step of 2 uOhm / 0.5 uOhm / 5 F / 50 F / 10 mAh, none clamped."""
    from bms_estimator.can.dbc import load_db

    large = load_db("large-cell")
    enc = StateEncoder(large)
    frames = enc.encode_cells([7], 0.5, 1.0145e-3, 3.3e-4, 30400.0, 9.6e-4, 83600.0, 0.002)
    a = large.decode_message(frames[0].arbitration_id, frames[0].data)
    b = large.decode_message(frames[1].arbitration_id, frames[1].data)
    assert a["R0"] == pytest.approx(1.0145, abs=0.001) and a["R1"] == pytest.approx(0.33, abs=0.001)
    assert b["C1"] == pytest.approx(30400.0, abs=2.5) and b["C2"] == pytest.approx(83600.0, abs=25.0)
    assert b["R2"] == pytest.approx(0.96, abs=0.00025)
    pack = enc.encode_pack_sox({"capacity_ah_mean": 56.01})
    health = [large.decode_message(f.arbitration_id, f.data) for f in pack
              if f.arbitration_id == large.get_message_by_name("PackHealth").frame_id]
    assert health and health[0]["CapacityMean"] == pytest.approx(56.01, abs=0.005)
    assert enc.clamped_values == 0
    # the same cell on the project DBC: C1 clamped, R1 off by a step of 8 uOhm
    small = StateEncoder(DB)
    frames = small.encode_cells([7], 0.5, 1.0145e-3, 3.3e-4, 30400.0, 9.6e-4, 83600.0, 0.002)
    assert small.clamped_values == 1
    assert DB.decode_message(frames[0].arbitration_id, frames[0].data)["R1"] == pytest.approx(0.328)


def test_an_unknown_file_name_is_still_a_file_and_a_shipped_name_is_found_from_anywhere(tmp_path, monkeypatch):
    from bms_estimator.can.dbc import load_db

    monkeypatch.chdir(tmp_path)
    assert load_db("large-cell").get_message_by_name("CellStateB").get_signal_by_name("C1").scale == 5
    with pytest.raises(OSError):
        load_db("larger-cell")
