"""replay: pacing by the log's timestamps, and receivers see the LOG's timestamps at any speed."""

from __future__ import annotations

import itertools
import math
import threading
import time

import can
import numpy as np
import pytest
from replay_helpers import N_CELLS

from bms_estimator.can.bus import BusConfig
from bms_estimator.can.dbc import load_project_db
from bms_estimator.can.decoder import FrameDecoder
from bms_estimator.can.sampler import SampleAssembler
from bms_estimator.cli.__main__ import main
from bms_estimator.replay.replay import (
    LogTimeUdpMulticastBus,
    log_span,
    open_bus_log_time,
    open_replay_bus,
    parse_speed,
    read_log,
    replay_messages,
)

_ids = itertools.count()


def _channel() -> str:
    return f"bms-replay-test-{time.monotonic_ns()}-{next(_ids)}"


def _first(path, seconds: float) -> list[can.Message]:
    return [m for m in read_log(path) if m.timestamp < seconds]


def _key(m: can.Message) -> tuple:
    return (m.arbitration_id, m.is_extended_id, bytes(m.data), m.timestamp)


def _replay_virtual(messages: list[can.Message], speed) -> tuple[list[can.Message], object]:
    """Replay onto a fresh virtual channel; a plain python-can receiver collects what it sees."""
    ch = _channel()
    rx = can.Bus(interface="virtual", channel=ch)
    tx = open_replay_bus("virtual", ch)
    try:
        stats = replay_messages(messages, tx, speed)
        got = []
        while (m := rx.recv(0)) is not None:
            got.append(m)
    finally:
        tx.shutdown()
        rx.shutdown()
    return got, stats


def _samples(messages: list[can.Message]) -> list:
    dec = FrameDecoder(load_project_db(), "default", N_CELLS)
    sa = SampleAssembler(N_CELLS)
    out = []
    for m in messages:
        out.extend(sa.feed_frame(dec.decode(m), m.timestamp))
    return out


def test_same_frames_and_timestamps_at_every_speed(encoded):
    log = _first(encoded["log"], 2.0)  # 2 s of bus traffic, 264 frames
    expect = [_key(m) for m in log]
    results = {}
    for speed in ("max", 50, 1):
        msgs = _first(encoded["log"], 2.0)  # fresh objects: the replayer clears their channel
        for m in msgs:
            m.channel = "can7"  # a logged channel must not leak into the send
        got, stats = _replay_virtual(msgs, speed)
        assert all(m.channel is None for m in msgs)
        results[speed] = [_key(m) for m in got]
        assert stats.sent == len(log) and stats.send_errors == 0
        assert stats.first_log_s == 0.0 and stats.last_log_s == log[-1].timestamp
        if speed != "max":  # paced: never faster than asked (lower bound only; a slow machine is later)
            assert stats.wall_s >= 0.95 * log[-1].timestamp / speed
    assert results["max"] == expect
    assert results[50] == expect
    assert results[1] == expect


def test_service_samples_are_identical_at_max_and_50x(encoded):
    log = _first(encoded["log"], 20.0)
    got_max, _ = _replay_virtual(log, "max")
    got_50, _ = _replay_virtual(log, 50)
    a, b = _samples(got_max), _samples(got_50)
    assert len(a) == 19
    for x, y in zip(a, b, strict=True):
        assert x.t_s == y.t_s and x.current_a == y.current_a
        np.testing.assert_array_equal(x.cell_voltage_v, y.cell_voltage_v)
        np.testing.assert_array_equal(x.valid, y.valid)
    assert all(s.valid.all() for s in a)


def test_asc_and_blf_logs_replay_like_the_candump_log(encoded):
    d = encoded["dir"]
    from bms_estimator.replay.encode_log import write_messages

    log = _first(encoded["log"], 3.0)
    for suffix in (".asc", ".blf"):
        path = d / f"replay_input{suffix}"
        write_messages(log, path)
        got, stats = _replay_virtual(list(read_log(path)), "max")
        assert stats.sent == len(log)
        assert [_key(m)[:3] for m in got] == [_key(m)[:3] for m in log]
        np.testing.assert_allclose([m.timestamp for m in got], [m.timestamp for m in log], atol=1e-6)
    assert log_span(encoded["log"]) == (0.0, pytest.approx(599.99))


def test_stop_event_ends_a_real_time_replay(encoded):
    log = _first(encoded["log"], 30.0)
    stop = threading.Event()
    threading.Timer(0.2, stop.set).start()
    ch = _channel()
    tx = open_replay_bus("virtual", ch)
    try:
        t0 = time.monotonic()
        stats = replay_messages(log, tx, 1.0, stop=stop)
    finally:
        tx.shutdown()
    assert stats.stopped and 0 < stats.sent < len(log)
    assert time.monotonic() - t0 < 5


@pytest.mark.parametrize("speed", [1e-300, 1e-12], ids=["tiny-speed", "slow-speed-over-a-clock-jump"])
def test_a_wait_longer_than_the_clock_can_sleep_is_waited_not_a_traceback(speed):
    """A frame due further ahead than time.sleep/Event.wait accept (about 292 years: a tiny --speed, or a
    log whose clock jumps from boot time to epoch time at a slow one) is waited for, in slices, until the
    stop event; before, the wait raised OverflowError ("timestamp out of range for platform time_t") and
    the command ended in a traceback."""
    jump = 1.0 if speed < 1e-100 else 1.7e9  # 1e300 s ahead, or 1.7e21 s
    msgs = [can.Message(timestamp=t, arbitration_id=0x100, data=b"\x01") for t in (5.0, 5.0 + jump)]
    stop = threading.Event()
    threading.Timer(0.2, stop.set).start()
    tx = open_replay_bus("virtual", _channel())
    try:
        stats = replay_messages(msgs, tx, speed, stop=stop)
    finally:
        tx.shutdown()
    assert stats.stopped and stats.sent == 1 and stats.send_errors == 0


def test_progress_callback_and_speed_parsing(encoded):
    log = _first(encoded["log"], 5.0)
    calls = []
    ch = _channel()
    tx = open_replay_bus("virtual", ch)
    try:
        replay_messages(log, tx, "max", progress=lambda n, t: calls.append((n, t)))
    finally:
        tx.shutdown()
    assert calls[-1] == (len(log), log[-1].timestamp)
    assert parse_speed("max") == math.inf and parse_speed("50") == 50.0 and parse_speed("0.5x") == 0.5
    for bad in ("0", "-1", "fast", "nan"):
        with pytest.raises(ValueError):
            parse_speed(bad)


def test_replay_command_on_a_virtual_bus(encoded, tmp_path, capsys):
    log = _first(encoded["log"], 1.0)
    from bms_estimator.replay.encode_log import write_messages

    path = tmp_path / "short.log"
    write_messages(log, path)
    ch = _channel()
    rx = can.Bus(interface="virtual", channel=ch)
    try:
        rc = main(["replay", str(path), "--interface", "virtual", "--channel", ch, "--speed", "max"])
        got = []
        while (m := rx.recv(0)) is not None:
            got.append(m)
    finally:
        rx.shutdown()
    assert rc == 0
    assert [_key(m) for m in got] == [_key(m) for m in log]
    assert f"{len(log)} frames" in capsys.readouterr().out
    assert main(["replay", str(tmp_path / "missing.log")]) == 3  # a data error


@pytest.mark.parametrize("name, content, message", [
    ("empty.log", b"", "empty.log: empty log (the file is 0 bytes): no CAN frame in it"),
    # python-can's BLF reader said "unpack requires a buffer of 72 bytes"
    ("empty.blf", b"", "empty.blf: empty log (the file is 0 bytes): no CAN frame in it"),
    ("empty.asc", b"", "empty.asc: empty log (the file is 0 bytes): no CAN frame in it"),
    ("blank.log", b"\n", "blank.log: no CAN frame in the log"),
    ("words.log", b"hello world\n", "words.log: unreadable after 0 frames at line 1, 'hello world', not a candump -L "
                                     "frame '(time) channel id#data' (ValueError: "),
    ("bad.blf", b"garbage\n", "bad.blf: unreadable as a CAN log ("),
    ("late.log", b"(1.000000) can0 123#00\n\n(1.010000) can0 123#01\nnonsense\n",
     "late.log: unreadable after 2 frames at line 4, 'nonsense', not a candump -L frame"),
    # cut in the middle of its last frame's data: python-can sent 123#0011 as a 2-byte frame
    ("cut.log", b"(1.000000) can0 123#0011223344556677\n(1.010000) can0 123#0011", "cut.log: its last line has no line end"),
])
def test_replay_of_an_unreadable_or_empty_log_is_a_data_error(tmp_path, capsys, name, content, message):
    """Each was exit 2 with python-can's bare message ('not enough values to unpack'), or exit 0 having sent
    nothing; now one line naming the file (exit 3)."""
    path = tmp_path / name
    path.write_bytes(content)
    assert main(["replay", str(path), "-i", "virtual", "-c", _channel(), "--speed", "max", "--no-progress"]) == 3
    err = capsys.readouterr().err
    assert err.startswith(f"bms-estimator replay: error: {path}") and message in err, err
    assert len(err.strip().splitlines()) == 1


@pytest.mark.parametrize("suffix, message", [(".blf", "truncated BLF file"), (".asc", "truncated ASC file")])
def test_replay_of_a_truncated_log_is_refused_before_sending(tmp_path, capsys, suffix, message):
    """python-can stops quietly at the cut of a .blf or .asc: replay sent the first part with exit 0."""
    path = tmp_path / f"cut{suffix}"
    with can.Logger(str(path)) as w:
        for k in range(2000):
            w.on_message_received(can.Message(timestamp=1.0 + 0.01 * k, arbitration_id=0x100, data=bytes(8)))
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    ch = _channel()
    rx = can.Bus(interface="virtual", channel=ch)
    try:
        assert main(["replay", str(path), "-i", "virtual", "-c", ch, "--speed", "max", "--no-progress"]) == 3
        assert rx.recv(0) is None  # nothing went out
    finally:
        rx.shutdown()
    assert f"{path}: {message}" in capsys.readouterr().err


def test_udp_multicast_receiver_keeps_the_log_time(encoded):
    """python-can's udp_multicast receiver stamps frames on arrival; LogTimeUdpMulticastBus keeps the log's."""
    log = _first(encoded["log"], 1.0)
    group, port = "239.74.163.9", 43000 + (time.monotonic_ns() // 1000) % 2000
    try:
        rx = open_bus_log_time(BusConfig(interface="udp_multicast", channel=group, options={"port": port}))
        plain = can.Bus(interface="udp_multicast", channel=group, port=port)
        tx = open_replay_bus("udp_multicast", group, port=port)
    except (OSError, can.CanError) as exc:
        pytest.skip(f"no IPv4 multicast on this machine: {exc}")
    assert isinstance(rx, LogTimeUdpMulticastBus)
    try:
        got: list[can.Message] = []

        def receive() -> None:
            while len(got) < len(log):
                m = rx.recv(2.0)
                if m is None:
                    return
                got.append(m)

        th = threading.Thread(target=receive)
        th.start()
        stats = replay_messages(_first(encoded["log"], 1.0), tx, 20)
        th.join(10)
        if not got:
            pytest.skip("multicast datagrams are not looped back on this machine")
        assert stats.sent == len(log)
        assert [_key(m) for m in got] == [_key(m) for m in log]
        first_plain = plain.recv(1.0)
        assert first_plain is not None and abs(first_plain.timestamp - time.time()) < 60  # wall clock, not log
    finally:
        for b in (rx, plain, tx):
            b.shutdown()


def test_open_bus_log_time_leaves_other_interfaces_to_the_service():
    ch = _channel()
    bus = open_bus_log_time(BusConfig(interface="virtual", channel=ch))
    try:
        assert type(bus).__name__ == "VirtualBus"
    finally:
        bus.shutdown()
