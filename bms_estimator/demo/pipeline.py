"""The demo's pipeline: shipped drive cycle -> pack CAN traffic -> the real service -> MQTT.

1. :func:`prepare_pack` (:mod:`bms_estimator.replay.encode_log`, in memory): the measured
   cell is identified on the whole recording, a pack of ``n_cells`` is drawn with the seeded
   spread (cell 0 = the measured voltage, the others simulated + the measured residual),
   and the pack is encoded as the frames of the project DBC at the DBC's rates (10 ms
   current, 100 ms cell voltages, 1 s temperatures). The reference capacity of the pack
   (``Q_ref``, the simulated cells' capacities are ``Q_ref`` times their factor) is the one
   ``bms-estimator soc`` uses for the measured file: measured from its end-of-test rest when
   it ends at a relaxed rest, else the stated one.
2. :func:`run_pipeline` starts the real :class:`~bms_estimator.service.daemon.Service`, with an
   ``on_snapshot`` hook (:func:`record_service`) that keeps every sample's estimate for the
   summary (the data path is the service's own, see :mod:`bms_estimator.service.pipeline`),
   and hands it the frames in process with :meth:`Service.feed
   <bms_estimator.service.daemon.Service.feed>`: each frame takes the path a received frame
   takes after the bus (decoder, sampler, estimator, MQTT), without a python-can bus object,
   its reader thread and queue in between (they cost more than the estimator; the replay over
   a bus is ``bms-estimator replay``). The frames carry the log's own timestamps. At
   ``speed="max"`` they go in slices of :data:`FEED_SLICE`; a finite speed paces slices of
   20 ms of wall time by their timestamps. One extra current frame at the log's end closes the
   last 1 s sample. The service publishes each MQTT topic at most every
   :data:`MQTT_PUBLISH_PERIOD_S` of log time (``mqtt.publish_period_s``) and every final
   state at the stop; CAN output and the health server are off (nothing would read them here).
3. An MQTT subscriber (aiomqtt) on the same broker feeds a
   :class:`~bms_estimator.replay.dashboard.DashboardState` (the live view) and keeps the
   newest payload of every topic; without a broker the view is fed from the service's state
   directly. The run ends when the service has decoded every frame; the service then stops
   as it would under systemd (final state published, ``offline``), and the subscriber waits
   until every cell's last state has arrived.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import math
import os
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import can
import numpy as np

from .. import aio
from ..analysis import PARAM_KEYS, reference_capacity
from ..core.ocv import OcvCurve
from ..data import load_recording
from ..ocv_table import read_ocv_table
from ..replay.encode_log import CellSpread, FrameArrays, PackTrace, build_pack, frame_arrays, truth_dict
from ..samples import CELLS, drive_cycle, ocv_table

__all__ = [
    "DEFAULT_CYCLE",
    "FEED_SLICE",
    "Frame",
    "MQTT_PUBLISH_PERIOD_S",
    "MqttWatcher",
    "PackSetup",
    "Record",
    "record_service",
    "RunResult",
    "prepare_pack",
    "run_pipeline",
]

#: default drive cycle per shipped cell: one that is not the cell's training file in the paper table
DEFAULT_CYCLE = {"lg-hg2": "la92", "panasonic-18650pf": "cycle_2"}
#: frames handed to the service per slice at ``speed="max"`` (the live view ticks in between)
FEED_SLICE = 4096
#: ``mqtt.publish_period_s`` of the demo's service: each topic at most once per 30 s of log time
#: (the final states at the stop regardless); the figure and summary read every sample
MQTT_PUBLISH_PERIOD_S = 30.0
PACK_ID = "demo"


# ------------------------------------------------------------------- the pack
@dataclass
class PackSetup:
    cell: str
    cycle: str
    n_cells: int
    seed: int
    capacity_stated_ah: float
    ocv_path: str
    ocv: OcvCurve
    trace: PackTrace
    frames: FrameArrays
    truth: dict[str, Any]
    prepare_s: float

    @property
    def duration_s(self) -> float:
        return self.trace.duration_s

    @property
    def n_samples(self) -> int:
        return int(self.trace.current_a.size)


def prepare_pack(cell: str = "lg-hg2", cycle: str | None = None, n_cells: int = 16, *, seed: int = 0,
                 duration_s: float | None = None, spread: CellSpread | None = None) -> PackSetup:
    """Encode a shipped drive cycle as the CAN traffic of an ``n_cells`` pack (module docstring, 1)."""
    if cell not in CELLS:
        raise ValueError(f"unknown cell {cell!r}; shipped: {', '.join(sorted(CELLS))}")
    q_stated, cycles = CELLS[cell]
    cycle = cycle or DEFAULT_CYCLE.get(cell, cycles[-1])
    if cycle not in cycles:
        raise ValueError(f"no shipped {cell} cycle {cycle!r}; shipped: {', '.join(cycles)}")
    t0 = time.perf_counter()
    rec = load_recording(drive_cycle(cell, cycle))
    ocv_path = ocv_table(cell)
    ocv = read_ocv_table(ocv_path)
    # the reference capacity exactly as `bms-estimator soc` takes it for this file (from full)
    q_ref, source = reference_capacity(rec.current_a, rec.voltage_v, rec.dt_s, ocv, q_stated, 1.0)
    trace = build_pack(rec, n_cells, ocv, q_stated, seed=seed, spread=spread or CellSpread(),
                       initial_soc=1.0, reference_capacity_ah=q_ref, duration_s=duration_s,
                       ocv_source=str(ocv_path))
    fa = frame_arrays(trace)
    truth = truth_dict(trace, fa, out="(in memory: bms-estimator demo)")
    truth["reference"]["capacity_source"] = f"{source} (as bms-estimator soc, on the whole file)"
    truth["cycle"] = {"cell": cell, "cycle": cycle}
    return PackSetup(cell, cycle, n_cells, seed, float(q_stated), str(ocv_path), ocv, trace, fa, truth,
                     time.perf_counter() - t0)


def closing_frame(fa: FrameArrays, period_s: float) -> can.Message:
    """A repeat of the last current frame at the log's end, with the next alive counter value and
    its CRC (as the sender's next frame): it completes the last sample period."""
    from ..can.dbc import load_project_db
    from ..can.e2e import E2EStamper

    db = load_project_db()
    cur_id = int(db.get_message_by_name("PackMeasurement").frame_id)
    last = int(np.flatnonzero(fa.arbitration_id == cur_id)[-1])
    p_us = int(round(period_s * 1e6))
    t_end_us = (int(fa.t_us[-1]) // p_us + 1) * p_us
    data = E2EStamper(db, "default").next_after(cur_id, np.asarray([fa.data[last]], dtype="<u8").tobytes())
    return can.Message(timestamp=fa.t0_s + t_end_us / 1e6, arbitration_id=cur_id,
                       is_extended_id=fa.extended.get(cur_id, True), dlc=8, data=data, check=False)


# ----------------------------------------------------------------- recording
@dataclass
class Record:
    """Every sample the service estimated (rows in arrival order)."""

    n_cells: int
    capacity: int = 16384
    rows: int = 0
    t_s: np.ndarray = field(init=False)
    current_a: np.ndarray = field(init=False)
    voltage_v: np.ndarray = field(init=False)
    v_o: np.ndarray = field(init=False)
    soc: np.ndarray = field(init=False)
    capacity_ah: np.ndarray = field(init=False)
    params: dict[str, np.ndarray] = field(init=False)
    pack_sox: dict[str, float] = field(default_factory=dict)  # the last sample's pack SOP/SOE/SOH

    def __post_init__(self) -> None:
        n, c = self.n_cells, self.capacity
        self.t_s = np.full(c, np.nan)
        self.current_a = np.full(c, np.nan)
        self.voltage_v = np.full((c, n), np.nan)
        self.v_o = np.full((c, n), np.nan)
        self.soc = np.full((c, n), np.nan)
        self.capacity_ah = np.full((c, n), np.nan)
        self.params = {k: np.full((c, n), np.nan) for k in PARAM_KEYS}

    def _grow(self) -> None:
        c = self.capacity
        for name in ("t_s", "current_a", "voltage_v", "v_o", "soc", "capacity_ah"):
            a = getattr(self, name)
            b = np.full((2 * c, *a.shape[1:]), np.nan)
            b[:c] = a
            setattr(self, name, b)
        for k, a in self.params.items():
            b = np.full((2 * c, *a.shape[1:]), np.nan)
            b[:c] = a
            self.params[k] = b
        self.capacity = 2 * c

    def add(self, t_s: float, current_a: float, voltage_v: np.ndarray, est: Any) -> None:
        if self.rows >= self.capacity:
            self._grow()
        k = self.rows
        self.t_s[k] = t_s
        self.current_a[k] = current_a
        self.voltage_v[k] = voltage_v
        self.v_o[k] = est.v_o
        self.soc[k] = est.soc
        self.capacity_ah[k] = est.capacity_ah
        p = est.params
        for key in PARAM_KEYS:
            self.params[key][k] = p[key]
        self.rows = k + 1

    def trimmed(self) -> "Record":
        """A copy with exactly ``rows`` rows."""
        out = Record(self.n_cells, max(1, self.rows))
        n = self.rows
        for name in ("t_s", "current_a", "voltage_v", "v_o", "soc", "capacity_ah"):
            setattr(out, name, getattr(self, name)[:n].copy())
        out.params = {k: v[:n].copy() for k, v in self.params.items()}
        out.pack_sox = dict(self.pack_sox)
        out.rows = n
        return out


def record_service(svc: Any, expected_samples: int = 16384) -> Record:
    """Attach a :class:`Record` of every sample ``svc`` estimates (an ``on_snapshot`` hook)."""
    record = Record(svc.n_cells, max(16, int(expected_samples) + 8))

    def hook(snap: Any) -> None:
        if snap.current_valid and math.isfinite(snap.current_a):
            record.add(snap.t_s, snap.current_a, snap.sample.cell_voltage_v, svc.estimator)
            record.pack_sox = dict(getattr(snap, "pack_sox", {}))

    svc.pipeline.add_hook(hook)
    return record


# ---------------------------------------------------------------------- MQTT
class MqttWatcher:
    """Subscriber to the service's topics, in a thread with its own event loop (so that it keeps
    up with a service running flat out): feeds a dashboard state (under :attr:`lock`) and keeps
    the newest payload of every topic."""

    def __init__(self, state: Any, host: str, port: int, lock: threading.Lock | None = None) -> None:
        self.state = state
        self.host, self.port = host, port
        self.lock = lock if lock is not None else threading.Lock()
        self.latest: dict[str, str] = {}
        self.messages = 0
        self.error: str | None = None
        self._subscribed = threading.Event()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._task: asyncio.Task[None] | None = None
        self._thread: threading.Thread | None = None

    def cell_payloads(self, pack_id: str, n_cells: int, base: str = "bms") -> list[dict[str, Any] | None]:
        with self.lock:
            texts = [self.latest.get(f"{base}/{pack_id}/cell/{i}/state") for i in range(n_cells)]
        return [json.loads(t) if t is not None else None for t in texts]

    def start(self, timeout: float = 15.0) -> bool:
        """Connect and subscribe; True when subscribed (else :attr:`error` says why)."""
        self._thread = threading.Thread(target=self._main, name="bms-demo-mqtt-view", daemon=True)
        self._thread.start()
        if not self._subscribed.wait(timeout) and self.error is None:
            self.error = f"no subscription within {timeout:g} s"
        return self.error is None

    def stop(self, timeout: float = 5.0) -> None:
        loop, task = self._loop, self._task
        if loop is not None and task is not None and not loop.is_closed():
            with contextlib.suppress(RuntimeError):
                loop.call_soon_threadsafe(task.cancel)
        if self._thread is not None:
            self._thread.join(timeout)

    def _main(self) -> None:
        loop = self._loop = asyncio.new_event_loop()
        try:
            self._task = loop.create_task(self._run())
            with contextlib.suppress(asyncio.CancelledError):
                loop.run_until_complete(self._task)
        finally:
            loop.close()
            self._subscribed.set()

    async def _run(self) -> None:
        import aiomqtt

        with self.lock:
            self.state.broker = f"{self.host}:{self.port}"
        try:
            async with aiomqtt.Client(self.host, self.port, identifier=f"bms-demo-view-{os.getpid()}",
                                      timeout=10) as client:
                for topic in self.state.subscriptions():
                    await client.subscribe(topic, qos=1)
                with self.lock:
                    self.state.connected, self.state.status = True, "connected"
                self._subscribed.set()
                clock = time.monotonic
                async for message in client.messages:
                    topic = message.topic.value
                    payload = message.payload
                    text = (bytes(payload).decode("utf-8", "replace") if isinstance(payload, (bytes, bytearray))
                            else str(payload))
                    with self.lock:
                        self.messages += 1
                        self.latest[topic] = text
                        self.state.apply(topic, text, clock())
        except aiomqtt.MqttError as exc:
            self.error = str(exc) or type(exc).__name__
            with self.lock:
                self.state.status = f"subscriber: {self.error}"
        finally:
            with self.lock:
                self.state.connected = False


def feed_state_directly(state: Any, svc: Any, now: float) -> None:
    """Without a broker: hand the dashboard the payloads the service would have published."""
    from ..service import schema

    snap = svc.pipeline.last
    if snap is None:
        return
    topics = svc.publisher.topics
    for topic, payload in zip(topics.cells, schema.snapshot_cell_payloads(snap)):
        state.apply(topic, schema.dumps(payload), now)
    state.apply(topics.pack, schema.dumps(schema.pack_payload(snap)), now)
    state.apply(topics.availability, "online", now)


# ----------------------------------------------------------------------- run
@dataclass
class Progress:
    """What the live view shows (read from the event loop)."""

    log_total_s: float
    speed: float
    frames_sent: int = 0
    t_start: float = field(default_factory=time.perf_counter)

    def elapsed(self) -> float:
        return time.perf_counter() - self.t_start


@dataclass
class ViewData:
    """Handed to the live view: the service, the dashboard state (read it under ``lock``), progress."""

    svc: Any
    state: Any
    progress: Progress
    lock: threading.Lock


@dataclass
class RunResult:
    record: Record
    samples: int
    frames_sent: int
    frames_decoded: int
    decode_errors: int
    rx_dropped: int
    wall_s: float  # replay start to the last frame decoded
    speed: float
    mqtt_messages: int
    mqtt_published: int
    mqtt_final: list[dict[str, Any] | None]  # newest cell payloads received over MQTT (None = none)
    mqtt_error: str | None
    final_state: dict[str, np.ndarray]
    notes: list[str]

    @property
    def effective_speed(self) -> float:
        return (self.samples / self.wall_s) if self.wall_s > 0 else math.inf


def service_config(setup: PackSetup, channel: str, state_path: Path, broker: Any) -> Any:
    """The service's configuration for the demo. ``BMS_*`` environment variables (the service's
    overrides) are ignored: the demo is self-contained, whatever the shell has set."""
    from ..service.config import ServiceConfig

    class DemoConfig(ServiceConfig):
        @classmethod
        def settings_customise_sources(cls, settings_cls, init_settings, env_settings, dotenv_settings,
                                       file_secret_settings):  # type: ignore[override]
            return (init_settings,)

    mqtt: dict[str, Any] = {"enabled": False}
    if broker is not None and broker.enabled:
        mqtt = {"enabled": True, "host": broker.host, "port": broker.port,
                "client_id": f"bms-demo-{os.getpid()}", "timeout_s": 10.0,
                "publish_period_s": MQTT_PUBLISH_PERIOD_S}
    return DemoConfig(
        pack={"pack_id": PACK_ID, "n_cells": setup.n_cells, "capacity_ah": setup.capacity_stated_ah,
              "ocv_csv": setup.ocv_path},
        # the frames come from Service.feed, not from this (idle) bus: no reopening for its silence
        can={"interface": "virtual", "channel": channel, "output": {"enabled": False},
             "bus": {"silence_reopen_s": None}},
        mqtt=mqtt,
        health={"enabled": False},
        state={"path": str(state_path), "save_interval_s": 3600.0},
        logging={"level": "WARNING"},
    )


class Frame:
    """A received frame as the service's decoder reads it (the attributes of a ``can.Message``
    it uses), made about 10x faster than a ``can.Message``."""

    __slots__ = ("timestamp", "arbitration_id", "is_extended_id", "data")
    is_error_frame = False
    is_remote_frame = False

    def __init__(self, timestamp: float, arbitration_id: int, is_extended_id: bool, data: bytes) -> None:
        self.timestamp = timestamp
        self.arbitration_id = arbitration_id
        self.is_extended_id = is_extended_id
        self.data = data


def iter_frames(fa: FrameArrays, start: int, stop: int) -> Iterator[Frame]:
    """Frames ``start:stop`` of ``fa`` as :class:`Frame` objects (timestamps as
    :meth:`FrameArrays.iter_messages` makes them)."""
    ts = ((int(round(fa.t0_s * 1e6)) + fa.t_us[start:stop]) / 1e6).tolist()
    ids = fa.arbitration_id[start:stop].tolist()
    blob = fa.data[start:stop].astype("<u8").tobytes()
    ext = fa.extended
    for k, (t, i) in enumerate(zip(ts, ids)):
        yield Frame(t, i, ext.get(i, True), blob[8 * k : 8 * k + 8])


def feed_slices(fa: FrameArrays, speed: float, wall_step_s: float = 0.02) -> list[tuple[int, int, float]]:
    """``(start, stop, due_s)`` slices of the frames: at ``speed`` max slices of
    :data:`FEED_SLICE` frames, all due at once; at a finite speed, ``wall_step_s`` of wall time
    each, due ``(t - t_first) / speed`` after the start."""
    n = len(fa)
    if n == 0:
        return []
    if math.isinf(speed):
        return [(a, min(n, a + FEED_SLICE), 0.0) for a in range(0, n, FEED_SLICE)]
    step_us = max(1, int(round(speed * wall_step_s * 1e6)))
    rel = fa.t_us - fa.t_us[0]
    step = rel // step_us  # the wall step each frame falls in (frames are in time order)
    bounds = np.concatenate([[0], np.flatnonzero(np.diff(step)) + 1, [n]])
    return [(int(a), int(b), float(rel[a]) / 1e6 / speed) for a, b in zip(bounds[:-1], bounds[1:])]


async def run_pipeline(setup: PackSetup, *, broker: Any = None, speed: float = math.inf,
                       on_tick: Callable[[ViewData], None] | None = None,
                       tick_s: float = 0.25, dashboard: Any = None) -> RunResult:
    """Run the service over the pack's frames (module docstring, 2-3).

    ``broker``: a :class:`~bms_estimator.demo.broker.BrokerInfo` (None or disabled = no MQTT).
    ``on_tick(ViewData)`` is called every ``tick_s`` of wall time from the event loop (the live
    view). ``dashboard``: the state to feed (a new one by default).
    """
    from ..replay.dashboard import DashboardState

    state = dashboard if dashboard is not None else DashboardState(PACK_ID)
    lock = threading.Lock()
    mqtt_on = broker is not None and broker.enabled
    channel = f"bms-demo-{os.getpid()}-{time.monotonic_ns()}"
    total = len(setup.frames) + 1
    progress = Progress(setup.duration_s, speed)
    notes: list[str] = []
    with tempfile.TemporaryDirectory(prefix="bms-demo-") as tmp:
        cfg = service_config(setup, channel, Path(tmp) / "state.npz", broker)
        from ..service.daemon import Service

        svc = Service(cfg)
        record = record_service(svc, setup.n_samples)
        watcher = MqttWatcher(state, broker.host, broker.port, lock) if mqtt_on else None
        if watcher is not None:
            # subscribe before the service starts, so that the view sees everything it publishes
            if not await asyncio.to_thread(watcher.start):
                notes.append(f"MQTT subscriber could not connect ({watcher.error}): view fed from the service")
        else:
            state.status = "MQTT off: fed from the service directly"
        stop = asyncio.Event()
        svc_task = asyncio.create_task(svc.run(stop), name="bms-demo-service")
        await aio.wait_for(svc.ready.wait(), 15)

        fa = setup.frames

        async def feed() -> None:
            t_start = progress.t_start
            for a, b, due in feed_slices(fa, speed):
                wait = due - (time.perf_counter() - t_start)
                if wait > 0:
                    await asyncio.sleep(wait)
                await svc.feed(iter_frames(fa, a, b))
                progress.frames_sent = b
            await svc.feed([closing_frame(fa, svc.period_s)])
            progress.frames_sent = total

        progress.t_start = time.perf_counter()
        feeder = asyncio.create_task(feed(), name="bms-demo-feed")
        wall = math.nan
        direct = watcher is None or watcher.error is not None
        try:
            next_tick = 0.0
            while not feeder.done():
                now = time.perf_counter()
                if on_tick is not None and now >= next_tick:
                    next_tick = now + tick_s
                    with lock:
                        if direct:
                            feed_state_directly(state, svc, time.monotonic())
                        state.tick(time.monotonic())
                    on_tick(ViewData(svc, state, progress, lock))
                await asyncio.wait({feeder}, timeout=0.02)
            feeder.result()  # an exception in the feed is the run's
            wall = time.perf_counter() - progress.t_start
        finally:
            if not feeder.done():
                feeder.cancel()
                with contextlib.suppress(BaseException):
                    await feeder
            stop.set()
            with contextlib.suppress(Exception):
                await aio.wait_for(svc_task, 30)
        final_t = record.t_s[record.rows - 1] if record.rows else math.nan
        if watcher is not None:
            # the service published its final states on shutdown: wait until they are all here
            deadline = time.monotonic() + 15
            while time.monotonic() < deadline and watcher.error is None:
                finals = watcher.cell_payloads(PACK_ID, setup.n_cells)
                if all(p is not None and p.get("t_s") == final_t for p in finals):
                    break
                await asyncio.sleep(0.05)
            else:
                notes.append("not every cell's final state arrived over MQTT")
            await asyncio.to_thread(watcher.stop)
        with lock:
            if direct:
                feed_state_directly(state, svc, time.monotonic())
            state.tick(time.monotonic())
        if on_tick is not None:
            on_tick(ViewData(svc, state, progress, lock))
    dec = svc.decoder.counters
    if dec.frames < total:
        notes.append(f"the service decoded {dec.frames} of {total} frames")
    rec = record.trimmed()
    return RunResult(
        record=rec, samples=rec.rows, frames_sent=progress.frames_sent,
        frames_decoded=dec.frames, decode_errors=dec.errors, rx_dropped=0,
        wall_s=wall, speed=speed, mqtt_messages=watcher.messages if watcher else 0,
        mqtt_published=svc.publisher.counters.published,
        mqtt_final=watcher.cell_payloads(PACK_ID, setup.n_cells) if watcher else [None] * setup.n_cells,
        mqtt_error=watcher.error if watcher else None,
        final_state={k: np.array(v, copy=True) for k, v in svc.estimator.state_dict().items()},
        notes=notes,
    )
