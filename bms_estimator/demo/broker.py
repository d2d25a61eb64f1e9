"""The demo's MQTT broker: the one given, else one it starts itself, else none.

:func:`open_broker` (a context manager) picks, for ``choice``:

``HOST[:PORT]``  that broker (nothing is started or stopped)
``auto``         ``mosquitto`` when the program is installed (``$PATH``, ``/usr/sbin``,
                 ``/usr/local/sbin``), else ``embedded``, else ``none``
``mosquitto``    a Mosquitto process on a free 127.0.0.1 port with a generated config
                 (anonymous, no persistence, a deep per-client queue, log to a file) in a
                 temporary folder; terminated
                 (SIGTERM, then SIGKILL) when the context ends
``embedded``     amqtt's broker (pure Python, asyncio) in a child process of its own (in the
                 demo's process it held the service back through the interpreter lock), on a
                 free 127.0.0.1 port, anonymous, without its logging and ``$SYS`` plugins;
                 it ends when the context closes its stdin (or the demo is gone)
``none``         no broker: the service runs with MQTT disabled

A choice that cannot be had falls through to the next one of ``auto`` and the reason is kept
in :attr:`BrokerInfo.note` (printed by the demo).
"""

from __future__ import annotations

import asyncio
import contextlib
import importlib
import logging
import os
import select
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

from .. import aio
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
                "embedded": "embedded amqtt broker (pure Python, own process)"}.get(self.kind, self.kind)
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
#: what the child process prints once its listener is bound
_READY = "bms-demo-broker-ready"


def serve_embedded(port: int) -> None:
    """The child process of :class:`_EmbeddedBroker`: amqtt's broker on 127.0.0.1:``port``,
    anonymous, without its logging and ``$SYS`` plugins; prints :data:`_READY` once bound and
    ends when its stdin closes (the demo stops it, or the demo is gone)."""
    import sys

    logging.getLogger("amqtt").setLevel(logging.CRITICAL)  # client connects/disconnects are not the demo's news

    async def main() -> None:
        from amqtt.broker import Broker

        config = {
            "listeners": {"default": {"type": "tcp", "bind": f"127.0.0.1:{port}"}},
            "plugins": {"amqtt.plugins.authentication.AnonymousAuthPlugin": {"allow_anonymous": True}},
        }
        broker = Broker(config)
        await broker.start()
        print(_READY, flush=True)
        await asyncio.to_thread(sys.stdin.read)  # returns at EOF: the parent closed it or exited
        with contextlib.suppress(Exception):
            await aio.wait_for(broker.shutdown(), 5)

    asyncio.run(main())


class _EmbeddedBroker:
    """amqtt's broker (pure Python) in a child process of its own: in the demo's process it
    shared one interpreter lock with the service and the subscriber, and every message it
    routed held the estimator back."""

    def __init__(self, port: int) -> None:
        self.port = port
        self.proc: subprocess.Popen[str] | None = None
        self._log = tempfile.TemporaryFile("w+")

    def start(self, timeout: float = 20.0) -> None:
        root = str(Path(__file__).resolve().parents[2])  # the folder holding bms_estimator
        env = dict(os.environ)
        env["PYTHONPATH"] = root + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
        code = f"from bms_estimator.demo.broker import serve_embedded; serve_embedded({int(self.port)})"
        try:
            self.proc = subprocess.Popen([sys.executable, "-c", code], stdin=subprocess.PIPE,
                                         stdout=subprocess.PIPE, stderr=self._log, text=True, env=env)
        except OSError as exc:
            raise BrokerUnavailable(f"embedded broker did not start: {exc}") from exc
        assert self.proc.stdout is not None
        deadline = time.monotonic() + timeout
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                self.stop()
                raise BrokerUnavailable(f"embedded broker did not start within {timeout:g} s")
            ready, _, _ = select.select([self.proc.stdout], [], [], left)
            if not ready:
                continue
            line = self.proc.stdout.readline()
            if line.strip() == _READY:
                return
            if not line:  # the child ended before it was ready
                self.stop()
                raise BrokerUnavailable(f"embedded broker failed: {self._tail()}")

    def _tail(self) -> str:
        with contextlib.suppress(Exception):
            self._log.seek(0)
            lines = [ln.strip() for ln in self._log.read().splitlines() if ln.strip()]
            if lines:
                return lines[-1][:300]
        return f"exit code {self.proc.returncode if self.proc is not None else '?'}"

    def stop(self, timeout: float = 10.0) -> None:
        proc = self.proc
        if proc is not None and proc.poll() is None:
            with contextlib.suppress(Exception):
                assert proc.stdin is not None
                proc.stdin.close()  # the child shuts its broker down and ends
            try:
                proc.wait(timeout)
            except subprocess.TimeoutExpired:
                proc.terminate()
                try:
                    proc.wait(2)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait()
        if proc is not None:
            for f in (proc.stdin, proc.stdout):
                with contextlib.suppress(Exception):
                    if f is not None:
                        f.close()
        with contextlib.suppress(Exception):
            self._log.close()


def embedded_available() -> bool:
    """True when ``amqtt.broker`` imports.  It is imported, not only found
    (``importlib.util.find_spec``): a broken install (a dependency missing or of the wrong
    version) is found but fails in the broker's child process, where it would be a traceback."""
    try:
        importlib.import_module("amqtt.broker")
    except Exception:  # noqa: BLE001 - ImportError or a broken install
        return False
    return True


@contextlib.contextmanager
def _embedded() -> Iterator[BrokerInfo]:
    if not embedded_available():
        raise BrokerUnavailable("the embedded broker needs the 'amqtt' package (pip install amqtt)")
    broker = None
    try:
        last: BaseException | None = None
        for _attempt in range(3):  # a free port can be taken between the probe and the bind
            broker = _EmbeddedBroker(free_port())
            try:
                broker.start()
            except BrokerUnavailable as exc:
                last, broker = exc, None
                continue
            break
        if broker is None:
            raise BrokerUnavailable(str(last))
        pid = broker.proc.pid if broker.proc is not None else "?"
        yield BrokerInfo("embedded", "127.0.0.1", broker.port, f"amqtt, process {pid}")
    finally:
        if broker is not None:
            broker.stop()


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
