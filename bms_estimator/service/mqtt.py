"""MQTT publishing of estimator results (aiomqtt), with Home Assistant discovery.

Topics (``<base>`` = ``mqtt.base_topic``, default ``bms``; cells are indexed
from 0 like the estimator's arrays):

* ``<base>/<pack_id>/cell/<i>/state``  JSON ``{"soc", "r0_ohm", "r1_ohm",
  "c1_f", "r2_ohm", "c2_f", "c0_v", "tau1_s", "tau2_s", "stale", "t_s"}``
  (non-finite numbers are ``null``; ``tau*`` derived from R*C when absent)
* ``<base>/<pack_id>/pack/state``      JSON, see :func:`pack_summary`
* ``<base>/<pack_id>/availability``    ``online`` / ``offline``, retained;
  ``offline`` is also the connection's last will (retained) and is published
  by :meth:`MqttPublisher.close` on a clean shutdown.
* ``<discovery_prefix>/sensor/<unique_id>/config``  retained Home Assistant
  discovery configs (pack SOC min/mean/max, current, stale cells; per cell
  SOC and R0), re-sent whenever ``<discovery_prefix>/status`` says ``online``.

The estimator never waits for the network: :meth:`~MqttPublisher.submit_cells`
and :meth:`~MqttPublisher.submit_pack` only put the newest payload per topic
into a bounded buffer (an older unsent payload of the same topic is replaced
and counted as dropped; when the buffer is full the least recently updated
topic is evicted and counted) and never raise. :meth:`~MqttPublisher.run` is
the publishing task: it connects, publishes, and reconnects with exponential
back-off and jitter while the broker is unreachable.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import math
import random
import re
import ssl
import threading
from collections import OrderedDict
from collections.abc import Iterable, Mapping
from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING, Any

import aiomqtt
import numpy as np
import structlog

if TYPE_CHECKING:
    from .config import MqttConfig
    from .health import Metrics

__all__ = ["CELL_KEYS", "MqttCounters", "MqttPublisher", "pack_summary"]

log = structlog.get_logger("bms.mqtt")

#: Keys of a cell state payload, in publishing order (``t_s`` is added last).
CELL_KEYS = ("soc", "r0_ohm", "r1_ohm", "c1_f", "r2_ohm", "c2_f", "c0_v", "tau1_s", "tau2_s", "stale")

_PUBLISH_BATCH = 256
# HA discovery object ids allow [a-zA-Z0-9_-] only.
_HA_ID_BAD = re.compile(r"[^A-Za-z0-9_-]")


@dataclass
class MqttCounters:
    published: int = 0  # messages acknowledged by the client library / broker
    dropped: int = 0  # state payloads never sent (superseded or evicted)
    connects: int = 0
    connect_failures: int = 0
    disconnects: int = 0  # connections lost after being established
    submit_errors: int = 0  # bad input to submit_*: logged and ignored


def _num(x: Any) -> float | int | bool | str | None:
    """JSON-safe scalar: numpy -> python, non-finite -> None."""
    if isinstance(x, np.generic):
        x = x.item()
    if isinstance(x, bool) or x is None or isinstance(x, str):
        return x
    if isinstance(x, int):
        return x
    try:
        f = float(x)
    except (TypeError, ValueError):
        return None
    return f if math.isfinite(f) else None


def _jsonable(obj: Any) -> Any:
    if isinstance(obj, Mapping):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, np.ndarray):
        return [_jsonable(v) for v in obj.tolist()]
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    return _num(obj)


def pack_summary(
    t_s: float,
    soc: Any,
    current_a: float | None,
    *,
    stale: Any = None,
    **extra: Any,
) -> dict[str, Any]:
    """Pack payload: ``t_s, soc_min, soc_mean, soc_max, current_a,
    cells_stale`` (+ ``extra``, e.g. counters). NaN SOCs are ignored."""
    s = np.asarray(soc, dtype=float).reshape(-1)
    finite = s[np.isfinite(s)]
    out: dict[str, Any] = {
        "t_s": t_s,
        "soc_min": float(finite.min()) if finite.size else None,
        "soc_mean": float(finite.mean()) if finite.size else None,
        "soc_max": float(finite.max()) if finite.size else None,
        "current_a": current_a,
        "cells_stale": int(np.count_nonzero(np.asarray(stale, dtype=bool))) if stale is not None else 0,
    }
    out.update(extra)
    return out


class _LatestBuffer:
    """Newest payload per topic, bounded; thread-safe."""

    def __init__(self, maxsize: int) -> None:
        self.maxsize = max(1, int(maxsize))
        self._items: OrderedDict[str, tuple[str, bool]] = OrderedDict()
        self._lock = threading.Lock()

    def __len__(self) -> int:
        return len(self._items)

    def put_many(self, items: Iterable[tuple[str, str, bool]]) -> int:
        """Insert; return how many payloads were dropped (superseded/evicted)."""
        dropped = 0
        with self._lock:
            for topic, payload, retain in items:
                if topic in self._items:
                    dropped += 1
                    self._items.move_to_end(topic)
                self._items[topic] = (payload, retain)
                while len(self._items) > self.maxsize:
                    self._items.popitem(last=False)
                    dropped += 1
        return dropped

    def pop_all(self) -> list[tuple[str, str, bool]]:
        with self._lock:
            items = [(t, p, r) for t, (p, r) in self._items.items()]
            self._items.clear()
        return items

    def restore(self, items: list[tuple[str, str, bool]]) -> int:
        """Put unsent items back at the front unless a newer payload exists."""
        dropped = 0
        with self._lock:
            for topic, payload, retain in reversed(items):
                if topic in self._items:
                    dropped += 1  # superseded meanwhile
                    continue
                self._items[topic] = (payload, retain)
                self._items.move_to_end(topic, last=False)
            while len(self._items) > self.maxsize:
                self._items.popitem(last=False)
                dropped += 1
        return dropped


class MqttPublisher:
    """Publishes estimator states to MQTT; see the module docstring.

    ``submit_*`` may be called from any thread and before :meth:`run`
    started (payloads wait in the buffer). Run :meth:`run` as a task; stop
    it with :meth:`close` (publishes ``offline``, disconnects cleanly) or by
    cancelling it (best-effort ``offline``).
    """

    def __init__(
        self,
        cfg: MqttConfig,
        pack_id: str,
        n_cells: int,
        *,
        metrics: Metrics | None = None,
        sw_version: str | None = None,
    ) -> None:
        self.cfg = cfg
        self.pack_id = pack_id
        self.n_cells = int(n_cells)
        self.metrics = metrics
        self.sw_version = sw_version or _package_version()
        self.counters = MqttCounters()

        root = f"{cfg.base_topic}/{pack_id}"
        self.topic_root = root
        self.availability_topic = f"{root}/availability"
        self.pack_topic = f"{root}/pack/state"
        self.ha_status_topic = f"{cfg.discovery_prefix}/status"
        self._cell_topics = [f"{root}/cell/{i}/state" for i in range(self.n_cells)]

        self._buffer = _LatestBuffer(cfg.buffer_max)
        self._wakeup = asyncio.Event()
        self._closing = False
        self._discovery_due = False
        self._connected = False
        self._loop: asyncio.AbstractEventLoop | None = None
        self._loop_thread: int | None = None
        self._run_task: asyncio.Task[None] | None = None
        self._done: asyncio.Event | None = None
        self._tls: ssl.SSLContext | None = None
        self._submit_error_logged = 0

    # ------------------------------------------------------------------ topics
    def cell_topic(self, i: int) -> str:
        return self._cell_topics[i]

    @property
    def connected(self) -> bool:
        return self._connected

    @property
    def buffered(self) -> int:
        return len(self._buffer)

    def stats(self) -> dict[str, int]:
        return asdict(self.counters)

    # ------------------------------------------------------------------ submit
    def submit_cells(self, t_s: float, arrays: Mapping[str, Any]) -> None:
        """Queue one state per cell from per-cell arrays (length ``n_cells``
        or scalars). Keys: :data:`CELL_KEYS` plus any extra numeric arrays.
        Never raises, never blocks."""
        if not self.cfg.enabled or self._closing:
            return
        try:
            n = self.n_cells
            cols: dict[str, list[Any]] = {}
            keys = [k for k in CELL_KEYS if k in arrays] + [k for k in arrays if k not in CELL_KEYS]
            for key in keys:
                if key == "t_s":
                    continue
                arr = np.asarray(arrays[key])
                if arr.ndim == 0:
                    arr = np.broadcast_to(arr, (n,))
                arr = arr.reshape(-1)
                if arr.shape[0] != n:
                    raise ValueError(f"{key!r} has {arr.shape[0]} values, expected {n}")
                if key == "stale":
                    cols[key] = [bool(v) for v in arr.astype(bool).tolist()]
                else:
                    cols[key] = [_num(v) for v in arr.astype(float).tolist()]
            for tau, (r, c) in (("tau1_s", ("r1_ohm", "c1_f")), ("tau2_s", ("r2_ohm", "c2_f"))):
                if tau not in cols and r in cols and c in cols:
                    cols[tau] = [
                        _num(rv * cv) if rv is not None and cv is not None else None
                        for rv, cv in zip(cols[r], cols[c])
                    ]
            if "stale" not in cols:
                cols["stale"] = [False] * n
            order = [k for k in CELL_KEYS if k in cols] + [k for k in cols if k not in CELL_KEYS]
            t = _num(t_s)
            items = []
            for i in range(n):
                payload = {k: cols[k][i] for k in order}
                payload["t_s"] = t
                items.append((self._cell_topics[i], json.dumps(payload, allow_nan=False), False))
            self._put(items)
        except Exception as exc:  # noqa: BLE001 - must never raise into the estimator
            self._submit_failed("submit_cells", exc)

    def submit_pack(self, payload: Mapping[str, Any]) -> None:
        """Queue the pack state (any JSON-able mapping, see :func:`pack_summary`).
        Never raises, never blocks."""
        if not self.cfg.enabled or self._closing:
            return
        try:
            if not isinstance(payload, Mapping):
                raise TypeError(f"pack payload must be a mapping, not {type(payload).__name__}")
            text = json.dumps(_jsonable(payload), allow_nan=False)
            self._put([(self.pack_topic, text, False)])
        except Exception as exc:  # noqa: BLE001
            self._submit_failed("submit_pack", exc)

    def _submit_failed(self, what: str, exc: Exception) -> None:
        self._count("submit_errors")
        # Log the first few and then every 1000th, so a bad caller cannot flood the log.
        if self._submit_error_logged < 5 or self.counters.submit_errors % 1000 == 0:
            self._submit_error_logged += 1
            with contextlib.suppress(Exception):
                log.error("mqtt submit rejected", call=what, error=f"{type(exc).__name__}: {exc}")

    def _put(self, items: list[tuple[str, str, bool]]) -> None:
        dropped = self._buffer.put_many(items)
        if dropped:
            self._count("dropped", dropped)
        self._wake()

    def _wake(self) -> None:
        loop = self._loop
        if loop is None or threading.get_ident() == self._loop_thread:
            self._wakeup.set()
        elif not loop.is_closed():
            with contextlib.suppress(RuntimeError):
                loop.call_soon_threadsafe(self._wakeup.set)

    def _count(self, name: str, n: int = 1) -> None:
        setattr(self.counters, name, getattr(self.counters, name) + n)
        m = self.metrics
        if m is not None:
            mname = {
                "published": "mqtt_published",
                "dropped": "mqtt_dropped",
                "connects": "mqtt_connects",
                "connect_failures": "mqtt_connect_failures",
            }.get(name)
            if mname:
                m.inc(mname, n)

    def _set_connected(self, value: bool) -> None:
        self._connected = value
        if self.metrics is not None:
            self.metrics.set("mqtt_connected", int(value))

    # --------------------------------------------------------------- discovery
    def discovery_messages(self) -> list[tuple[str, str]]:
        """Home Assistant discovery (topic, JSON config) pairs."""
        pid = _HA_ID_BAD.sub("_", self.pack_id)
        prefix = self.cfg.discovery_prefix
        device = {
            "identifiers": [f"bms_estimator_{pid}"],
            "name": f"Battery pack {pid}",
            "manufacturer": "bms-estimator",
            "model": "ECM + SOC estimator",
            "sw_version": self.sw_version,
        }
        common = {
            "availability_topic": self.availability_topic,
            "payload_available": "online",
            "payload_not_available": "offline",
            "device": device,
        }

        def pct(key: str) -> str:
            return (
                f"{{{{ (value_json.{key} * 100) | round(2) if value_json.{key} is number else none }}}}"
            )

        def scaled(key: str, factor: float, digits: int) -> str:
            return (
                f"{{{{ (value_json.{key} * {factor}) | round({digits}) "
                f"if value_json.{key} is number else none }}}}"
            )

        out: list[tuple[str, str]] = []

        def add(uid: str, name: str, state_topic: str, template: str, **extra: Any) -> None:
            cfg = {
                "name": name,
                "unique_id": uid,
                "state_topic": state_topic,
                "value_template": template,
                **common,
                **extra,
            }
            out.append((f"{prefix}/sensor/{uid}/config", json.dumps(cfg)))

        battery = {"device_class": "battery", "unit_of_measurement": "%", "state_class": "measurement"}
        for key, label in (("soc_min", "SOC min"), ("soc_mean", "SOC mean"), ("soc_max", "SOC max")):
            add(f"bms_{pid}_pack_{key}", label, self.pack_topic, pct(key), **battery)
        add(
            f"bms_{pid}_pack_current",
            "Current",
            self.pack_topic,
            scaled("current_a", 1, 3),
            device_class="current",
            unit_of_measurement="A",
            state_class="measurement",
        )
        add(
            f"bms_{pid}_pack_cells_stale",
            "Stale cells",
            self.pack_topic,
            "{{ value_json.cells_stale }}",
            state_class="measurement",
            entity_category="diagnostic",
        )
        for i in range(self.n_cells):
            topic = self._cell_topics[i]
            add(f"bms_{pid}_cell{i}_soc", f"Cell {i} SOC", topic, pct("soc"), **battery)
            add(
                f"bms_{pid}_cell{i}_r0",
                f"Cell {i} R0",
                topic,
                scaled("r0_ohm", 1000, 4),
                unit_of_measurement="mΩ",
                state_class="measurement",
                icon="mdi:resistor",
                entity_category="diagnostic",
            )
        return out

    # -------------------------------------------------------------------- run
    async def run(self) -> None:
        """Publishing task: returns after :meth:`close`, or raises
        ``CancelledError`` when cancelled. Returns at once when MQTT is
        disabled. Never raises anything else."""
        if not self.cfg.enabled:
            log.info("mqtt disabled")
            return
        self._loop = asyncio.get_running_loop()
        self._loop_thread = threading.get_ident()
        self._run_task = asyncio.current_task()
        self._done = asyncio.Event()
        failures = 0
        try:
            while not self._closing:
                try:
                    was_connected = await self._session()
                except asyncio.CancelledError:
                    raise
                except Exception as exc:  # noqa: BLE001 - keep going whatever happens
                    if _cancelling():
                        raise asyncio.CancelledError from exc
                    log.exception("mqtt session error", error=repr(exc))
                    was_connected = False
                if self._closing:
                    break
                failures = 0 if was_connected else failures + 1
                delay = self._backoff(max(failures, 1))
                log.info("mqtt reconnecting", in_s=round(delay, 3), failed_attempts=failures)
                self._wakeup.clear()
                with contextlib.suppress(asyncio.TimeoutError):
                    # Woken early only by close() (submissions are ignored here).
                    await asyncio.wait_for(self._wait_closing(), timeout=delay)
        finally:
            self._set_connected(False)
            self._done.set()

    async def _wait_closing(self) -> None:
        while not self._closing:
            self._wakeup.clear()
            await self._wakeup.wait()

    def _backoff(self, attempt: int) -> float:
        lo, hi = self.cfg.reconnect_min_s, self.cfg.reconnect_max_s
        base = min(hi, lo * (2.0 ** min(attempt - 1, 60)))
        return max(lo, random.uniform(base / 2, base))

    async def close(self, timeout_s: float = 5.0) -> None:
        """Publish ``offline``, disconnect, and wait for :meth:`run` to end
        (cancelling it after ``timeout_s``). Further submissions are ignored."""
        self._closing = True
        self._wake()
        task, done = self._run_task, self._done
        if task is None or task.done() or task is asyncio.current_task() or done is None:
            return
        try:
            await asyncio.wait_for(done.wait(), timeout=timeout_s)
        except asyncio.TimeoutError:
            log.warning("mqtt publisher did not stop in time; cancelling")
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await asyncio.wait_for(asyncio.shield(done.wait()), timeout=2.0)

    # ----------------------------------------------------------------- session
    def _tls_context(self) -> ssl.SSLContext | None:
        t = self.cfg.tls
        if not t.enabled:
            return None
        if self._tls is None:
            ctx = ssl.create_default_context(
                ssl.Purpose.SERVER_AUTH, cafile=str(t.ca_file) if t.ca_file else None
            )
            if t.cert_file is not None:
                ctx.load_cert_chain(str(t.cert_file), str(t.key_file) if t.key_file else None)
            if t.insecure:
                ctx.check_hostname = False
                ctx.verify_mode = ssl.CERT_NONE
            self._tls = ctx
        return self._tls

    def _make_client(self) -> aiomqtt.Client:
        cfg = self.cfg
        client = aiomqtt.Client(
            cfg.host,
            cfg.port,
            username=cfg.username,
            password=cfg.password.get_secret_value() if cfg.password is not None else None,
            identifier=cfg.client_id or f"bms-estimator-{self.pack_id}",
            will=aiomqtt.Will(self.availability_topic, "offline", qos=cfg.qos, retain=True),
            keepalive=cfg.keepalive,
            timeout=cfg.timeout_s,
            tls_context=self._tls_context(),
        )
        client.pending_calls_threshold = 10 * _PUBLISH_BATCH
        return client

    async def _session(self) -> bool:
        """One connection: True if it got connected (then lost or closed)."""
        cfg = self.cfg
        try:
            client = self._make_client()
        except (OSError, ValueError, ssl.SSLError) as exc:
            self._count("connect_failures")
            log.error("mqtt client setup failed", error=f"{type(exc).__name__}: {exc}")
            return False
        entered = False
        try:
            async with client:
                entered = True
                self._count("connects")
                self._set_connected(True)
                log.info("mqtt connected", host=cfg.host, port=cfg.port, tls=cfg.tls.enabled)
                await self._serve(client)
        except aiomqtt.MqttError as exc:
            if _cancelling():
                # e.g. the disconnect in __aexit__ timed out while we were being
                # cancelled: never turn a cancellation into a reconnect.
                raise asyncio.CancelledError from exc
            if not entered:
                self._count("connect_failures")
                log.warning(
                    "mqtt connect failed",
                    host=cfg.host,
                    port=cfg.port,
                    error=str(exc),
                    failures=self.counters.connect_failures,
                )
            elif not self._closing:
                self._count("disconnects")
                log.warning("mqtt connection lost", error=str(exc))
        finally:
            self._set_connected(False)
        return entered

    async def _serve(self, client: aiomqtt.Client) -> None:
        cfg = self.cfg
        listener: asyncio.Task[None] | None = None
        wake: asyncio.Task[bool] | None = None
        try:
            if cfg.discovery:
                await client.subscribe(self.ha_status_topic, qos=1)
            await self._publish_one(client, self.availability_topic, "online", True)
            if cfg.discovery:
                self._discovery_due = False
                await self._publish_discovery(client)
            listener = asyncio.create_task(self._listen(client))
            while True:
                if listener.done():
                    listener.result()  # re-raise MqttError on a lost connection
                    raise aiomqtt.MqttError("message listener ended")
                if self._discovery_due:
                    self._discovery_due = False
                    await self._publish_discovery(client)
                closing = self._closing
                items = self._buffer.pop_all()
                if items:
                    await self._publish_items(client, items)
                if closing:
                    await self._publish_one(client, self.availability_topic, "offline", True)
                    log.info("mqtt closing: published offline")
                    return
                if items:
                    continue
                self._wakeup.clear()
                if len(self._buffer) or self._discovery_due or self._closing:
                    continue
                wake = asyncio.create_task(self._wakeup.wait())
                await asyncio.wait({wake, listener}, return_when=asyncio.FIRST_COMPLETED)
                wake.cancel()
                wake = None
        except asyncio.CancelledError:
            # Cancelled (not close()): best effort to tell the world we are gone.
            with contextlib.suppress(BaseException):
                await asyncio.wait_for(
                    client.publish(self.availability_topic, "offline", qos=cfg.qos, retain=True),
                    timeout=1.0,
                )
            raise
        finally:
            if wake is not None:
                wake.cancel()
            if listener is not None:
                listener.cancel()
                with contextlib.suppress(BaseException):
                    await listener

    async def _listen(self, client: aiomqtt.Client) -> None:
        async for message in client.messages:
            if message.topic.matches(self.ha_status_topic):
                payload = message.payload
                if isinstance(payload, (bytes, bytearray)):
                    payload = bytes(payload).decode("utf-8", "replace")
                if str(payload).strip().lower() == "online":
                    log.info("home assistant online: re-sending discovery")
                    self._discovery_due = True
                    self._wakeup.set()

    async def _publish_one(self, client: aiomqtt.Client, topic: str, payload: str, retain: bool) -> None:
        await client.publish(topic, payload, qos=self.cfg.qos, retain=retain, timeout=self.cfg.timeout_s)
        self._count("published")

    async def _publish_discovery(self, client: aiomqtt.Client) -> None:
        msgs = [(t, p, True) for t, p in self.discovery_messages()]
        failed = await self._publish_batch(client, msgs)
        if failed:
            self._discovery_due = True  # try again on the next connection
            raise failed[0][1]
        log.info("home assistant discovery published", sensors=len(msgs))

    async def _publish_items(self, client: aiomqtt.Client, items: list[tuple[str, str, bool]]) -> None:
        failed = await self._publish_batch(client, items)
        if failed:
            unsent = [item for item, _ in failed]
            dropped = self._buffer.restore(unsent)
            if dropped:
                self._count("dropped", dropped)
            raise failed[0][1]

    async def _publish_batch(
        self, client: aiomqtt.Client, items: list[tuple[str, str, bool]]
    ) -> list[tuple[tuple[str, str, bool], aiomqtt.MqttError]]:
        """Publish concurrently (QoS>0 waits for acks); return the failures."""
        failed: list[tuple[tuple[str, str, bool], aiomqtt.MqttError]] = []
        qos, timeout = self.cfg.qos, self.cfg.timeout_s
        for start in range(0, len(items), _PUBLISH_BATCH):
            chunk = items[start : start + _PUBLISH_BATCH]
            if failed:  # connection is broken: do not even try the rest
                failed.extend((item, failed[0][1]) for item in chunk)
                continue
            results = await asyncio.gather(
                *(client.publish(t, p, qos=qos, retain=r, timeout=timeout) for t, p, r in chunk),
                return_exceptions=True,
            )
            ok = 0
            for item, res in zip(chunk, results):
                if res is None:
                    ok += 1
                elif isinstance(res, aiomqtt.MqttError):
                    failed.append((item, res))
                elif isinstance(res, BaseException):
                    failed.append((item, aiomqtt.MqttError(f"{type(res).__name__}: {res}")))
            if ok:
                self._count("published", ok)
        return failed


def _cancelling() -> bool:
    """True while the current task has a pending cancellation request."""
    task = asyncio.current_task()
    return bool(task is not None and getattr(task, "cancelling", lambda: 0)())


def _package_version() -> str:
    try:
        from importlib.metadata import version

        return version("bms-estimator")
    except Exception:  # noqa: BLE001 - not installed (source tree)
        return "0+unknown"
