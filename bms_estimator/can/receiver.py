"""Reception off the event loop: one thread reads the bus into a bounded queue that counts what it drops.

The event loop that runs the estimator also formats and sends its outputs; a 200-cell
sample holds it for milliseconds to tens of milliseconds. Frames must not wait for
that: while the loop is busy they would pile up in the kernel's socket buffer, and
beyond it be lost where nothing counts them. :class:`RxThread` therefore calls the
python-can bus's blocking ``recv`` in a thread of its own (the socket calls release
the GIL) and appends each frame to a bounded queue:

* a full queue drops the frame and counts it (``BusCounters.rx_dropped``, exported
  as ``bms_can_rx_dropped{reason="queue_full"}``): frames are lost only where
  a counter sees them;
* the loop is woken once per batch, not once per frame (``call_soon_threadsafe``
  only when the queue turns non-empty), and takes everything queued in one
  :meth:`RxThread.get_batch`;
* an exception from ``recv`` (the interface went away) ends the thread and is
  handed to the loop as the next item, a :class:`RxFailure`, so the owner can reopen.

The queue is a ``collections.deque`` under a lock: appends and the batch swap are
O(1), and its length is the backlog (``RxThread.backlog``).
"""

from __future__ import annotations

import asyncio
import collections
import threading

import can
import structlog

from .. import aio

__all__ = ["RxFailure", "RxThread"]

log = structlog.get_logger(__name__)


class RxFailure:
    """Queued when the bus's ``recv`` raised; the thread has ended."""

    __slots__ = ("exc",)

    def __init__(self, exc: BaseException) -> None:
        self.exc = exc


class RxThread:
    """Reads ``bus`` in a daemon thread into a queue of at most ``maxsize`` frames.

    ``on_drop`` is called (from the thread) for every frame the full queue dropped.
    Start with :meth:`start` inside a running loop; :meth:`stop` ends it (within ``poll_s``).
    """

    def __init__(self, bus: can.BusABC, maxsize: int, *, on_drop: collections.abc.Callable[[], None],
                 poll_s: float = 0.1, name: str = "bms-can-rx") -> None:
        self.bus = bus
        self.maxsize = max(1, int(maxsize))
        self.poll_s = poll_s
        self._on_drop = on_drop
        self._items: collections.deque[can.Message | RxFailure] = collections.deque()
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._wake: asyncio.Event | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._notified = False
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)

    @property
    def backlog(self) -> int:
        return len(self._items)

    def start(self) -> None:
        self._loop = asyncio.get_running_loop()
        self._wake = asyncio.Event()
        self._thread.start()

    def stop(self, timeout: float | None = None) -> None:
        """Ask the thread to end and wait up to ``timeout`` for it (it may still be in ``recv``)."""
        self._stop.set()
        if self._thread.is_alive() and self._thread is not threading.current_thread():
            self._thread.join(timeout)

    @property
    def stopped(self) -> bool:
        return self._stop.is_set()

    # ------------------------------------------------------------ the thread
    def _run(self) -> None:
        bus, poll = self.bus, self.poll_s
        while not self._stop.is_set():
            try:
                msg = bus.recv(timeout=poll)
            except Exception as exc:  # noqa: BLE001 - any receive failure: the owner reopens
                if not self._stop.is_set():
                    self.fail(exc)
                return
            if msg is not None:
                self._put(msg)

    def _put(self, msg: can.Message) -> None:
        with self._lock:
            if len(self._items) >= self.maxsize:
                dropped = True
            else:
                dropped = False
                self._items.append(msg)
                wake = not self._notified
                self._notified = True
        if dropped:
            self._on_drop()
        elif wake:
            self._notify()

    def fail(self, exc: BaseException) -> None:
        """Queue a failure (always, even past ``maxsize``: it must be seen). Any thread."""
        with self._lock:
            self._items.append(RxFailure(exc))
            self._notified = True
        self._notify()

    def _notify(self) -> None:
        loop, wake = self._loop, self._wake
        if loop is None or wake is None or loop.is_closed():
            return
        try:
            loop.call_soon_threadsafe(wake.set)
        except RuntimeError:  # the loop closed meanwhile
            pass

    # -------------------------------------------------------------- the loop
    def take(self, limit: int) -> list[can.Message | RxFailure]:
        """Up to ``limit`` queued items, oldest first, without waiting."""
        with self._lock:
            items = self._items
            if len(items) <= limit:
                out = list(items)
                items.clear()
            else:
                out = [items.popleft() for _ in range(limit)]
            if not items:
                self._notified = False
        return out

    async def get_batch(self, limit: int = 4096, timeout: float | None = None) -> list[can.Message | RxFailure]:
        """Wait for at least one item (raises ``TimeoutError`` after ``timeout``) and return up to ``limit``."""
        assert self._wake is not None, "start() first"
        while True:
            out = self.take(limit)
            if out:
                return out
            self._wake.clear()
            with self._lock:
                if self._items:
                    continue
            if timeout is None:
                await self._wake.wait()
            else:
                await aio.wait_for(self._wake.wait(), timeout)
