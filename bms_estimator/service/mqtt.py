"""MQTT publishing of estimator results (aiomqtt), with Home Assistant discovery.

Topics, payload keys and the Home Assistant entities are defined in
:mod:`bms_estimator.service.schema`; this module only moves them. The service
hands each :class:`~bms_estimator.service.pipeline.Snapshot` to
:meth:`MqttPublisher.submit_snapshot`.

The estimator never waits for the network: the ``submit_*`` methods only put the newest payload per topic
into a bounded buffer (an older unsent payload of the same topic is replaced
and counted as dropped; when the buffer is full the least recently updated
topic is evicted and counted) and never raise. :meth:`~MqttPublisher.run` is
the publishing task: it connects, publishes, and reconnects with exponential
back-off and jitter while the broker is unreachable, or drops each connection at once
(a second client with this client id: only a connection that lasted ``reconnect_max_s``
resets the back-off).
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import random
import re
import ssl
import threading
import time
from collections import OrderedDict
from collections.abc import Iterable, Mapping
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import aiomqtt
import numpy as np
import structlog

from .. import aio, package_version
from ..errors import ConfigError
from ..jsonsafe import to_jsonable
from . import schema
from .config import MAX_CELLS
from .mqtt_client import MqttClient

if TYPE_CHECKING:
    from .config import MqttConfig, TlsConfig
    from .metrics import ServiceMetrics
    from .pipeline import Snapshot

__all__ = ["MqttCounters", "MqttPublisher", "tls_context"]

log = structlog.get_logger("bms.mqtt")

_PUBLISH_BATCH = 256
#: failed connects in a row logged each (the back-off grows meanwhile); after them one in _LOG_FAILURES_EVERY
_LOG_FAILURES_FIRST = 10
_LOG_FAILURES_EVERY = 100
#: discovery topics subscribed to at once when looking for orphans (:meth:`MqttPublisher.remove_orphans`): well
#: below the messages a broker queues for one client (Mosquitto's max_queued_messages: 1000 by default)
ORPHAN_SCAN_BATCH = 256
#: discovery configs, their removal and the availability are retained and sent QoS 1
_CONTROL_QOS = 1


@dataclass
class MqttCounters:
    published: int = 0  # messages acknowledged by the client library / broker
    dropped: int = 0  # state payloads never sent (superseded or evicted)
    connects: int = 0
    connect_failures: int = 0
    disconnects: int = 0  # connections lost after being established
    submit_errors: int = 0  # bad input to submit_*: logged and ignored


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
        metrics: ServiceMetrics | None = None,
        sw_version: str | None = None,
        expire_after_s: float | None = None,
        sop_horizons_s: Iterable[float] = schema.SOX_HORIZONS_S,
    ) -> None:
        self.cfg = cfg
        self.pack_id = pack_id
        self.n_cells = int(n_cells)
        self.metrics = metrics
        self.sw_version = sw_version or package_version()
        self.counters = MqttCounters()

        self.topics = topics = schema.Topics(cfg.base_topic, pack_id, cfg.discovery_prefix, self.n_cells)
        self.topic_root = topics.root
        self.availability_topic = topics.availability
        self.pack_topic = topics.pack
        self.ha_status_topic = topics.ha_status
        self._cell_topics = topics.cells

        self._buffer = _LatestBuffer(cfg.buffer_max)
        self._wakeup = asyncio.Event()
        self._closing = False
        self._close_offline = True  # close(): publish offline (not for a reload that keeps the topic)
        self._discovery_due = False
        self._ha_online_at = -math.inf  # monotonic time of the last discovery re-send for Home Assistant
        self._ha_online_timer: asyncio.TimerHandle | None = None
        self._connected = False
        self._loop: asyncio.AbstractEventLoop | None = None
        self._loop_thread: int | None = None
        self._run_task: asyncio.Task[None] | None = None
        self._done: asyncio.Event | None = None
        self._tls: ssl.SSLContext | None = None
        self._submit_error_logged = 0
        self.expire_after_s = expire_after_s
        self.sop_horizons_s = tuple(sop_horizons_s)  # the SOP limit entities announced (estimator.sop.horizons_s)
        self._last_t: np.ndarray | None = None  # per cell: frame time, SOC and stale flag last queued
        self._last_soc: np.ndarray | None = None
        self._last_stale: np.ndarray | None = None
        self._pack_last_t: float | None = None
        self._submitted: dict[str, float] = {}  # topic -> when its oldest unsent state was submitted
        self._orphans_checked = False  # once per run: the configuration does not change in between
        self._failed_in_a_row = 0  # connects failed since the last one that succeeded (what is logged)

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
    def submit_snapshot(self, snap: Snapshot, *, final: bool = False) -> None:
        """Queue the cell and pack states of one snapshot, as ``publish_period_s`` and
        ``soc_deadband`` allow (on the frames' time). ``final=True`` (the newest state when the
        service stops): every topic not yet sent at ``snap.t_s``, whatever the period and
        deadband, so that a thinned stream still ends on the estimator's last state.
        Never raises, never blocks."""
        if not self.cfg.enabled or self._closing:
            return
        try:
            send = self._due_cells(snap, final=final)
            items = []
            if send.any():
                due = np.flatnonzero(send)
                texts = schema.snapshot_cell_payload_texts(snap, due)  # one JSON build for all cells
                items = [(self._cell_topics[i], text, False) for i, text in zip(due.tolist(), texts)]
            if self._pack_due(snap.t_s, final=final):
                items.append((self.pack_topic, schema.dumps(schema.pack_payload(snap)), False))
            if items:
                self._put(items)
        except Exception as exc:  # noqa: BLE001 - must never raise into the estimator
            self._submit_failed("submit_snapshot", exc)

    def _pack_due(self, t_s: float, *, final: bool = False) -> bool:
        last = self._pack_last_t
        if final:
            if last == t_s:
                return False
        elif last is not None and t_s >= last and t_s - last < self.cfg.publish_period_s - 1e-9:
            return False
        self._pack_last_t = t_s
        return True

    def _due_cells(self, snap: Snapshot, *, final: bool = False) -> np.ndarray:
        """Cells to publish now: their period is over and (with a deadband) they changed;
        ``final``: every cell not sent at ``snap.t_s`` yet."""
        cfg, n = self.cfg, self.n_cells
        if self._last_t is None:
            self._last_t = np.full(n, -np.inf)
            self._last_soc = np.full(n, np.nan)
            self._last_stale = np.zeros(n, dtype=bool)
        t = snap.t_s
        age = t - self._last_t
        due = (age >= cfg.publish_period_s - 1e-9) | (age < 0)  # time went back: start again
        if final:
            due = self._last_t != t
        elif cfg.soc_deadband > 0:
            soc = np.asarray(snap.cells["soc"], dtype=float)
            stale = ~snap.valid
            with np.errstate(invalid="ignore"):
                moved = ~(np.abs(soc - self._last_soc) < cfg.soc_deadband)  # NaN on either side: moved
            due &= moved | (stale != self._last_stale) | (age >= cfg.max_period_s - 1e-9) | (age < 0)
            self._last_soc = np.where(due, soc, self._last_soc)
            self._last_stale = np.where(due, stale, self._last_stale)
        self._last_t = np.where(due, t, self._last_t)
        return due

    def submit_cells(self, t_s: float, arrays: Mapping[str, Any]) -> None:
        """Queue one state per cell from per-cell arrays (length ``n_cells``
        or scalars), keys as in ``schema.CELL_FIELDS`` plus any extra numeric arrays.
        Never raises, never blocks."""
        if not self.cfg.enabled or self._closing:
            return
        try:
            texts = schema.cell_payload_texts(t_s, arrays, self.n_cells)
            self._put([(self._cell_topics[i], text, False) for i, text in enumerate(texts)])
        except Exception as exc:  # noqa: BLE001 - must never raise into the estimator
            self._submit_failed("submit_cells", exc)

    def submit_pack(self, payload: Mapping[str, Any]) -> None:
        """Queue a pack state (any JSON-able mapping). Never raises, never blocks."""
        if not self.cfg.enabled or self._closing:
            return
        try:
            if not isinstance(payload, Mapping):
                raise TypeError(f"pack payload must be a mapping, not {type(payload).__name__}")
            self._put([(self.pack_topic, schema.dumps(to_jsonable(payload)), False)])
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
        if self.metrics is not None:
            now = time.monotonic()
            for topic, _, _ in items:
                self._submitted.setdefault(topic, now)
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
        if m is not None and name in ("published", "dropped", "connects", "connect_failures"):
            getattr(m, f"mqtt_{name}").inc(n)

    def _set_connected(self, value: bool) -> None:
        self._connected = value
        if self.metrics is not None:
            self.metrics.mqtt_connected.set(int(value))

    # --------------------------------------------------------------- discovery
    def discovery_messages(self) -> list[tuple[str, str]]:
        """Home Assistant discovery (topic, JSON config) pairs (see ``schema.discovery_messages``)."""
        return schema.discovery_messages(self.topics, sw_version=self.sw_version, expire_after_s=self.expire_after_s,
                                         sop_horizons_s=self.sop_horizons_s)

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
                aio.raise_if_cancelling()  # one a library's wait swallowed (:mod:`bms_estimator.aio`)
                started = time.monotonic()
                try:
                    was_connected = await self._session()
                except asyncio.CancelledError:
                    raise
                except Exception as exc:  # noqa: BLE001 - keep going whatever happens
                    if aio.cancelling():
                        raise asyncio.CancelledError from exc
                    log.exception("mqtt session error", error=repr(exc))
                    was_connected = False
                if self._closing:
                    break
                # only a connection that lasted resets the back-off: one the broker drops at once
                # (another client with this client id) backs off as a failed connect does
                stable = was_connected and time.monotonic() - started >= self.cfg.reconnect_max_s
                failures = 0 if stable else failures + 1
                delay = self._backoff(max(failures, 1))
                if self._logs_failure():
                    log.info("mqtt reconnecting", in_s=round(delay, 3), failed_attempts=failures)
                self._wakeup.clear()
                with contextlib.suppress(asyncio.TimeoutError):
                    # Woken early only by close() (submissions are ignored here).
                    await aio.wait_for(self._wait_closing(), timeout=delay)
        finally:
            self._set_connected(False)
            self._done.set()

    async def _wait_closing(self) -> None:
        while not self._closing:
            self._wakeup.clear()
            await self._wakeup.wait()

    def _logs_failure(self) -> bool:
        """Whether this failed connect is logged: each of the first :data:`_LOG_FAILURES_FIRST` in a row, then
        one in :data:`_LOG_FAILURES_EVERY`. A broker down for days (a vehicle out of coverage) is tried every
        ``reconnect_max_s``: a WARNING and an INFO each time, 2880 lines a day at 60 s, pushed the rest of the
        journal out (the CAN bus's silence is said the same way)."""
        n = self._failed_in_a_row
        return n <= _LOG_FAILURES_FIRST or n % _LOG_FAILURES_EVERY == 0

    def _backoff(self, attempt: int) -> float:
        lo, hi = self.cfg.reconnect_min_s, self.cfg.reconnect_max_s
        base = min(hi, lo * (2.0 ** min(attempt - 1, 60)))
        return max(lo, random.uniform(base / 2, base))

    def same_availability(self, other: MqttPublisher) -> bool:
        """Whether ``other`` announces on this publisher's broker and availability topic, so that a
        reload from one to the other can leave ``online`` standing (:meth:`close`'s ``offline``)."""
        return (self.cfg.enabled and other.cfg.enabled and self.availability_topic == other.availability_topic
                and (self.cfg.host, self.cfg.port) == (other.cfg.host, other.cfg.port))

    async def close(self, timeout_s: float = 5.0, *, offline: bool = True) -> None:
        """Publish ``offline``, disconnect, and wait for :meth:`run` to end
        (cancelling it after ``timeout_s``). Further submissions are ignored.

        ``offline=False`` (a reload to a publisher of :meth:`same_availability`) disconnects cleanly
        without it: the retained ``online`` stands, and Home Assistant's entities do not turn
        unavailable for the second the new service takes to connect. A clean disconnect does not
        fire the will; a process that dies before its successor connects still leaves ``online``
        behind, which the entities' ``expire_after`` ends."""
        self._close_offline = offline
        self._closing = True
        self._wake()
        task, done = self._run_task, self._done
        if task is None or task.done() or task is asyncio.current_task() or done is None:
            return
        try:
            await aio.wait_for(done.wait(), timeout=timeout_s)
        except asyncio.TimeoutError:
            log.warning("mqtt publisher did not stop in time; cancelling")
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await aio.wait_for(asyncio.shield(done.wait()), timeout=2.0)

    # ----------------------------------------------------------------- session
    def _tls_context(self) -> ssl.SSLContext | None:
        if self._tls is None:
            self._tls = tls_context(self.cfg.tls)
        return self._tls

    def _make_client(self) -> aiomqtt.Client:
        cfg = self.cfg
        client = MqttClient(
            cfg.host,
            cfg.port,
            username=cfg.username,
            password=cfg.password.get_secret_value() if cfg.password is not None else None,
            identifier=cfg.client_id or f"bms-estimator-{self.pack_id}",
            will=aiomqtt.Will(self.availability_topic, "offline", qos=_CONTROL_QOS, retain=True),
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
            self._failed_in_a_row += 1
            why = "; ".join(exc.problems) if isinstance(exc, ConfigError) else f"{type(exc).__name__}: {exc}"
            if self._logs_failure():
                log.error("mqtt client setup failed", error=why, failures_in_a_row=self._failed_in_a_row)
            return False
        entered = False
        try:
            async with client:
                entered = True
                self._count("connects")
                self._set_connected(True)
                after = {"after_failed_connects": self._failed_in_a_row} if self._failed_in_a_row else {}
                self._failed_in_a_row = 0
                log.info("mqtt connected", host=cfg.host, port=cfg.port, tls=cfg.tls.enabled, **after)
                await self._serve(client)
        except aiomqtt.MqttError as exc:
            if aio.cancelling():
                # e.g. the disconnect in __aexit__ timed out while we were being
                # cancelled: never turn a cancellation into a reconnect.
                raise asyncio.CancelledError from exc
            if not entered:
                self._count("connect_failures")
                self._failed_in_a_row += 1
                if self._logs_failure():
                    log.warning(
                        "mqtt connect failed",
                        host=cfg.host,
                        port=cfg.port,
                        error=str(exc),
                        failures=self.counters.connect_failures,
                        failures_in_a_row=self._failed_in_a_row,
                        **({"next_logged_at": _LOG_FAILURES_EVERY} if self._failed_in_a_row == _LOG_FAILURES_FIRST else {}),
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
            if not self._orphans_checked:
                try:
                    await self.remove_orphans(client)
                except asyncio.TimeoutError:  # e.g. an ACL that hides the probe: go on without
                    log.warning("home assistant: could not scan for orphan entities (no answer in time)")
                self._orphans_checked = True
            if cfg.discovery:
                self._discovery_due = False
                await self._publish_discovery(client)
            listener = asyncio.create_task(self._listen(client))
            while True:
                aio.raise_if_cancelling()  # one aiomqtt's publish swallowed: never block on it again
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
                    if self._close_offline:
                        await self._publish_one(client, self.availability_topic, "offline", True)
                        log.info("mqtt closing: published offline")
                    else:
                        log.info("mqtt closing for a reload: availability left online")
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
                await aio.wait_for(
                    client.publish(self.availability_topic, "offline", qos=_CONTROL_QOS, retain=True),
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

    #: Home Assistant's "online" re-sends discovery at most this often; more are coalesced
    #: into one delayed re-send (a flood of "online" must not flood the broker and the log)
    HA_ONLINE_MIN_INTERVAL_S = 10.0

    async def _listen(self, client: aiomqtt.Client) -> None:
        async for message in client.messages:
            if message.topic.matches(self.ha_status_topic):
                if _text(message.payload).strip().lower() == "online":
                    self._ha_online()

    def _ha_online(self) -> None:
        now = time.monotonic()
        wait = self._ha_online_at + self.HA_ONLINE_MIN_INTERVAL_S - now
        if wait <= 0:
            log.info("home assistant online: re-sending discovery")
            self._ha_online_at = now
            self._discovery_due = True
            self._wakeup.set()
        elif self._ha_online_timer is None:
            log.debug("home assistant online again: discovery re-sent later", in_s=round(wait, 1))
            self._ha_online_timer = asyncio.get_running_loop().call_later(wait, self._ha_online_later)

    def _ha_online_later(self) -> None:
        self._ha_online_timer = None
        self._ha_online()

    async def _publish_one(self, client: aiomqtt.Client, topic: str, payload: str, retain: bool) -> None:
        await client.publish(topic, payload, qos=_CONTROL_QOS, retain=retain, timeout=self.cfg.timeout_s)
        self._count("published")

    async def _publish_discovery(self, client: aiomqtt.Client) -> None:
        msgs = [(t, p, True) for t, p in self.discovery_messages()]
        failed = await self._publish_batch(client, msgs, qos=_CONTROL_QOS)
        if failed:
            self._discovery_due = True  # try again on the next connection
            raise failed[0][1]
        log.info("home assistant discovery published", sensors=len(msgs))

    def _is_ours(self, topic: str) -> bool:
        """A discovery config topic of this pack (``<prefix>/<component>/bms_<pack>_{pack|cell<i>}_<uid>/config``
        with a ``<uid>`` of the schema's: ``bms_rack_pack_pack_soc_min`` is pack "rack_pack"'s, not "rack"'s)."""
        parts = topic.split("/")
        if len(parts) < 4 or parts[-1] != "config":
            return False
        rest = parts[-2]
        prefix = self.topics.unique_id_prefix
        if not rest.startswith(prefix):
            return False
        m = re.fullmatch(r"(pack|cell\d+)_(.+)", rest[len(prefix):])
        return m is not None and m[2] in (schema.PACK_ENTITY_UIDS if m[1] == "pack" else schema.CELL_ENTITY_UIDS)

    async def remove_orphans(self, client: aiomqtt.Client) -> int:
        """Remove this pack's retained discovery configs that the current configuration does not
        publish (a pack that had more cells, or discovery turned off): subscribe to the discovery
        topics this pack may have used (:meth:`~bms_estimator.service.schema.Topics.discovery_filters`),
        at most :data:`ORPHAN_SCAN_BATCH` at a time, collect the retained configs of each batch up to a
        probe message of our own, and clear the orphans with an empty retained message. Returns their
        number.

        Scanned: the unique ids of the pack and of its ``n_cells`` cells that this configuration does not
        announce (all of them with discovery off), then the cells beyond, a batch of cells at a time up to
        the first batch that has none (a pack's cells were always ``0 .. n - 1``: the orphans of one that
        had more are the cells from ``n_cells`` on), at most ``pack.n_cells``' limit.

        A batch at a time: a broker queues at most so many messages for a client (Mosquitto's
        ``max_queued_messages``, 1000 by default) and drops the rest. One subscription to every
        discovery config on the broker (``<prefix>/+/+/config``) had the configs beyond it dropped, the
        probe with them: a pack of more than about 90 cells, or any pack on a broker holding more than
        1000 configs, timed out and never removed its orphans."""
        cfg = self.cfg
        topics = self.topics
        keep = {t for t, _ in self.discovery_messages()} if cfg.discovery else set()
        announced = {t.split("/")[-2] for t in keep}
        own = [f for f in topics.discovery_filters(range(self.n_cells), pack=True) if f.split("/")[-2] not in announced]
        per_batch = max(1, ORPHAN_SCAN_BATCH // len(schema.CELL_ENTITY_UIDS))  # cells
        await client.subscribe(topics.probe, qos=_CONTROL_QOS)
        found: set[str] = set()
        try:
            for start in range(0, len(own), ORPHAN_SCAN_BATCH):
                found |= await self._scan_batch(client, own[start : start + ORPHAN_SCAN_BATCH])
            for first in range(self.n_cells, MAX_CELLS, per_batch):
                batch = topics.discovery_filters(range(first, min(first + per_batch, MAX_CELLS)))
                more = await self._scan_batch(client, batch)
                if not more:
                    break
                found |= more
        finally:
            await client.unsubscribe(topics.probe)
        orphans = sorted(found - keep)
        if orphans:
            failed = await self._publish_batch(client, [(t, "", True) for t in orphans], qos=_CONTROL_QOS)
            if failed:
                raise failed[0][1]
            log.info("home assistant: removed entities this configuration no longer has", removed=len(orphans))
        return len(orphans)

    async def _scan_batch(self, client: aiomqtt.Client, filters: list[str]) -> set[str]:
        """This pack's retained discovery configs under ``filters`` (subscribed to for as long as it takes)."""
        await client.subscribe([(f, _CONTROL_QOS) for f in filters])
        try:
            return await self._retained_until_probe(client, self.topics.probe)
        finally:
            await client.unsubscribe(filters)

    async def _retained_until_probe(self, client: aiomqtt.Client, probe: str) -> set[str]:
        """This pack's retained discovery configs that arrive before a probe message published now (the
        broker sends a subscription's retained messages before it handles the publish after it)."""
        cfg = self.cfg
        token = f"{random.getrandbits(64):016x}"
        found: set[str] = set()
        await client.publish(probe, token, qos=_CONTROL_QOS, retain=False, timeout=cfg.timeout_s)
        async with asyncio.timeout(cfg.timeout_s):
            async for message in client.messages:
                topic = message.topic.value
                if topic == probe and _text(message.payload) == token:
                    break
                if topic == self.ha_status_topic and _text(message.payload).strip().lower() == "online":
                    self._discovery_due = True
                elif message.retain and message.payload and self._is_ours(topic):
                    found.add(topic)
        return found

    async def _publish_items(self, client: aiomqtt.Client, items: list[tuple[str, str, bool]]) -> None:
        failed = await self._publish_batch(client, items)
        m = self.metrics
        if m is not None:
            now, lost = time.monotonic(), {t for (t, _, _), _ in failed}
            for topic, _, _ in items:
                since = self._submitted.pop(topic, None) if topic not in lost else None
                if since is not None:
                    m.mqtt_publish_latency.observe(now - since)
        if failed:
            unsent = [item for item, _ in failed]
            dropped = self._buffer.restore(unsent)
            if dropped:
                self._count("dropped", dropped)
            raise failed[0][1]

    async def _publish_batch(
        self, client: aiomqtt.Client, items: list[tuple[str, str, bool]], qos: int | None = None
    ) -> list[tuple[tuple[str, str, bool], aiomqtt.MqttError]]:
        """Publish concurrently (QoS>0 waits for acks); return the failures."""
        failed: list[tuple[tuple[str, str, bool], aiomqtt.MqttError]] = []
        qos = self.cfg.qos if qos is None else qos
        timeout = self.cfg.timeout_s
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


def tls_context(t: TlsConfig) -> ssl.SSLContext | None:
    """The client's SSL context for ``mqtt.tls`` (None when off). A file it names that cannot be used
    (missing, unreadable, not PEM, a key that is not the certificate's) raises :class:`ConfigError`
    naming the key and the path: ssl's own errors name neither (``[Errno 2] No such file or directory``)."""
    if not t.enabled:
        return None
    files = {"ca_file": t.ca_file, "cert_file": t.cert_file, "key_file": t.key_file}
    problems = [p for key, path in files.items() if path is not None and (p := _tls_file_problem(key, path))]
    if problems:
        raise ConfigError("invalid configuration:", problems)
    try:
        ctx = ssl.create_default_context(ssl.Purpose.SERVER_AUTH, cafile=str(t.ca_file) if t.ca_file else None)
    except ssl.SSLError as exc:
        raise ConfigError("invalid configuration:", [f"mqtt.tls.ca_file: {t.ca_file}: not a PEM CA certificate "
                                                     f"({exc.reason or exc})"]) from None
    if t.cert_file is not None:
        key_path = t.key_file if t.key_file is not None else t.cert_file
        try:
            # no passphrase: OpenSSL would otherwise ask for one on the terminal, at every (re)connect
            ctx.load_cert_chain(str(t.cert_file), str(t.key_file) if t.key_file else None, password=_no_passphrase)
        except ssl.SSLError as exc:
            if _encrypted_pem(key_path):
                key = "key_file" if t.key_file is not None else "cert_file"
                raise ConfigError("invalid configuration:", [
                    f"mqtt.tls.{key}: {key_path}: the private key is encrypted and a service has no one to type "
                    f"its passphrase: store it unencrypted (openssl pkey -in KEY -out KEY.plain), readable by the "
                    f"service's user only"]) from None
            what = f"{t.cert_file}" + (f", mqtt.tls.key_file: {t.key_file}" if t.key_file else "")
            raise ConfigError("invalid configuration:", [f"mqtt.tls.cert_file: {what}: not a PEM certificate and its "
                                                         f"key ({exc.reason or exc})"]) from None
    if t.insecure:
        ctx.check_hostname = False
        ctx.verify_mode = ssl.CERT_NONE
    return ctx


def _no_passphrase() -> bytes:
    """The passphrase of an encrypted key: none (a daemon cannot prompt; the load then fails)."""
    return b""


def _encrypted_pem(path: Path) -> bool:
    """Whether a PEM file holds an encrypted private key (PKCS#8 or the legacy Proc-Type header)."""
    try:
        text = Path(path).read_bytes()
    except OSError:
        return False
    return b"ENCRYPTED PRIVATE KEY" in text or b"Proc-Type: 4,ENCRYPTED" in text


def _tls_file_problem(key: str, path: Path) -> str | None:
    """``mqtt.tls.<key>: <path>: <why>`` when the file cannot be read, else None."""
    try:
        with open(path, "rb"):
            return None
    except OSError as exc:
        return f"mqtt.tls.{key}: {path}: {(exc.strerror or str(exc)).lower()}"


def _text(payload: Any) -> str:
    if isinstance(payload, (bytes, bytearray)):
        return bytes(payload).decode("utf-8", "replace")
    return "" if payload is None else str(payload)
