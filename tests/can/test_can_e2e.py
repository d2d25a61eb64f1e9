"""End-to-end checks of input frames (issue 16): alive counter and CRC, each failure dropped and counted."""

from __future__ import annotations

import can
import cantools
import pytest

from bms_estimator.can.decoder import EventKind, FrameDecoder
from bms_estimator.can.e2e import crc8_autosar, crc8_sae_j1850, sum8, xor8
from bms_estimator.can.mapping import MappingError, load_mapping, mapping_to_dict

from bmscan_helpers import fox_current_frame, frame, own_current_frame


def _with_e2e(preset: str, e2e: dict) -> dict:
    m = mapping_to_dict(load_mapping(preset))
    m["e2e"] = e2e
    return m


def test_crc_algorithms_give_their_published_check_values():
    """The catalogue's check value: the CRC of the ASCII bytes '123456789'."""
    assert crc8_sae_j1850(b"123456789") == 0x4B
    assert crc8_autosar(b"123456789") == 0xDF
    assert xor8(b"\x01\x02\x04") == 0x07 and sum8(b"\xff\x02") == 0x01


def _own(db, current_a: float, counter: int) -> can.Message:
    msg = own_current_frame(db, current_a)
    m = db.get_message_by_name("PackMeasurement")
    values = m.decode(msg.data)
    values["MeasurementCounter"] = counter
    return frame(db, "PackMeasurement", values)


@pytest.mark.parametrize("bit_fields", [True, False])
def test_a_skipped_or_repeated_counter_value_is_dropped_and_counted(project_db, bit_fields):
    """The project DBC's MeasurementCounter, evaluated when the mapping names it, on the decoder's
    bit-field path (which reads the counter although no mapping entry does) and through cantools."""
    dec = FrameDecoder(project_db, _with_e2e("default", {"PackMeasurement": {"counter": "MeasurementCounter"}}), 1,
                       bit_fields=bit_fields)
    assert any(p.fields is not None for p in dec._plans.values()) is bit_fields
    counters = [13, 14, 15, 0, 1, 3, 4, 4, 5]  # wraps 15 -> 0; skips 2; repeats 4
    currents = [float(k) for k in range(len(counters))]
    got = []
    for i, c in zip(currents, counters):
        got.append([e.value for e in dec.decode(_own(project_db, i, c)) if e.kind == EventKind.CURRENT])
    assert got == [[0.0], [1.0], [2.0], [3.0], [4.0], [], [6.0], [], [8.0]]
    assert dec.counters.e2e_counter == 2
    assert dec.counters.errors == 2


@pytest.mark.parametrize("bit_fields", [True, False])
def test_a_sender_that_wakes_with_its_counters_restarted_is_not_a_counter_failure(project_db, bit_fields):
    """A BMS that sleeps while the vehicle is parked wakes with its alive counters restarted: the first
    frame of every counter group (one per cell group on a multiplexed message: about 100 frames for 200
    cells) was dropped and counted as ``e2e_counter``, a false alarm at every wake. A frame more than
    ``E2E_RESYNC_S`` (5 s, the sampler's gap) of frame time after the previous one of its group starts
    the count afresh; within it, a restarted counter is still a failure."""
    from bms_estimator.can.e2e import E2E_RESYNC_S

    dec = FrameDecoder(project_db, _with_e2e("default", {"PackMeasurement": {"counter": "MeasurementCounter"}}), 1,
                       bit_fields=bit_fields)

    def at(t: float, current_a: float, counter: int) -> can.Message:
        m = _own(project_db, current_a, counter)
        m.timestamp = t
        return m

    stream = [at(0.1 * k, 1.0, (7 + k) % 16) for k in range(5)]  # counters 7..11
    stream += [at(0.4 + 600.0, 2.0, 0), at(0.5 + 600.0, 2.0, 1)]  # asleep 10 min, counters restarted
    stream += [at(0.6 + 600.0 + E2E_RESYNC_S - 0.2, 3.0, 0)]  # restarted again after less than 5 s: a failure
    got = [[e.value for e in dec.decode(m) if e.kind == EventKind.CURRENT] for m in stream]
    assert got == [[1.0]] * 5 + [[2.0], [2.0], []]
    assert dec.counters.e2e_counter == 1


def test_without_e2e_the_counter_is_not_evaluated(project_db):
    dec = FrameDecoder(project_db, _with_e2e("default", {}), 1)
    assert all(dec.decode(_own(project_db, 1.0, 0)) for _ in range(3))
    assert dec.counters.e2e_counter == 0


def test_the_project_preset_checks_every_input_frame_by_default():
    e2e = load_mapping("default").e2e
    assert {k: (v.counter, v.crc, v.crc_algorithm if v.crc else None) for k, v in e2e.items()} == {
        "PackMeasurement": ("MeasurementCounter", "MeasurementCrc", "crc8_sae_j1850"),
        "CellVoltages": ("VoltageCounter", None, None),
        "CellTemperatures": ("TemperatureCounter", None, None),
    }
    assert load_mapping("bms_estimator") == load_mapping("default")


def _stamped_current(db, stamper, current_a: float, t: float) -> can.Message:
    m = db.get_message_by_name("PackMeasurement")
    data = m.encode({"PackCurrent": current_a, "PackVoltage": 400.0, "MeasurementCounter": 0, "CurrentInvalid": 0,
                     "VoltageInvalid": 0, "MeasurementCrc": 0})
    return can.Message(timestamp=t, arbitration_id=m.frame_id, is_extended_id=True,
                       data=stamper.stamp(m.frame_id, data))


@pytest.mark.parametrize("spoof_a", [5000.0, -5000.0, 4999.999])
def test_a_spoofed_in_range_current_never_reaches_a_sample(project_db, spoof_a):
    """The default mapping on the project DBC: an injected frame with an in-range +-5000 A current
    and a wrong CRC (the sender's next counter value, as a spoofer would guess it) is dropped and
    counted; the 1 s sample's current is the real sender's 10 A."""
    from bms_estimator.can.e2e import E2EStamper
    from bms_estimator.can.sampler import SampleAssembler

    stamper = E2EStamper(project_db, "default")
    dec, smp = FrameDecoder(project_db, "default", 1), SampleAssembler(1)
    m = project_db.get_message_by_name("PackMeasurement")
    samples = []
    for k in range(201):
        t = 100.0 + 0.01 * k
        samples += smp.feed_frame(dec.decode(_stamped_current(project_db, stamper, 10.0, t)), t)
        if k in (30, 130):
            real = bytearray(m.encode({"PackCurrent": spoof_a, "PackVoltage": 400.0, "MeasurementCounter": 0,
                                       "CurrentInvalid": 0, "VoltageInvalid": 0, "MeasurementCrc": 0}))
            real = bytearray(stamper.stamp(m.frame_id, bytes(real)))
            stamper.stamp(m.frame_id, bytes(real), counter=(real[6] & 0xF) - 1)  # the spoofer's guess is not sent
            real[7] ^= 0x5A  # ...and its CRC is wrong
            samples += smp.feed_frame(dec.decode(can.Message(timestamp=t + 0.005, arbitration_id=m.frame_id,
                                                             is_extended_id=True, data=bytes(real))), t + 0.005)
    assert dec.counters.e2e_crc == 2 and dec.counters.e2e_counter == 0 and dec.counters.errors == 2
    assert len(samples) == 2 and all(s.current_a == pytest.approx(10.0) for s in samples)


def test_a_skipped_counter_value_on_the_default_mapping_is_counted(project_db):
    from bms_estimator.can.e2e import E2EStamper

    stamper = E2EStamper(project_db, "default")
    dec = FrameDecoder(project_db, "default", 1)
    got = []
    for k in range(6):
        msg = _stamped_current(project_db, stamper, float(k), 0.01 * k)
        if k == 3:
            _stamped_current(project_db, stamper, 0.0, 0.0)  # one frame lost on the bus
            msg = _stamped_current(project_db, stamper, float(k), 0.01 * k)
        got.append([e.value for e in dec.decode(msg) if e.kind == EventKind.CURRENT])
    assert got == [[0.0], [1.0], [2.0], [], [4.0], [5.0]]
    assert dec.counters.e2e_counter == 1 and dec.counters.e2e_crc == 0


def test_the_stamper_writes_what_the_decoder_checks(project_db):
    """E2EStamper's scalar and array forms give the same bytes; crc_rows equals the scalar CRC."""
    import numpy as np

    from bms_estimator.can.e2e import CRC_ALGORITHMS, E2EStamper, crc_rows

    rng = np.random.default_rng(4)
    rows = rng.integers(0, 256, (300, 7), dtype=np.uint8)
    for name, fn in CRC_ALGORITHMS.items():
        assert crc_rows(name, rows).tolist() == [fn(bytes(r)) for r in rows], name
    for name in ("PackMeasurement", "CellVoltages"):
        fid = project_db.get_message_by_name(name).frame_id
        payload = rng.integers(0, 2**63, 200, dtype=np.int64).astype(np.uint64)
        if name == "CellVoltages":
            payload &= ~np.uint64(0xFFF)
            payload |= rng.integers(0, 4, 200).astype(np.uint64)  # four multiplexer values
        a, b = E2EStamper(project_db), E2EStamper(project_db)
        bulk = a.stamp_rows(fid, payload[:120])
        bulk = np.concatenate([bulk, a.stamp_rows(fid, payload[120:])])  # the counters run on
        one = [b.stamp(fid, int(p).to_bytes(8, "little")) for p in payload]
        assert [int(x).to_bytes(8, "little") for x in bulk] == one
        dec = FrameDecoder(project_db, "default", 12)
        for d in one:
            dec.decode(can.Message(arbitration_id=fid, is_extended_id=True, data=d))
        assert (dec.counters.e2e_counter, dec.counters.e2e_crc) == (0, 0)


def test_foxbms_ivt_message_counter(foxbms_db):
    """foxBMS' own scheme: the IVT-S current frame's 4-bit IVT_MsgCount_Result_I (its DBC has no CRC)."""
    mapping = _with_e2e("foxbms", {"CS_IsabellenhuetteIvtString0Curr": {"counter": "IVT_MsgCount_Result_I"}})
    dec = FrameDecoder(foxbms_db, mapping, 4)

    def fox(ma: int, count: int) -> can.Message:
        msg = fox_current_frame(foxbms_db, ma)
        m = foxbms_db.get_message_by_name("CS_IsabellenhuetteIvtString0Curr")
        values = m.decode(msg.data)
        values["IVT_MsgCount_Result_I"] = count
        return frame(foxbms_db, "CS_IsabellenhuetteIvtString0Curr", values)

    out = [len(dec.decode(fox(1000 * k, c))) for k, c in enumerate([7, 8, 10, 11])]
    assert out == [1, 1, 0, 1]
    assert dec.counters.e2e_counter == 1


_CRC_DBC = """VERSION ""
BO_ 2566914048 Meas: 8 BMS
 SG_ Current : 0|32@1- (0.001,0) [-2147483.647|2147483.647] "A" X
 SG_ Voltage : 32|16@1+ (0.01,0) [0|655.35] "V" X
 SG_ Counter : 48|4@1+ (1,0) [0|15] "" X
 SG_ Crc : 56|8@1+ (1,0) [0|255] "" X
BO_ 2566914049 Cells: 8 BMS
 SG_ Base M : 0|16@1+ (1,0) [0|1999] "" X
 SG_ V0 m0 : 16|16@1+ (0.0001,0) [0|6.5534] "V" X
"""


@pytest.fixture
def crc_db(tmp_path):
    path = tmp_path / "crc.dbc"
    path.write_text(_CRC_DBC)
    return cantools.database.load_file(str(path))


def _crc_mapping(algorithm: str = "crc8_sae_j1850") -> dict:
    return {
        "current": {"message": "Meas", "signal": "Current"},
        "cell_voltages": [{"message": "Cells", "signal_pattern": r"V(?P<slot>\d+)", "mux_stride": 1}],
        "e2e": {"Meas": {"counter": "Counter", "crc": "Crc", "crc_algorithm": algorithm}},
    }


def _meas(db, current_a: float, counter: int, *, crc=crc8_sae_j1850, corrupt: bool = False) -> can.Message:
    m = db.get_message_by_name("Meas")
    data = bytearray(m.encode({"Current": current_a, "Voltage": 400.0, "Counter": counter, "Crc": 0}))
    data[7] = crc(bytes(data[:7]))
    if corrupt:
        data[2] ^= 0x10  # one flipped bit in the current
    return can.Message(arbitration_id=m.frame_id, is_extended_id=True, data=bytes(data))


@pytest.mark.parametrize("algorithm", ["crc8_sae_j1850", "crc8_autosar", "xor8", "sum8"])
def test_a_bad_crc_is_dropped_and_counted(crc_db, algorithm):
    from bms_estimator.can.e2e import CRC_ALGORITHMS

    crc = CRC_ALGORITHMS[algorithm]
    dec = FrameDecoder(crc_db, _crc_mapping(algorithm), 1)
    good = dec.decode(_meas(crc_db, -12.5, 0, crc=crc))
    assert [e.value for e in good] == [pytest.approx(-12.5)]
    bad = _meas(crc_db, -12.5, 1, crc=crc, corrupt=True)  # a corrupted in-range current
    assert dec.decode(bad) == []
    assert dec.counters.e2e_crc == 1 and dec.counters.e2e_counter == 0
    # the corrupted frame did not advance the counter: 1 is still the next one
    assert [e.value for e in dec.decode(_meas(crc_db, 3.0, 1, crc=crc))] == [pytest.approx(3.0)]
    assert dec.counters.errors == 1


def test_a_spoofed_frame_with_a_wrong_crc_is_not_a_measurement(crc_db):
    """An injected +-5000 A frame (in range for the mapping) without the right CRC is dropped."""
    dec = FrameDecoder(crc_db, _crc_mapping(), 1)
    assert dec.decode(_meas(crc_db, 10.0, 5))
    m = crc_db.get_message_by_name("Meas")
    spoof = can.Message(arbitration_id=m.frame_id, is_extended_id=True,
                        data=m.encode({"Current": 5000.0, "Voltage": 400.0, "Counter": 6, "Crc": 0}))
    assert dec.decode(spoof) == []
    assert dec.counters.e2e_crc == 1


def test_e2e_mapping_problems_are_named(crc_db, project_db):
    bad = _crc_mapping()
    bad["e2e"] = {"Meas": {"crc": "Voltage"}}  # 16 bit
    with pytest.raises(MappingError) as exc:
        FrameDecoder(crc_db, bad, 1)
    assert "e2e.Meas: crc 'Voltage' must be 8 bit, byte aligned" in str(exc.value.problems)
    with pytest.raises(MappingError) as exc:
        FrameDecoder(project_db, _with_e2e("default", {"CellStateA": {"counter": "CellIndex"}}), 1)
    assert "e2e.CellStateA: not an input message of this mapping" in str(exc.value.problems)
    with pytest.raises(MappingError) as exc:
        load_mapping(_with_e2e("default", {"PackMeasurement": {}}))
    assert "name a counter, a crc, or both" in str(exc.value.problems)



def test_a_frame_exactly_the_resync_time_after_the_previous_is_still_checked(project_db):
    """Only a frame MORE than ``E2E_RESYNC_S`` after the previous one of its group starts afresh:
    a restarted counter exactly 5 s later is a counter failure; one 5.5 s after that is accepted."""
    from bms_estimator.can.e2e import E2E_RESYNC_S

    dec = FrameDecoder(project_db, _with_e2e("default", {"PackMeasurement": {"counter": "MeasurementCounter"}}), 1)

    def at(t: float, current_a: float, counter: int) -> can.Message:
        m = _own(project_db, current_a, counter)
        m.timestamp = t
        return m

    stream = [at(2.0, 1.0, 7), at(2.0 + E2E_RESYNC_S, 2.0, 0), at(2.0 + E2E_RESYNC_S + 5.5, 3.0, 9)]
    got = [[e.value for e in dec.decode(m) if e.kind == EventKind.CURRENT] for m in stream]
    assert got == [[1.0], [], [3.0]]
    assert dec.counters.e2e_counter == 1
