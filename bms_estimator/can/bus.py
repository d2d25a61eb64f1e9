"""python-can bus for the asyncio service: open, receive, send, survive.

:func:`open_bus` opens a python-can bus from a :class:`BusConfig`
(``interface``/``channel``/``bitrate``/...; on ``socketcan`` the bitrate is
the kernel's business - ``ip link set can0 type can bitrate 500000`` or
systemd-networkd - and is not passed).

:class:`ResilientBus` owns one bus at a time and keeps it alive:

* receive: a thread of its own reads the bus into a bounded queue
  (:class:`~bms_estimator.can.receiver.RxThread`; overflow is dropped and
  counted), so frames are taken off the socket while the event loop is busy
  with a tick and its outputs. ``await rx.recv_batch()`` takes everything
  queued at once; ``await rx.recv()`` / ``async for msg in rx`` one frame.
* send: :meth:`ResilientBus.send` / :meth:`send_many` only enqueue; a daemon
  thread does the (possibly blocking) ``bus.send(msg, timeout)``. A full queue
  or a down bus drops frames (counted) rather than blocking the estimator.
* failures: a ``can.CanError``/``OSError`` from receiving (or a fatal
  ``OSError`` from sending: ENODEV, ENETDOWN, ENXIO, EBADF) closes the bus and
  reopens it with exponential back-off (``reopen_initial_s`` doubling up to
  ``reopen_max_s``; back-off resets once the new bus delivered a frame); any
  other failed send, whatever it raises, is counted (``tx_errors``) and logged, and
  the sender thread goes on with the next frame. An
  interface that disappears and comes back (USB adapter, ``ip link set can0
  down/up``) is survived without restarting the service.
* silence: no frame for ``silence_reopen_s`` (default 5 s) reopens the bus the
  same way. A socketcan socket whose interface was deleted and re-created
  reports no error; it just stays deaf. A bus that is really quiet is reopened
  with the same back-off, growing to ``reopen_max_s``.

Everything is counted in :class:`BusCounters` and logged.
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import queue
import threading
import time
from collections.abc import AsyncIterator, Callable, Iterable
from dataclasses import dataclass, fields
from typing import Any

import can
import structlog
from pydantic import BaseModel, ConfigDict, Field

from .. import aio
from ..errors import one_line_error
from .receiver import RxFailure, RxThread

__all__ = ["BusConfig", "BusCounters", "ResilientBus", "open_bus"]

log = structlog.get_logger(__name__)

_FATAL_TX_ERRNOS = {errno.ENODEV, errno.ENETDOWN, errno.ENXIO, errno.EBADF}
#: interfaces whose bitrate is configured by the OS, not by python-can
_OS_BITRATE_INTERFACES = {"socketcan", "virtual", "udp_multicast"}


class BusConfig(BaseModel):
    """How to open the CAN bus (passed to ``can.Bus``) and how hard to retry."""

    model_config = ConfigDict(extra="forbid")

    interface: str = "socketcan"
    channel: str | int = "can0"
    bitrate: int | None = Field(None, gt=0, description="None = keep the interface's setting")
    data_bitrate: int | None = Field(None, gt=0)
    fd: bool = False
    receive_own_messages: bool = False
    can_filters: list[dict[str, Any]] | None = None
    options: dict[str, Any] = Field(default_factory=dict, description="extra keyword arguments for can.Bus")
    reopen_initial_s: float = Field(0.5, gt=0)
    reopen_max_s: float = Field(30.0, gt=0)
    rx_queue_size: int = Field(100_000, ge=1)
    tx_queue_size: int = Field(20_000, ge=1)
    tx_timeout_s: float = Field(0.05, ge=0)
    notifier_timeout_s: float = Field(0.1, gt=0, description="receive thread's poll period (how soon it notices a stop)")
    silence_reopen_s: float | None = Field(
        5.0, gt=0, description="reopen the bus after this long without a frame (an interface deleted and "
                               "re-created leaves an open socket deaf); None = never")


@dataclass
class BusCounters:
    opens: int = 0  # successful opens
    open_failures: int = 0
    bus_errors: int = 0  # receive-side failures that caused a reopen
    silence_reopens: int = 0  # reopens after silence_reopen_s without a frame
    rx_frames: int = 0  # handed to the consumer by recv()/recv_batch() (frames still queued are not counted)
    rx_error_frames: int = 0
    rx_dropped: int = 0  # receive queue overflow
    rx_malformed: int = 0  # datagrams that were no CAN frame (udp_multicast): skipped, the bus kept
    rx_kernel_dropped: int = 0  # lost in the kernel before we read them (socket buffer full), where it says
    tx_frames: int = 0
    tx_errors: int = 0
    tx_dropped: int = 0  # queue full or no bus

    def as_dict(self) -> dict[str, int]:
        return {f.name: getattr(self, f.name) for f in fields(self)}


def open_bus(cfg: BusConfig, *, log_time: bool = False) -> can.BusABC:
    """Open a python-can bus as configured. Raises ``can.CanError``/``OSError``/``ValueError``.

    ``udp_multicast`` opens :class:`~bms_estimator.can.udp.UdpMulticastReceiver`
    (malformed datagrams skipped and counted, a large socket buffer; ``log_time``
    keeps the sender's timestamps); ``socketcan`` opens
    :class:`~bms_estimator.can.socketcan.SocketcanReceiver` (the kernel's drop count,
    ``SO_RXQ_OVFL``). Both report it as ``kernel_drops()``.
    """
    if cfg.interface == "udp_multicast":
        from .udp import UdpMulticastReceiver

        if UdpMulticastReceiver is None:  # pragma: no cover
            raise ImportError("udp_multicast needs msgpack: pip install 'python-can[multicast]'")
        kw: dict[str, Any] = {"channel": cfg.channel, "receive_own_messages": cfg.receive_own_messages,
                              "log_time": log_time}
        if cfg.fd:
            kw["fd"] = True
        if cfg.can_filters is not None:
            kw["can_filters"] = cfg.can_filters
        kw.update(cfg.options)
        return UdpMulticastReceiver(**kw)
    if cfg.interface == "socketcan":
        from .socketcan import SocketcanReceiver

        if SocketcanReceiver is not None:
            kw = {"channel": cfg.channel, "receive_own_messages": cfg.receive_own_messages}
            if cfg.fd:
                kw["fd"] = True
            if cfg.bitrate is not None:
                log.debug("can.bus.bitrate_by_os", channel=cfg.channel, bitrate=cfg.bitrate,
                          hint=f"ip link set {cfg.channel} type can bitrate {cfg.bitrate}")
            if cfg.can_filters is not None:
                kw["can_filters"] = cfg.can_filters
            kw.update(cfg.options)
            return SocketcanReceiver(**kw)
    kwargs: dict[str, Any] = {
        "interface": cfg.interface,
        "channel": cfg.channel,
        "receive_own_messages": cfg.receive_own_messages,
    }
    if cfg.fd:
        kwargs["fd"] = True
    if cfg.bitrate is not None and cfg.interface not in _OS_BITRATE_INTERFACES:
        kwargs["bitrate"] = cfg.bitrate
    elif cfg.bitrate is not None and cfg.interface == "socketcan":
        log.debug("can.bus.bitrate_by_os", channel=cfg.channel, bitrate=cfg.bitrate,
                  hint=f"ip link set {cfg.channel} type can bitrate {cfg.bitrate}")
    if cfg.data_bitrate is not None and cfg.interface not in _OS_BITRATE_INTERFACES:
        kwargs["data_bitrate"] = cfg.data_bitrate
    if cfg.can_filters is not None:
        kwargs["can_filters"] = cfg.can_filters
    kwargs.update(cfg.options)
    return can.Bus(**kwargs)


def _shutdown_quietly(bus: can.BusABC) -> None:
    with contextlib.suppress(Exception):
        bus.shutdown()


class ResilientBus:
    """A CAN bus that reopens itself; see the module docstring.

    Use inside a running event loop::

        async with ResilientBus(cfg) as rx:
            async for msg in rx:
                ...
            rx.send_many(frames)
    """

    def __init__(self, cfg: BusConfig, *, bus_factory: Callable[[BusConfig], can.BusABC] = open_bus) -> None:
        self.cfg = cfg
        self.counters = BusCounters()
        self._factory = bus_factory
        self._bus: can.BusABC | None = None
        self._bus_lock = threading.Lock()
        self._rx: RxThread | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._closed = False
        self._backoff = cfg.reopen_initial_s
        self._got_frame_since_open = False
        self._tx_queue: queue.Queue[can.Message | None] = queue.Queue(maxsize=cfg.tx_queue_size)
        self._tx_thread: threading.Thread | None = None
        self._fail_request: BaseException | None = None
        self._opened = asyncio.Event()
        self._open_task: asyncio.Task[None] | None = None
        self.last_error: str | None = None  # why the bus is not open (the last open failure or bus error)
        self._kernel_drops_before = 0  # kernel drops of the sockets closed so far

    # ------------------------------------------------------------- lifecycle
    async def __aenter__(self) -> ResilientBus:
        await self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    async def start(self) -> None:
        """Bind to the running loop, start the sender thread and begin opening the bus in the background.

        Returns at once; :meth:`wait_open` waits for the first successful open.
        """
        self._loop = asyncio.get_running_loop()
        if self._tx_thread is None:
            self._tx_thread = threading.Thread(target=self._tx_worker, name="bms-can-tx", daemon=True)
            self._tx_thread.start()
        self._ensure_open_task()

    def _ensure_open_task(self) -> asyncio.Task[None]:
        task = self._open_task
        if task is None or task.done():
            task = self._open_task = asyncio.get_running_loop().create_task(self._open(), name="bms-can-open")
        return task

    async def close(self) -> None:
        """Stop receiving and sending; a pending :meth:`recv` raises ``RuntimeError``, ``async for`` ends."""
        self._closed = True
        rx = self._rx
        if rx is not None:
            rx.fail(RuntimeError("bus closed"))  # wakes a pending recv()
        task, self._open_task = self._open_task, None
        if task is not None and not task.done():
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await task
        self._teardown()
        if self._tx_thread is not None:
            # the bus is gone: the sender drops what is queued at once, so the stop sentinel gets in
            # even behind a full queue (a bus-off adapter's), where put_nowait lost it and left the
            # thread waiting for ever
            await asyncio.get_running_loop().run_in_executor(None, self._stop_sender, 2.0)
            self._tx_thread = None

    def _stop_sender(self, timeout: float) -> None:
        thread = self._tx_thread
        with contextlib.suppress(queue.Full):
            self._tx_queue.put(None, timeout=timeout)
        if thread is not None:
            thread.join(timeout)

    @property
    def is_open(self) -> bool:
        return self._bus is not None

    @property
    def state(self) -> str:
        """``"open"``, ``"down"`` (opening or reopening in the background) or ``"closed"``."""
        if self._closed:
            return "closed"
        return "open" if self._bus is not None else "down"

    def describe(self) -> str:
        """One line for status displays: ``can0 (socketcan): open`` / ``...: down (OSError: ...)``."""
        text = f"{self.cfg.channel} ({self.cfg.interface}): {self.state}"
        if self.state == "down" and self.last_error:
            text += f" ({self.last_error})"
        if self.counters.silence_reopens:
            text += f"; reopened {self.counters.silence_reopens}x after {self.cfg.silence_reopen_s:g} s without a frame"
        return text

    async def wait_open(self, timeout: float | None = None) -> bool:
        """Wait until a bus is open (e.g. before sending the first frames)."""
        try:
            await aio.wait_for(self._opened.wait(), timeout)
            return True
        except asyncio.TimeoutError:
            return False

    @property
    def rx_backlog(self) -> int:
        """Frames received by the receive thread and not yet taken by :meth:`recv_batch`."""
        rx = self._rx
        return 0 if rx is None else rx.backlog

    def refresh_kernel_drops(self) -> int:
        """Update ``counters.rx_kernel_dropped`` from the open bus (where its transport reports
        what the kernel dropped: udp_multicast) and return it. Cheap; called about once a second."""
        bus = self._bus
        probe = getattr(bus, "kernel_drops", None)
        if probe is not None:
            with contextlib.suppress(Exception):
                d = probe()
                if d is not None:
                    self.counters.rx_kernel_dropped = self._kernel_drops_before + int(d)
        return self.counters.rx_kernel_dropped

    def _teardown(self) -> None:
        self.refresh_kernel_drops()
        self._kernel_drops_before = self.counters.rx_kernel_dropped  # the next socket counts from 0
        rx = self._rx
        with self._bus_lock:
            bus, self._bus = self._bus, None
        self._rx = None
        self._opened.clear()
        if rx is not None:
            rx.stop(timeout=self.cfg.notifier_timeout_s * 5)
        if bus is not None:
            with contextlib.suppress(Exception):
                bus.shutdown()

    async def _open(self) -> None:
        """Open the bus, retrying with back-off until it works or we are closed."""
        loop = asyncio.get_running_loop()
        self._loop = loop
        while not self._closed:
            try:
                bus = await self._call_factory()
            except asyncio.CancelledError:
                raise
            except Exception as exc:  # can.CanError, OSError, ValueError, ImportError of a driver...
                self.counters.open_failures += 1
                self.last_error = one_line_error(exc)
                log.warning(
                    "can.bus.open_failed",
                    interface=self.cfg.interface,
                    channel=self.cfg.channel,
                    error=repr(exc),
                    retry_in_s=self._backoff,
                )
                await asyncio.sleep(self._backoff)
                self._backoff = min(self._backoff * 2.0, self.cfg.reopen_max_s)
                continue
            if hasattr(bus, "on_malformed"):
                bus.on_malformed = self._count_malformed
            rx = RxThread(bus, self.cfg.rx_queue_size, on_drop=self._count_rx_drop,
                          poll_s=self.cfg.notifier_timeout_s)
            with self._bus_lock:
                self._bus = bus
            self._rx = rx
            rx.start()
            self._got_frame_since_open = False
            self.counters.opens += 1
            self.last_error = None
            self._opened.set()
            log.info("can.bus.open", interface=self.cfg.interface, channel=self.cfg.channel, opens=self.counters.opens)
            return

    async def _call_factory(self) -> can.BusABC:
        """``bus_factory(cfg)`` in a daemon thread of its own (:func:`bms_estimator.aio.in_thread`): an
        adapter whose open blocks (python-can's slcan sleeps 2 s in its constructor; a wedged driver for
        ever) holds neither the event loop (ticks, watchdog, signals) nor a stop. Cancelled meanwhile
        (:meth:`close`), the bus it returns late is shut down."""
        return await aio.in_thread(lambda: self._factory(self.cfg), name="bms-can-open", discard=_shutdown_quietly)

    def _count_rx_drop(self) -> None:
        self.counters.rx_dropped += 1
        n = self.counters.rx_dropped
        if n in (1, 10, 100, 1000) or n % 100000 == 0:
            log.warning("can.bus.rx_queue_full", rx_queue_size=self.cfg.rx_queue_size, rx_dropped=n)

    def _count_malformed(self) -> None:
        self.counters.rx_malformed += 1
        if self.counters.rx_malformed in (1, 10, 100, 1000) or self.counters.rx_malformed % 10000 == 0:
            log.warning("can.bus.malformed", interface=self.cfg.interface, channel=self.cfg.channel,
                        malformed=self.counters.rx_malformed)

    async def _fail(self, exc: BaseException, *, silence: bool = False) -> None:
        self.last_error = one_line_error(exc)
        if silence:
            n = self.counters.silence_reopens
            if n <= 3 or n % 100 == 0:  # a parked vehicle is silent for hours: a few lines, then one per 100
                log.warning("can.bus.silent", silent_s=self.cfg.silence_reopen_s, reopen_in_s=self._backoff,
                            silence_reopens=n)
        else:
            self.counters.bus_errors += 1
            log.warning("can.bus.error", error=repr(exc), reopen_in_s=self._backoff)
        self._teardown()
        if not self._closed:
            await asyncio.sleep(self._backoff)
            self._backoff = min(self._backoff * 2.0, self.cfg.reopen_max_s)
            self._ensure_open_task()

    # --------------------------------------------------------------- receive
    async def recv(self) -> can.Message:
        """The next received frame; see :meth:`recv_batch`."""
        return (await self.recv_batch(1))[0]

    async def recv_batch(self, limit: int = 4096) -> list[can.Message]:
        """The frames received so far (at least one, at most ``limit``, oldest first);
        reopens the bus as often as needed.

        Opening runs in a thread of its own (:meth:`_call_factory`), so a slow
        USB/serial adapter's handshake does not stall the loop.

        Raises ``asyncio.CancelledError`` when cancelled and ``RuntimeError`` after :meth:`close`.
        """
        while True:
            if self._closed:
                raise RuntimeError("bus closed")
            if self._fail_request is not None:
                exc, self._fail_request = self._fail_request, None
                await self._fail(exc)
                continue
            rx = self._rx
            if rx is None:
                try:
                    await asyncio.shield(self._ensure_open_task())
                except asyncio.CancelledError:
                    if self._closed and not aio.cancelling():  # the open task was cancelled by close()
                        raise RuntimeError("bus closed") from None
                    raise
                continue
            try:
                items = await rx.get_batch(limit, self.cfg.silence_reopen_s)
            except asyncio.TimeoutError:
                if self._closed:
                    raise RuntimeError("bus closed") from None
                # Silence is a fault: a socket bound to an interface that was deleted and
                # re-created stays open and deaf; reopening binds to the new one.
                self.counters.silence_reopens += 1
                await self._fail(TimeoutError(f"no frame for {self.cfg.silence_reopen_s:g} s"), silence=True)
                continue
            if self._closed:
                raise RuntimeError("bus closed")
            frames: list[can.Message] = []
            for item in items:
                if isinstance(item, RxFailure):  # the last item: the thread has ended
                    if frames:
                        self._fail_request = item.exc  # deliver these first, reopen on the next call
                        break
                    await self._fail(item.exc)
                    break
                frames.append(item)
            if not frames:
                continue
            if not self._got_frame_since_open:
                self._got_frame_since_open = True
                self._backoff = self.cfg.reopen_initial_s
            c = self.counters
            c.rx_frames += len(frames)
            c.rx_error_frames += sum(1 for m in frames if m.is_error_frame)
            return frames

    def __aiter__(self) -> AsyncIterator[can.Message]:
        return self._iterate()

    async def _iterate(self) -> AsyncIterator[can.Message]:
        while not self._closed:
            try:
                yield await self.recv()
            except RuntimeError:
                return

    # ------------------------------------------------------------------ send
    def send(self, msg: can.Message) -> bool:
        """Queue one frame for sending; False if it was dropped (queue full or bus down)."""
        if self._bus is None:
            self.counters.tx_dropped += 1
            return False
        try:
            self._tx_queue.put_nowait(msg)
            return True
        except queue.Full:
            self.counters.tx_dropped += 1
            return False

    def send_many(self, msgs: Iterable[can.Message]) -> int:
        """Queue frames; returns how many were queued."""
        return sum(1 for m in msgs if self.send(m))

    async def drain(self, timeout: float = 5.0) -> bool:
        """Wait until the send queue is empty (True) or ``timeout`` passed (False)."""
        deadline = time.monotonic() + timeout
        while self._tx_queue.unfinished_tasks:
            if time.monotonic() > deadline:
                return False
            await asyncio.sleep(0.005)
        return True

    def _tx_worker(self) -> None:
        q = self._tx_queue
        fails_logged = 0
        while True:
            msg = q.get()
            try:
                if msg is None:
                    return
                with self._bus_lock:
                    bus = self._bus
                if bus is None:
                    self.counters.tx_dropped += 1
                    continue
                try:
                    bus.send(msg, timeout=self.cfg.tx_timeout_s)
                    self.counters.tx_frames += 1
                    fails_logged = 0
                except Exception as exc:  # noqa: BLE001 - python-can's errors, OSError, and whatever a driver raises:
                    # the thread must outlive every failed send, or no frame goes out again
                    self.counters.tx_errors += 1
                    if fails_logged < 3:  # do not flood the log while a bus is down
                        fails_logged += 1
                        log.warning("can.bus.send_failed", error=repr(exc), tx_errors=self.counters.tx_errors)
                    err = getattr(exc, "errno", None) or getattr(exc, "error_code", None)
                    if err in _FATAL_TX_ERRNOS:
                        self._request_reopen(exc, bus)
            finally:
                q.task_done()

    def _request_reopen(self, exc: BaseException, bus: can.BusABC) -> None:
        """Reopen after ``bus`` failed a send fatally, if it is still the bus in use: one torn down
        while the sender was inside its ``send`` (EBADF) says nothing about its successor."""
        loop = self._loop
        if loop is None or loop.is_closed():
            return

        def _set() -> None:
            if self._bus is not bus:
                return
            rx = self._rx
            if rx is not None:
                rx.fail(exc)  # wakes a pending recv()
            else:
                self._fail_request = exc

        with contextlib.suppress(RuntimeError):
            loop.call_soon_threadsafe(_set)
