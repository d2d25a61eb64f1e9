"""The demo's MQTT broker: the one given, else one it starts itself, else none.

:func:`open_broker` (a context manager) picks, for ``choice``:

``HOST[:PORT]``  that broker (nothing is started or stopped)
``auto``         ``mosquitto`` when the program is installed (``$PATH``, ``/usr/sbin``,
                 ``/usr/local/sbin``), else ``embedded``, else ``none``
``mosquitto``    a Mosquitto process on a free 127.0.0.1 port with a generated config
                 (anonymous, no persistence, a deep per-client queue, log to a file) in a
                 temporary folder; terminated
                 (SIGTERM, then SIGKILL) when the context ends
``embedded``     amqtt's broker (pure Python, asyncio) in a thread of its own with its own
                 event loop, on a free 127.0.0.1 port, anonymous, without its logging and
                 ``$SYS`` plugins; shut down when the context ends
``none``         no broker: the service runs with MQTT disabled

A choice that cannot be had falls through to the next one of ``auto`` and the reason is kept
in :attr:`BrokerInfo.note` (printed by the demo).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import tempfile
import threading
from collections.abc import Iterator
from dataclasses import dataclass

from ..mosquitto import Mosquitto, MosquittoError, find_mosquitto, free_port

__all__ = ["BrokerInfo", "BrokerUnavailable", "find_mosquitto", "free_port", "open_broker"]

CHOICES = ("auto", "mosquitto", "embedded", "none")


class BrokerUnavailable(RuntimeError):
    """The broker kind asked for cannot be started here."""


@dataclass
class BrokerInfo:
    kind: str  # "given", "mosquitto", "embedded", "none"
    host: str | None = None
    port: int | None = None
    note: str = ""

    @property
    def enabled(self) -> bool:
        return self.host is not None

    def describe(self) -> str:
        if not self.enabled:
            return "none: MQTT disabled" + (f" ({self.note})" if self.note else "")
        what = {"given": "given broker", "mosquitto": "Mosquitto started by the demo",
                "embedded": "embedded amqtt broker (pure Python)"}.get(self.kind, self.kind)
        return f"{what} at {self.host}:{self.port}" + (f" ({self.note})" if self.note else "")


# ------------------------------------------------------------------ mosquitto
@contextlib.contextmanager
def _mosquitto(program: str) -> Iterator[BrokerInfo]:
    with tempfile.TemporaryDirectory(prefix="bms-demo-mosquitto-") as tmp:
        last_err = ""
        for _attempt in range(3):  # a free port can be taken between the probe and the bind
            broker = Mosquitto(tmp, program=program)
            try:
                broker.start()
                break
            except MosquittoError as exc:
                last_err = str(exc)
        else:
            raise BrokerUnavailable(f"mosquitto ({program}) did not start: {last_err.strip()[:300]}")
        try:
            pid = broker.proc.pid if broker.proc is not None else "?"
            yield BrokerInfo("mosquitto", broker.host, broker.port, f"{program}, pid {pid}")
        finally:
            broker.stop()


# ------------------------------------------------------------------- embedded
class _EmbeddedBroker:
    """amqtt's broker on its own event loop in a daemon thread."""

    def __init__(self, port: int) -> None:
        self.port = port
        self._loop: asyncio.AbstractEventLoop | None = None
        self._broker = None
        self._ready = threading.Event()
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._main, name="bms-demo-broker", daemon=True)

    def start(self, timeout: float = 15.0) -> None:
        self._thread.start()
        if not self._ready.wait(timeout):
            raise BrokerUnavailable("embedded broker did not start in time")
        if self._error is not None:
            raise BrokerUnavailable(f"embedded broker failed: {type(self._error).__name__}: {self._error}")

    def _main(self) -> None:
        loop = self._loop = asyncio.new_event_loop()
        asyncio.set_event_loop(loop)
        try:
            loop.run_until_complete(self._start())
        except BaseException as exc:  # noqa: BLE001 - reported to start()
            self._error = exc
            self._ready.set()
            loop.close()
            return
        self._ready.set()
        try:
            loop.run_forever()
        finally:
            with contextlib.suppress(Exception):
                loop.run_until_complete(loop.shutdown_asyncgens())
            loop.close()

    async def _start(self) -> None:
        from amqtt.broker import Broker

        config = {
            "listeners": {"default": {"type": "tcp", "bind": f"127.0.0.1:{self.port}"}},
            "plugins": {"amqtt.plugins.authentication.AnonymousAuthPlugin": {"allow_anonymous": True}},
        }
        self._broker = Broker(config)
        await self._broker.start()

    def stop(self, timeout: float = 10.0) -> None:
        loop, broker = self._loop, self._broker
        if loop is None or loop.is_closed():
            return

        async def _shutdown() -> None:
            if broker is not None:
                with contextlib.suppress(Exception):
                    await asyncio.wait_for(broker.shutdown(), timeout)
            # anything the broker left running (client handlers) ends with the loop
            me = asyncio.current_task()
            for task in asyncio.all_tasks():
                if task is not me:
                    task.cancel()

        fut = asyncio.run_coroutine_threadsafe(_shutdown(), loop)
        with contextlib.suppress(Exception):
            fut.result(timeout + 2)
        loop.call_soon_threadsafe(loop.stop)
        self._thread.join(timeout)


def embedded_available() -> bool:
    try:
        import amqtt.broker  # noqa: F401
    except Exception:  # noqa: BLE001 - ImportError or a broken install
        return False
    return True


@contextlib.contextmanager
def _embedded() -> Iterator[BrokerInfo]:
    if not embedded_available():
        raise BrokerUnavailable("the embedded broker needs the 'amqtt' package (pip install amqtt)")
    amqtt_log = logging.getLogger("amqtt")
    old_level = amqtt_log.level
    amqtt_log.setLevel(logging.CRITICAL)  # client connects/disconnects are not the demo's news
    broker = None
    try:
        last: BaseException | None = None
        for _attempt in range(3):
            port = free_port()
            broker = _EmbeddedBroker(port)
            try:
                broker.start()
            except BrokerUnavailable as exc:
                last, broker = exc, None
                continue
            break  # Broker.start() returns once its listener is bound
        if broker is None:
            raise BrokerUnavailable(str(last))
        yield BrokerInfo("embedded", "127.0.0.1", broker.port, "amqtt")
    finally:
        if broker is not None:
            broker.stop()
        amqtt_log.setLevel(old_level)


# ---------------------------------------------------------------------- choose
@contextlib.contextmanager
def open_broker(choice: str = "auto") -> Iterator[BrokerInfo]:
    """The broker for ``choice`` (module docstring); stops what it started on exit."""
    from ..replay.dashboard import parse_broker

    choice = (choice or "auto").strip()
    low = choice.lower()
    if low not in CHOICES:
        host, port = parse_broker(choice)
        yield BrokerInfo("given", host, port)
        return
    notes: list[str] = []
    order = {"auto": ("mosquitto", "embedded"), "mosquitto": ("mosquitto", "embedded"),
             "embedded": ("embedded",), "none": ()}[low]
    with contextlib.ExitStack() as stack:
        for kind in order:
            try:
                if kind == "mosquitto":
                    program = find_mosquitto()
                    if program is None:
                        raise BrokerUnavailable("mosquitto is not installed")
                    info = stack.enter_context(_mosquitto(program))
                else:
                    info = stack.enter_context(_embedded())
            except BrokerUnavailable as exc:
                notes.append(str(exc))
                continue
            if notes:
                info.note = "; ".join([*notes, info.note]) if info.note else "; ".join(notes)
            yield info
            return
    if low == "none":
        notes.append("--broker none")
    yield BrokerInfo("none", note="; ".join(notes))
