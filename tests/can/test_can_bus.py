"""Real python-can buses: virtual (in-process), udp_multicast (two processes in a netns), socketcan/vcan."""

from __future__ import annotations

import asyncio
import errno
import json
import os
import shutil
import socket
import subprocess
import sys
import textwrap
import time
import uuid
from pathlib import Path

import can
import numpy as np
import pytest
from can.interfaces.virtual import VirtualBus

from bms_estimator.can.bus import BusConfig, ResilientBus, open_bus
from bms_estimator.can.dbc import load_project_db
from bms_estimator.can.decoder import FrameDecoder
from bms_estimator.can.sampler import SampleAssembler

from bmscan_helpers import own_current_frame, own_voltage_frame

REPO_ROOT = Path(__file__).resolve().parents[2]
DB = load_project_db()


def run(coro, timeout: float = 30.0):
    async def guarded():
        return await asyncio.wait_for(coro, timeout)

    return asyncio.run(guarded())


def channel() -> str:
    return f"bmsest-{uuid.uuid4().hex[:8]}"


def fast(cfg: BusConfig, **kw) -> BusConfig:
    return cfg.model_copy(update={"reopen_initial_s": 0.01, "reopen_max_s": 0.05, **kw})


def make_stream(n_cells: int, seconds: float, t0: float = 500.0) -> list[can.Message]:
    msgs = []
    for k in range(int(seconds * 100)):
        t = t0 + k * 0.01
        msgs.append(own_current_frame(DB, 10.0 if (k // 50) % 2 else -5.0, t, voltage_v=3.7 * n_cells))
        if k % 10 == 3:
            for base in range(0, n_cells, 3):
                volts = [3.6 + 0.01 * c + 0.001 * (k % 7) for c in range(base, base + 3)]
                msgs.append(own_voltage_frame(DB, base, volts, t + 0.001))
    return msgs


def assemble(msgs, n_cells: int):
    dec = FrameDecoder(DB, "default", n_cells)
    smp = SampleAssembler(n_cells)
    out = []
    for m in msgs:
        out += smp.feed_frame(dec.decode(m), m.timestamp)
    return out, dec


def assert_same_samples(a, b):
    assert len(a) == len(b) > 0
    for x, y in zip(a, b):
        assert x.t_s == y.t_s and x.current_a == y.current_a
        np.testing.assert_array_equal(x.cell_voltage_v, y.cell_voltage_v)
        np.testing.assert_array_equal(x.valid, y.valid)


# ------------------------------------------------------------- virtual bus
def test_open_bus_passes_the_config():
    ch = channel()
    bus = open_bus(BusConfig(interface="virtual", channel=ch, bitrate=500_000, options={"preserve_timestamps": True}))
    try:
        assert bus.channel_info.endswith(ch) or ch in str(bus.channel_info)
        assert bus.preserve_timestamps
    finally:
        bus.shutdown()


def test_virtual_bus_receive_decode_and_send():
    n = 6
    ch = channel()
    stream = make_stream(n, 3.0)

    async def main():
        cfg = BusConfig(interface="virtual", channel=ch)
        sender = can.Bus(interface="virtual", channel=ch, preserve_timestamps=True)
        listener = None
        received = []
        try:
            async with ResilientBus(cfg) as rx:
                assert await rx.wait_open(5)
                for m in stream:
                    sender.send(m)
                while len(received) < len(stream):
                    received.append(await rx.recv())
                listener = can.Bus(interface="virtual", channel=ch)
                # and the send path: frames queued on rx reach another node
                out = [own_current_frame(DB, 1.0, 0.0)] * 5
                assert rx.send_many(out) == 5
                assert await rx.drain(5)
                got = [listener.recv(1.0) for _ in range(5)]
                assert listener.recv(0) is None
                assert all(g is not None and g.arbitration_id == out[0].arbitration_id for g in got)
                assert rx.counters.tx_frames == 5 and rx.counters.rx_frames == len(stream)
        finally:
            sender.shutdown()
            if listener is not None:
                listener.shutdown()
        return received

    received = run(main())
    assert [m.timestamp for m in received] == [m.timestamp for m in stream]
    direct, _ = assemble(stream, n)
    via_bus, dec = assemble(received, n)
    assert_same_samples(direct, via_bus)
    assert dec.counters.errors == 0 and len(via_bus) == 2
    assert via_bus[0].valid.all()
    # the last voltage frames before the end of the last period (t = 502 s) are those of tick k = 193
    k_last = max(k for k in range(300) if k % 10 == 3 and 500.0 + k * 0.01 + 0.001 < via_bus[-1].t_s)
    assert k_last == 193
    np.testing.assert_allclose(via_bus[-1].cell_voltage_v, [3.6 + 0.01 * c + 0.001 * (k_last % 7) for c in range(n)],
                               atol=1e-4)


@pytest.mark.parametrize("speedup", [None, 40.0])
def test_replay_speed_does_not_change_samples(speedup):
    """Frames replayed in (scaled) real time through a bus give the samples of an instant replay."""
    n = 4
    ch = channel()
    stream = make_stream(n, 2.5)
    expected, _ = assemble(stream, n)

    async def main():
        sender = can.Bus(interface="virtual", channel=ch, preserve_timestamps=True)
        dec = FrameDecoder(DB, "default", n)
        smp = SampleAssembler(n)
        samples = []
        try:
            async with ResilientBus(BusConfig(interface="virtual", channel=ch)) as rx:
                assert await rx.wait_open(5)

                async def produce():
                    prev = stream[0].timestamp
                    for m in stream:
                        if speedup:
                            await asyncio.sleep(max(0.0, (m.timestamp - prev) / speedup))
                        prev = m.timestamp
                        sender.send(m)

                prod = asyncio.create_task(produce())
                for _ in range(len(stream)):
                    m = await rx.recv()
                    samples.extend(smp.feed_frame(dec.decode(m), m.timestamp))
                await prod
        finally:
            sender.shutdown()
        return samples

    assert_same_samples(expected, run(main()))


class _FlakyBus(VirtualBus):
    """A virtual bus that dies (like an unplugged adapter) after ``fail_after`` frames."""

    def __init__(self, *a, fail_after: int, **kw):
        super().__init__(*a, **kw)
        self._left = fail_after

    def _recv_internal(self, timeout):
        msg, filtered = super()._recv_internal(timeout)
        if msg is not None:
            self._left -= 1
            if self._left < 0:
                raise can.CanOperationError("adapter unplugged", error_code=errno.ENODEV)
        return msg, filtered


def test_bus_that_goes_away_and_returns_is_survived():
    ch = channel()
    calls = {"n": 0}

    def factory(cfg: BusConfig) -> can.BusABC:
        calls["n"] += 1
        if calls["n"] <= 2:
            raise OSError(errno.ENODEV, "No such device")  # not plugged in yet
        if calls["n"] == 3:
            return _FlakyBus(channel=cfg.channel, fail_after=5)
        return VirtualBus(channel=cfg.channel)

    async def main():
        sender = can.Bus(interface="virtual", channel=ch)
        got = []
        try:
            async with ResilientBus(fast(BusConfig(interface="virtual", channel=ch)), bus_factory=factory) as rx:
                assert rx.send(own_current_frame(DB, 1.0)) is False  # no bus yet: dropped, no exception

                async def produce():
                    k = 0
                    while True:
                        sender.send(own_current_frame(DB, float(k % 100)))
                        k += 1
                        await asyncio.sleep(0.002)

                prod = asyncio.create_task(produce())
                try:
                    while len(got) < 30:
                        got.append(await rx.recv())
                finally:
                    prod.cancel()
                return got, rx.counters
        finally:
            sender.shutdown()

    got, counters = run(main(), timeout=20)
    assert len(got) == 30
    assert counters.open_failures == 2
    assert counters.bus_errors >= 1
    assert counters.opens >= 2
    assert counters.tx_dropped >= 1


def test_a_deaf_bus_is_reopened_after_silence():
    """An interface deleted and re-created leaves the open socket deaf, with no error (issue 16:
    nothing was received for 60 s). Here the first bus hears an old channel while the sender moves
    to a new one; after silence_reopen_s without a frame the bus is reopened, counted, and hears
    again within the silence limit plus the back-off."""
    old, new = channel(), channel()
    opened: list[str] = []

    def factory(cfg: BusConfig) -> can.BusABC:
        ch = old if not opened else new  # the first open binds to the interface about to vanish
        opened.append(ch)
        return VirtualBus(channel=ch)

    silence = 0.3
    cfg = fast(BusConfig(interface="virtual", channel=old), silence_reopen_s=silence)

    async def main():
        sender = can.Bus(interface="virtual", channel=old)
        async with ResilientBus(cfg, bus_factory=factory) as rx:
            assert await rx.wait_open(5)
            sender.send(own_current_frame(DB, 1.0))
            first = await asyncio.wait_for(rx.recv(), 5)
            sender.shutdown()
            sender = can.Bus(interface="virtual", channel=new)  # the interface "re-created"
            t_gone = time.monotonic()

            async def produce():
                while True:
                    sender.send(own_current_frame(DB, 2.0))
                    await asyncio.sleep(0.01)

            prod = asyncio.create_task(produce())
            try:
                second = await asyncio.wait_for(rx.recv(), 5)
            finally:
                prod.cancel()
            waited = time.monotonic() - t_gone
            status = rx.describe()
            sender.shutdown()
            return first, second, waited, rx.counters, status

    first, second, waited, counters, status = run(main(), timeout=20)
    assert FrameDecoder(DB, "default", 3).decode(second)[0].value == pytest.approx(2.0)
    assert opened[:2] == [old, new]
    assert counters.silence_reopens == 1 and counters.bus_errors == 0 and counters.opens == 2
    assert waited < silence + cfg.reopen_initial_s + 1.0, waited
    assert "reopened 1x after 0.3 s without a frame" in status


def test_silence_reopen_can_be_turned_off():
    ch = channel()

    async def main():
        async with ResilientBus(fast(BusConfig(interface="virtual", channel=ch), silence_reopen_s=None)) as rx:
            assert await rx.wait_open(5)
            with pytest.raises(asyncio.TimeoutError):
                await asyncio.wait_for(rx.recv(), 0.5)
            return rx.counters

    counters = run(main())
    assert counters.silence_reopens == 0 and counters.opens == 1


class _FdBus(VirtualBus):
    """A virtual bus with a file descriptor (like socketcan) whose recv() can be made to fail."""

    def __init__(self, *a, **kw):
        super().__init__(*a, **kw)
        self._r, self._w = socket.socketpair()
        self.fail = False

    def fileno(self) -> int:
        return self._r.fileno()

    def send(self, msg, timeout=None):  # pragma: no cover - unused
        super().send(msg, timeout)

    def poke(self) -> None:
        self._w.send(b"x")

    def _recv_internal(self, timeout):
        try:
            self._r.recv(1, socket.MSG_DONTWAIT)
        except BlockingIOError:
            pass
        if self.fail:
            raise OSError(errno.ENETDOWN, "Network is down")
        return super()._recv_internal(0)

    def shutdown(self):
        super().shutdown()
        self._r.close()
        self._w.close()


def test_selector_path_errors_reopen_instead_of_spinning():
    """A recv() error on a socketcan-style bus (in the receive thread) leads to a reopen, not a spin."""
    ch = channel()
    buses: list[_FdBus] = []

    def factory(cfg):
        b = _FdBus(channel=cfg.channel)
        buses.append(b)
        return b

    async def main():
        sender = can.Bus(interface="virtual", channel=ch)
        try:
            async with ResilientBus(fast(BusConfig(interface="virtual", channel=ch)), bus_factory=factory) as rx:
                assert await rx.wait_open(5)
                sender.send(own_current_frame(DB, 2.0))
                buses[-1].poke()
                first = await rx.recv()
                buses[-1].fail = True
                buses[-1].poke()
                recv_task = asyncio.create_task(rx.recv())
                for _ in range(500):
                    await asyncio.sleep(0.005)
                    if len(buses) >= 2 and rx.is_open:
                        break
                assert len(buses) >= 2, "bus was not reopened"
                sender.send(own_current_frame(DB, 3.0))
                buses[-1].poke()
                second = await asyncio.wait_for(recv_task, 5)
                return first, second, rx.counters
        finally:
            sender.shutdown()

    first, second, counters = run(main())
    assert first.data != second.data
    assert counters.bus_errors == 1 and counters.opens == 2


def test_receive_queue_overflow_is_counted_not_fatal():
    ch = channel()

    async def main():
        sender = can.Bus(interface="virtual", channel=ch)
        try:
            async with ResilientBus(BusConfig(interface="virtual", channel=ch, rx_queue_size=5)) as rx:
                assert await rx.wait_open(5)
                for k in range(20):
                    sender.send(own_current_frame(DB, float(k)))
                for _ in range(100):  # let the receive thread queue them while nobody reads
                    await asyncio.sleep(0.01)
                    if rx.counters.rx_dropped >= 15:
                        break
                got = [await rx.recv() for _ in range(5)]
                return got, rx.counters
        finally:
            sender.shutdown()

    got, counters = run(main())
    assert counters.rx_dropped == 15
    dec = FrameDecoder(DB, "default", 1)
    assert [dec.decode(m)[0].value for m in got] == [0.0, 1.0, 2.0, 3.0, 4.0]


def test_frames_are_read_while_the_event_loop_is_blocked():
    """Reception never waits for a tick: while the loop is held (a long tick), the receive
    thread takes every frame off the bus into the queue; one recv_batch then returns them
    all, in order, and nothing was dropped."""
    ch = channel()
    n = 500

    async def main():
        sender = can.Bus(interface="virtual", channel=ch)
        try:
            async with ResilientBus(BusConfig(interface="virtual", channel=ch)) as rx:
                assert await rx.wait_open(5)
                for k in range(n):
                    sender.send(own_current_frame(DB, float(k)))
                deadline = time.monotonic() + 20.0
                while rx.rx_backlog < n and time.monotonic() < deadline:
                    time.sleep(0.01)  # blocks the event loop on purpose: nothing here reads the bus
                backlog_while_blocked = rx.rx_backlog
                got = []
                while len(got) < n:
                    got += await rx.recv_batch()
                return backlog_while_blocked, got, rx.counters
        finally:
            sender.shutdown()

    backlog, got, counters = run(main())
    assert backlog == n
    dec = FrameDecoder(DB, "default", 1)
    assert [dec.decode(m)[0].value for m in got] == [float(k) for k in range(n)]
    assert counters.rx_dropped == 0 and counters.rx_frames == n


def test_a_bus_open_that_blocks_holds_neither_the_event_loop_nor_a_stop():
    """Opening runs off the event loop: an adapter whose open blocks (python-can's slcan sleeps 2 s
    in its constructor; a wedged USB driver for ever) held the loop, so no tick, no watchdog ping and
    no SIGTERM was served until it returned. Now close() ends while the open still blocks, and the
    bus that open returns late is shut down, never used."""
    import threading

    entered, release = threading.Event(), threading.Event()
    returned: list[can.BusABC] = []

    def factory(cfg: BusConfig) -> can.BusABC:
        entered.set()
        release.wait(3.0)  # bounded, so that the code before this fix fails rather than hangs
        bus = VirtualBus(channel=cfg.channel)
        returned.append(bus)
        return bus

    async def main():
        rx = ResilientBus(fast(BusConfig(interface="virtual", channel=channel())), bus_factory=factory)
        await rx.start()
        while not entered.is_set():
            await asyncio.sleep(0.005)
        await rx.close()
        closed_while_blocked = not returned
        release.set()
        while not (returned and returned[0]._is_shutdown):
            await asyncio.sleep(0.005)
        return closed_while_blocked, rx

    closed_while_blocked, rx = run(main(), timeout=20)
    assert closed_while_blocked, "close() waited for the blocked open"
    assert rx.state == "closed" and not rx.is_open and rx.counters.opens == 0


class _SendFailBus(VirtualBus):
    """A virtual bus whose send() raises the given exceptions, one per call, then sends."""

    def __init__(self, *a, failures, **kw):
        super().__init__(*a, **kw)
        self.failures = list(failures)

    def send(self, msg, timeout=None):
        if self.failures:
            raise self.failures.pop(0)
        super().send(msg, timeout)


def test_a_send_that_raises_anything_is_counted_and_sending_goes_on():
    """The sender thread caught python-can's errors, OSError and ValueError only: anything else a driver
    raises (a bug in it, a library of its own: here RuntimeError) ended the thread with a traceback, and
    no CAN frame went out again until a restart (queued, then dropped as the queue filled). Now every
    failed send is counted and logged, and the next frame goes out."""
    ch = channel()
    failures = [can.CanOperationError("No buffer space available", error_code=errno.ENOBUFS),
                RuntimeError("driver bug"), TypeError("driver bug")]

    async def main():
        listener = can.Bus(interface="virtual", channel=ch)
        try:
            cfg = fast(BusConfig(interface="virtual", channel=ch))
            async with ResilientBus(cfg, bus_factory=lambda c: _SendFailBus(channel=c.channel, failures=failures)) as rx:
                assert await rx.wait_open(5)
                for k in range(4):
                    assert rx.send(own_current_frame(DB, float(k)))
                drained = await rx.drain(5.0)
                got = listener.recv(1.0)
                return drained, got, rx.counters
        finally:
            listener.shutdown()

    drained, got, counters = run(main())
    assert drained, "the sender thread stopped sending"
    assert got is not None and FrameDecoder(DB, "default", 1).decode(got)[0].value == 3.0
    assert counters.tx_errors == 3 and counters.tx_frames == 1


class _SendBlocksUntilShutdownBus(VirtualBus):
    """send() blocks (a full controller queue) until the bus is shut down, then fails as a socket closed
    under it does: EBADF, one of the errors that reopen the bus."""

    def __init__(self, *a, **kw):
        super().__init__(*a, **kw)
        import threading

        self.closed = threading.Event()
        self.sending = threading.Event()

    def send(self, msg, timeout=None):
        self.sending.set()
        self.closed.wait(5.0)
        raise OSError(errno.EBADF, "Bad file descriptor")

    def shutdown(self):
        self.closed.set()
        super().shutdown()


def test_a_send_failing_on_a_bus_already_torn_down_does_not_reopen_its_successor():
    """A bus torn down (here after silence_reopen_s without a frame) while the sender thread is inside its
    send(): the send then fails with EBADF, and that asked for a reopen of whatever bus was current by
    then, the fresh one: torn down again, a bus error counted, frames lost for another back-off. Now a
    failure of a bus no longer in use is only counted."""
    ch = channel()
    buses: list[VirtualBus] = []

    def factory(cfg):
        bus = _SendBlocksUntilShutdownBus(channel=cfg.channel) if not buses else VirtualBus(channel=cfg.channel)
        buses.append(bus)
        return bus

    async def main():
        sender = can.Bus(interface="virtual", channel=ch)
        try:
            cfg = fast(BusConfig(interface="virtual", channel=ch), silence_reopen_s=0.3)
            async with ResilientBus(cfg, bus_factory=factory) as rx:
                assert await rx.wait_open(5)
                rx.send(own_current_frame(DB, 1.0))
                while not buses[0].sending.is_set():
                    await asyncio.sleep(0.005)
                got = []

                async def produce():  # once the first bus is gone, frames: no silence reopen of the next
                    while len(buses) < 2:
                        await asyncio.sleep(0.005)
                    while True:
                        sender.send(own_current_frame(DB, 2.0))
                        await asyncio.sleep(0.01)

                prod = asyncio.create_task(produce())
                try:
                    while len(got) < 60:  # 0.6 s of frames: twice the silence limit
                        got += await rx.recv_batch()
                finally:
                    prod.cancel()
                return rx.counters, len(buses)
        finally:
            sender.shutdown()

    counters, n_buses = run(main())
    assert counters.silence_reopens == 1 and counters.tx_errors == 1
    assert counters.bus_errors == 0 and counters.opens == 2 and n_buses == 2, counters


def test_close_ends_the_sender_thread_even_with_its_queue_full():
    """close() put its stop sentinel with put_nowait, dropped when the send queue was full (a bus-off
    adapter whose sends block): the sender thread then emptied the queue and waited for ever, one
    thread left behind per close (a reload, a reopen of the service). Now the sentinel is waited in."""
    ch = channel()

    async def main():
        cfg = fast(BusConfig(interface="virtual", channel=ch), tx_queue_size=4)
        made: list[_SendBlocksUntilShutdownBus] = []

        def factory(c):
            made.append(_SendBlocksUntilShutdownBus(channel=c.channel))
            return made[-1]

        rx = ResilientBus(cfg, bus_factory=factory)
        await rx.start()
        assert await rx.wait_open(5)
        thread = rx._tx_thread
        rx.send(own_current_frame(DB, 0.0))
        while not made[0].sending.is_set():  # the sender is inside send(): the next ones queue up
            await asyncio.sleep(0.005)
        queued = sum(rx.send(own_current_frame(DB, float(k))) for k in range(1, 10))
        await rx.close()
        thread.join(2.0)
        return queued, thread.is_alive(), rx.counters

    queued, alive, counters = run(main())
    assert queued == 4 and counters.tx_dropped >= 5  # the queue was full at the close
    assert not alive, "the sender thread outlived close()"


def test_close_ends_a_pending_receive():
    async def main():
        rx = ResilientBus(fast(BusConfig(interface="virtual", channel=channel())))
        await rx.start()
        assert await rx.wait_open(5)
        got = []

        async def consume():
            async for m in rx:
                got.append(m)

        task = asyncio.create_task(consume())
        await asyncio.sleep(0.05)
        await rx.close()
        await asyncio.wait_for(task, 2)  # ends, no exception
        with pytest.raises(RuntimeError):
            await rx.recv()

        never = ResilientBus(fast(BusConfig(interface="virtual", channel=channel())),
                             bus_factory=lambda cfg: (_ for _ in ()).throw(OSError(errno.ENODEV, "gone")))
        await never.start()
        waiter = asyncio.create_task(never.recv())
        await asyncio.sleep(0.05)
        await never.close()
        with pytest.raises(RuntimeError):
            await asyncio.wait_for(waiter, 2)
        return got, never.counters

    got, counters = run(main())
    assert got == [] and counters.open_failures >= 1


# ----------------------------------------------------- udp_multicast in a netns
RECEIVER = textwrap.dedent(
    """
    import asyncio, json, sys
    sys.path.insert(0, {repo!r})
    from bms_estimator.can.bus import BusConfig, ResilientBus
    from bms_estimator.can.dbc import load_project_db
    from bms_estimator.can.decoder import FrameDecoder
    from bms_estimator.can.sampler import SampleAssembler

    async def main():
        # no silence reopen: on a loaded machine the sender process may take longer than 5 s to start
        cfg = BusConfig(interface="udp_multicast", channel="239.74.163.2", fd=False, options={{"port": {port}}},
                        silence_reopen_s=None)
        dec = FrameDecoder(load_project_db(), "default", {n})
        smp = SampleAssembler({n})
        samples, frames = [], 0
        async with ResilientBus(cfg) as rx:
            if not await rx.wait_open(10):
                print(json.dumps({{"error": "bus did not open"}}), flush=True)
                return
            print("READY", flush=True)

            async def consume():
                nonlocal frames
                async for msg in rx:
                    if msg.arbitration_id == 0x7FF and not msg.is_extended_id:
                        return
                    frames += 1
                    samples.extend(smp.feed_frame(dec.decode(msg), msg.timestamp))

            await asyncio.wait_for(consume(), 30)
        print(json.dumps({{
            "frames": frames,
            "samples": [[s.t_s, s.current_a, list(map(float, s.cell_voltage_v)), list(map(bool, s.valid))]
                        for s in samples],
            "counters": dec.counters.as_dict(),
            "bus": rx.counters.as_dict(),
        }}), flush=True)

    asyncio.run(main())
    """
)

SENDER = textwrap.dedent(
    """
    import socket, sys, time
    sys.path.insert(0, {repo!r})
    sys.path.insert(0, {tests!r})
    import can
    from bms_estimator.can.dbc import load_project_db
    from bmscan_helpers import own_current_frame, own_voltage_frame
    db = load_project_db()
    bus = can.Bus(interface="udp_multicast", channel="239.74.163.2", port={port}, fd=False)
    raw = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)  # datagrams that are no CAN frame
    raw.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_LOOP, 1)
    n = {n}
    sent = junk = malformed = 0
    for k in range(320):  # a fixed count, not a time budget: a loaded machine sends the same frames
        if {bad_every} and k % {bad_every} == 0:
            raw.sendto(b"\\x00 not msgpack" if malformed % 2 else b"\\x93\\x01", ("239.74.163.2", {port}))
            malformed += 1
        bus.send(own_current_frame(db, -7.5, voltage_v=3.7 * n))
        sent += 1
        if k % 10 == 0:
            for base in range(0, n, 3):
                bus.send(own_voltage_frame(db, base, [3.5 + 0.01 * c for c in range(base, base + 3)]))
                sent += 1
        bus.send(can.Message(arbitration_id=0x123, data=b"junk", is_extended_id=False))
        sent += 1
        junk += 1
        time.sleep(0.01)
    time.sleep(0.2)
    bus.send(can.Message(arbitration_id=0x7FF, data=b"STOP", is_extended_id=False))
    print(sent, junk, malformed, flush=True)
    bus.shutdown()
    """
)


@pytest.fixture
def netns():
    ip = shutil.which("ip")
    if ip is None:
        pytest.skip("netns unavailable: no 'ip' command")
    name = f"bmsest-{os.getpid()}-{uuid.uuid4().hex[:4]}"
    r = subprocess.run([ip, "netns", "add", name], capture_output=True, text=True)
    if r.returncode != 0:
        pytest.skip(f"cannot create a network namespace (netns) here: {r.stderr.strip() or r.returncode}")
    try:
        for cmd in (["link", "set", "lo", "up"], ["route", "add", "224.0.0.0/4", "dev", "lo"]):
            r = subprocess.run([ip, "-n", name, *cmd], capture_output=True, text=True)
            if r.returncode != 0:
                pytest.skip(f"netns {name}: 'ip {' '.join(cmd)}' failed: {r.stderr.strip()}")
        yield name
    finally:
        subprocess.run([ip, "netns", "del", name], capture_output=True)


def _udp_run(netns, port: int, bad_every: int):
    pytest.importorskip("msgpack", reason="udp_multicast needs msgpack (python-can[multicast])")
    n = 6
    env = dict(os.environ, PYTHONPATH=str(REPO_ROOT))
    base = ["ip", "netns", "exec", netns, sys.executable, "-c"]
    rx = subprocess.Popen(base + [RECEIVER.format(repo=str(REPO_ROOT), port=port, n=n)],
                          stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    try:
        seen = []
        while True:  # log lines may come first
            line = rx.stdout.readline()
            seen.append(line)
            if line.strip() == "READY" or not line:
                break
        assert line.strip() == "READY", "".join(seen)
        tx = subprocess.run(
            base + [SENDER.format(repo=str(REPO_ROOT), tests=str(Path(__file__).parent), port=port, n=n,
                                         bad_every=bad_every)],
            capture_output=True, text=True, env=env, timeout=60)
        assert tx.returncode == 0, tx.stderr
        out, err = rx.communicate(timeout=60)
    finally:
        if rx.poll() is None:
            rx.kill()
            rx.wait()
    assert rx.returncode == 0, err
    result = json.loads(out.strip().splitlines()[-1])
    assert "error" not in result, result
    return result, tuple(map(int, tx.stdout.split()[-3:]))


def test_udp_multicast_between_two_processes(netns):
    n = 6
    result, (sent, junk, _) = _udp_run(netns, 43113, 0)
    assert result["frames"] >= 0.95 * sent, (result["frames"], sent)  # loopback multicast loses next to nothing
    samples = result["samples"]
    assert len(samples) >= 2
    for t_s, current, volts, valid in samples:
        assert t_s == int(t_s)  # whole-second grid on the receive timestamps
        if all(valid):
            assert current == pytest.approx(-7.5)
            assert volts == pytest.approx([3.5 + 0.01 * c for c in range(n)], abs=1e-4)
    assert any(all(v) for *_, v in samples)
    assert result["counters"]["unknown_id"] >= 0.95 * junk  # the junk frames were counted, not fatal
    assert result["counters"]["errors"] == 0



def test_malformed_datagrams_are_counted_not_fatal(netns):
    """5 datagrams a second that are no CAN frame (issue 16): each counted, the bus never torn
    down, and next to no valid frame lost (python-can's receiver raised on each, and the bus was
    reopened after 0.5 s: about 65 % of frames lost at this rate)."""
    result, (sent, _, malformed) = _udp_run(netns, 43115, 20)  # 16 bad datagrams over 3.2 s
    bus = result["bus"]
    assert malformed == 16
    assert bus["rx_malformed"] == malformed
    assert bus["bus_errors"] == 0 and bus["opens"] == 1
    assert result["frames"] >= 0.99 * sent, (result["frames"], sent)


# -------------------------------------------------------------- socketcan / vcan
def _vcan_channel() -> tuple[str, bool]:
    """An existing vcan interface or one we create; skip with the reason otherwise."""
    if not hasattr(socket, "AF_CAN"):
        pytest.skip("socketcan/vcan unavailable: Python has no AF_CAN support on this platform")
    ip = shutil.which("ip")
    if ip:
        r = subprocess.run([ip, "-o", "link", "show", "type", "vcan"], capture_output=True, text=True)
        names = [ln.split(":")[1].strip().split("@")[0] for ln in r.stdout.splitlines() if ":" in ln]
        if names:
            return names[0], False
        name = f"bmsv{os.getpid() % 100000}"
        r = subprocess.run([ip, "link", "add", "dev", name, "type", "vcan"], capture_output=True, text=True)
        if r.returncode == 0:
            subprocess.run([ip, "link", "set", "up", name], check=True)
            return name, True
        reason = r.stderr.strip()
    else:
        reason = "no 'ip' command"
    try:
        s = socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW)
        s.close()
    except OSError as exc:
        reason = f"{reason}; AF_CAN socket: {exc}"
    pytest.skip(f"socketcan/vcan unavailable (kernel without CAN/vcan support?): {reason}")


def test_socketcan_vcan_receive_decode_and_survive_link_down():
    """The real socketcan path (receive thread): receive, decode, and keep going after link down/up."""
    name, created = _vcan_channel()
    try:
        cfg = fast(BusConfig(interface="socketcan", channel=name))

        def try_send(bus, volts):
            try:
                bus.send(own_voltage_frame(DB, 0, volts))
            except can.CanError:  # link still down
                pass

        async def main():
            sender = can.Bus(interface="socketcan", channel=name)
            try:
                async with ResilientBus(cfg) as rx:
                    assert await rx.wait_open(5)
                    sender.send(own_voltage_frame(DB, 0, [3.1, 3.2, 3.3]))
                    first = await asyncio.wait_for(rx.recv(), 5)
                    if created:  # the interface goes away and comes back
                        subprocess.run(["ip", "link", "set", "down", name], check=True)
                        await asyncio.sleep(0.2)
                        subprocess.run(["ip", "link", "set", "up", name], check=True)
                        await asyncio.sleep(0.2)
                    second = None
                    for _ in range(50):
                        try_send(sender, [3.4, 3.5, 3.6])
                        try:
                            second = await asyncio.wait_for(rx.recv(), 0.2)
                            break
                        except asyncio.TimeoutError:
                            continue
                    return first, second
            finally:
                sender.shutdown()

        first, second = run(main())
        dec = FrameDecoder(DB, "default", 3)
        assert [round(e.value, 4) for e in dec.decode(first)] == [3.1, 3.2, 3.3]
        assert second is not None, "no frame after the link came back"
        assert [round(e.value, 4) for e in dec.decode(second)] == [3.4, 3.5, 3.6]
    finally:
        if created:
            subprocess.run(["ip", "link", "del", name], capture_output=True)


def test_socketcan_vcan_deleted_and_recreated_is_heard_again():
    """The real case behind silence_reopen_s: `ip link del` + `ip link add` of the interface leaves
    the old socket open and deaf; the service hears again within the silence limit plus back-off."""
    name, created = _vcan_channel()
    if not created:
        subprocess.run(["ip", "link", "del", name], capture_output=True)
        pytest.skip(f"vcan {name} exists already: not ours to delete")
    silence = 1.0
    cfg = fast(BusConfig(interface="socketcan", channel=name), silence_reopen_s=silence)
    try:
        async def main():
            async with ResilientBus(cfg) as rx:
                assert await rx.wait_open(5)
                with can.Bus(interface="socketcan", channel=name) as sender:
                    sender.send(own_current_frame(DB, 1.0))
                    await asyncio.wait_for(rx.recv(), 5)
                subprocess.run(["ip", "link", "del", name], check=True)
                subprocess.run(["ip", "link", "add", "dev", name, "type", "vcan"], check=True)
                subprocess.run(["ip", "link", "set", "up", name], check=True)
                t0 = time.monotonic()
                with can.Bus(interface="socketcan", channel=name) as sender:
                    for _ in range(400):
                        sender.send(own_current_frame(DB, 2.0))
                        try:
                            await asyncio.wait_for(rx.recv(), 0.02)
                            return time.monotonic() - t0, rx.counters
                        except asyncio.TimeoutError:
                            continue
                return None, rx.counters

        waited, counters = run(main())
        assert waited is not None, f"deaf after the interface was re-created: {counters}"
        assert waited < silence + cfg.reopen_max_s + 1.0
        assert counters.silence_reopens + counters.bus_errors >= 1
    finally:
        subprocess.run(["ip", "link", "del", name], capture_output=True)


KERNEL_DROPS = textwrap.dedent(
    """
    import json, sys, time
    sys.path.insert(0, {repo!r})
    import can
    from bms_estimator.can.udp import UdpMulticastReceiver
    rx = UdpMulticastReceiver(channel="239.74.163.2", port={port}, receive_buffer_bytes=4096)
    tx = can.Bus(interface="udp_multicast", channel="239.74.163.2", port={port})
    before = rx.kernel_drops()
    n = 2000
    for k in range(n):  # nobody reads: the small socket buffer overflows
        tx.send(can.Message(arbitration_id=0x100 + k % 7, data=bytes(8), is_extended_id=False))
    time.sleep(0.2)
    got = 0
    while rx.recv(0.2) is not None:
        got += 1
    print(json.dumps({{"sent": n, "received": got, "kernel_drops": rx.kernel_drops(), "before": before}}))
    tx.shutdown(); rx.shutdown()
    """
)


def test_udp_kernel_drops_are_counted(netns):
    """A receiver that falls behind loses datagrams in the kernel, where nothing counted them
    (issue 16: 5-29 % lost at saturation with every counter at 0). Now every datagram is either
    received or in the kernel's drop count: received + dropped == sent."""
    pytest.importorskip("msgpack", reason="udp_multicast needs msgpack (python-can[multicast])")
    env = dict(os.environ, PYTHONPATH=str(REPO_ROOT))
    r = subprocess.run(["ip", "netns", "exec", netns, sys.executable, "-c",
                        KERNEL_DROPS.format(repo=str(REPO_ROOT), port=43117)],
                       capture_output=True, text=True, env=env, timeout=60)
    assert r.returncode == 0, r.stderr
    res = json.loads(r.stdout.strip().splitlines()[-1])
    assert res["before"] == 0
    assert res["kernel_drops"] > 0, res  # the buffer did overflow
    assert res["received"] + res["kernel_drops"] == res["sent"], res


def test_kernel_drops_add_up_across_reopens():
    """Each socket counts its drops from 0: the bus's counter carries the closed sockets' drops."""
    ch = channel()
    drops = {"n": 0}

    class DroppingBus(VirtualBus):
        def kernel_drops(self):
            return drops["n"]

    async def main():
        async with ResilientBus(fast(BusConfig(interface="virtual", channel=ch)),
                                bus_factory=lambda cfg: DroppingBus(channel=cfg.channel)) as rx:
            assert await rx.wait_open(5)
            drops["n"] = 7
            assert rx.refresh_kernel_drops() == 7
            await rx._fail(OSError(errno.ENETDOWN, "down"))  # a reopen: a new socket
            drops["n"] = 0
            assert await rx.wait_open(5)
            drops["n"] = 3
            return rx.refresh_kernel_drops()

    assert run(main()) == 10


def test_rxq_overflow_control_message_is_read_and_the_rest_passed_on():
    """SO_RXQ_OVFL: the kernel's cumulative drop count rides on a control message; the
    timestamp message python-can parses is passed on untouched, in its place."""
    from bms_estimator.can.socketcan import SO_RXQ_OVFL, _OverflowTap, rxq_overflow_count

    ts = (socket.SOL_SOCKET, 35, b"\x01" * 16)  # SO_TIMESTAMPNS
    ovfl = (socket.SOL_SOCKET, SO_RXQ_OVFL, (1234).to_bytes(4, sys.byteorder))
    assert rxq_overflow_count([ts, ovfl]) == (1234, [ts])
    assert rxq_overflow_count([ts]) == (None, [ts])  # nothing dropped yet: the kernel sends none

    class FakeSock:
        def __init__(self):
            self.replies = [(b"f1", [ts], 0, ("vcan0",)), (b"f2", [ts, ovfl], 0, ("vcan0",)),
                            (b"f3", [ts], 0, ("vcan0",))]
            self.asked = []

        def recvmsg(self, bufsize, ancbufsize, flags=0):
            self.asked.append(ancbufsize)
            return self.replies.pop(0)

    sock = FakeSock()
    tap = _OverflowTap(sock)
    got = [tap.recvmsg(72, 32) for _ in range(3)]
    assert [g[1] for g in got] == [[ts], [ts], [ts]]
    assert tap.drops == 1234  # kept after a frame without the message
    assert all(a > 32 for a in sock.asked)  # room for the overflow message too


def test_socketcan_kernel_drops_are_counted():
    """On vcan: a receive queue that overflows while nobody reads reports its drops through
    SO_RXQ_OVFL, and received + dropped == sent."""
    name, created = _vcan_channel()
    try:
        from bms_estimator.can.socketcan import SocketcanReceiver

        rx = SocketcanReceiver(channel=name, receive_buffer_bytes=4096)
        sent = 2000
        with can.Bus(interface="socketcan", channel=name) as tx:
            for k in range(sent):
                while True:
                    try:
                        tx.send(own_current_frame(DB, float(k)), timeout=1.0)
                        break
                    except can.CanError:
                        time.sleep(0.001)
        received = 0
        while rx.recv(timeout=0.2) is not None:
            received += 1
        drops = rx.kernel_drops()
        rx.shutdown()
        assert drops is not None and drops > 0
        assert received + drops == sent
    finally:
        if created:
            subprocess.run(["ip", "link", "del", name], capture_output=True)
