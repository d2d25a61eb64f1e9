"""How much faster than real time a replayed pack goes through the estimator.

:func:`bench_replay_speedup` encodes a measured drive cycle (default: the shipped
LG HG2 UDDS sample, 4.4 h, cut to ``hours``) as the CAN traffic of an
``n_cells`` pack (:mod:`bms_estimator.replay.encode_log`: 10 ms current, 3 cells
per 100 ms voltage frame, 6 per 1 s temperature frame - 436 frames per second
for 96 cells), then replays it at ``max`` speed over an in-process python-can
``virtual`` bus and times, from the first frame sent to the last sample
estimated:

``via="daemon"`` (default when ``bms_estimator/service/daemon.py`` exists)
    the real service: ``Service.run`` (ResilientBus -> FrameDecoder ->
    SampleAssembler -> SocEstimator, its metrics and state saving; MQTT,
    health server and CAN output switched off, so only the input path and the
    estimator are measured). The replay thread is flow-controlled on the
    service's public receive counter (``ResilientBus.counters.rx_frames``) so
    that the service's bounded receive queue never overflows; every frame is
    checked to have been decoded.
``via="direct"``
    the same pipeline without the service: a receiving ``VirtualBus``
    (bounded queue = flow control) read in the main thread, ``FrameDecoder``
    + ``SampleAssembler`` + ``SocEstimator.update``.
``via="inline"``
    no bus and no second thread: ``replay_messages`` hands every frame to a
    sink whose ``send`` decodes, assembles and estimates at once (what an
    in-process demo can do with ``Service.pipeline.process_frame``; the results are the
    same because everything runs on frame time). The upper bound of this
    pipeline in CPython.

Both run the replayer (:func:`~bms_estimator.replay.replay.replay_messages`) in a
second thread that also makes the ``can.Message`` objects from the encoded arrays
(as a log reader would, minus file parsing). Preparation (identification,
simulation, encoding) is not timed. The figure is ``log seconds / wall seconds``.
Nothing here is asserted by the tests (speed depends on the machine).

Run: ``python -m benchmarks.replay_speedup [--hours H] [--cells N] [--via daemon|direct|inline|all]``.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import os
import tempfile
import threading
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import can
import numpy as np

from bms_estimator.core.ocv import OcvCurve
from bms_estimator.data import CellRecording, load_recording
from bms_estimator.ocv_table import read_ocv_table
from bms_estimator.samples import CELLS, drive_cycle, ocv_table
from bms_estimator.replay.encode_log import FrameArrays, build_pack, frame_arrays
from bms_estimator.replay.replay import open_replay_bus, replay_messages

__all__ = ["ReplayBenchResult", "bench_replay_speedup", "prepare_frames"]


@dataclass
class ReplayBenchResult:
    speedup: float  # log seconds per wall second
    via: str  # "daemon" or "direct"
    hours: float
    n_cells: int
    frames: int
    frames_per_s: float
    samples: int
    wall_s: float
    log_s: float
    prepare_s: float
    estimator_s: float | None = None  # direct path: CPU time inside SocEstimator.update
    notes: list[str] = field(default_factory=list)

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


def _tile(rec: CellRecording, n: int) -> CellRecording:
    """``rec`` repeated until it has ``n`` samples (a bench longer than the recording)."""
    if n <= len(rec):
        return rec
    reps = -(-n // len(rec))
    dt = rec.dt_s

    def rep(a):
        return None if a is None else np.tile(np.asarray(a), reps)[:n]

    return CellRecording(np.arange(n) * dt, rep(rec.current_a), rep(rec.voltage_v), rep(rec.temperature_c),
                         rec.source + f" (repeated x{reps})")


def prepare_frames(hours: float, n_cells: int, *, cell: str = "lg-hg2", cycle: str = "udds",
                   seed: int = 0) -> tuple[FrameArrays, OcvCurve, float, str]:
    """Encode ``hours`` of a shipped drive cycle for ``n_cells`` (the bench's input, untimed)."""
    rec = load_recording(drive_cycle(cell, cycle))
    n = int(round(hours * 3600 / rec.dt_s))
    rec = _tile(rec, n)
    q = CELLS[cell][0]
    ocv_path = ocv_table(cell)
    ocv = read_ocv_table(ocv_path)
    # the reference capacity is given (the stated one), so no online SOC run is needed here
    trace = build_pack(rec, n_cells, ocv, q, seed=seed, reference_capacity_ah=q, duration_s=hours * 3600)
    return frame_arrays(trace), ocv, q, str(ocv_path)


def _sender(fa: FrameArrays, bus: can.BusABC, out: dict, gate=None) -> threading.Thread:
    def run() -> None:
        msgs = fa.iter_messages()
        if gate is not None:
            msgs = gate(msgs)
        try:
            out["stats"] = replay_messages(msgs, bus, "max")
        except BaseException as exc:  # noqa: BLE001 - reported by the caller
            out["error"] = exc

    th = threading.Thread(target=run, name="bms-replay-bench", daemon=True)
    return th


def _bench_direct(fa: FrameArrays, ocv: OcvCurve, q: float, n_cells: int) -> tuple[float, int, int, float, list[str]]:
    from bms_estimator.can.dbc import load_project_db
    from bms_estimator.can.decoder import FrameDecoder
    from bms_estimator.can.sampler import SampleAssembler
    from bms_estimator.core.soc import SocEstimator

    channel = f"bms-bench-{os.getpid()}-{time.monotonic_ns()}"
    rx = can.Bus(interface="virtual", channel=channel, rx_queue_size=20_000)
    tx = open_replay_bus("virtual", channel)
    dec = FrameDecoder(load_project_db(), "default", n_cells)
    sampler = SampleAssembler(n_cells, period_s=1.0, staleness_s=5.0)
    est = SocEstimator(n_cells, ocv, q, 1.0, initial_soc=None)
    out: dict = {}
    th = _sender(fa, tx, out)
    decode, feed, update, recv = dec.decode, sampler.feed_frame, est.update, rx.recv
    perf, cpu = time.perf_counter, time.thread_time  # CPU time of this thread: not the GIL waits
    n = samples = 0
    t_est = 0.0
    try:
        t0 = perf()
        th.start()
        while True:
            msg = recv(0.2)
            if msg is None:
                if not th.is_alive():
                    break
                continue
            n += 1
            for s in feed(decode(msg), msg.timestamp):
                a = cpu()
                update(s.current_a, s.cell_voltage_v, s.valid)
                t_est += cpu() - a
                samples += 1
        wall = perf() - t0
    finally:
        th.join(5)
        tx.shutdown()
        rx.shutdown()
    if "error" in out:
        raise RuntimeError("replay thread failed") from out["error"]
    notes = []
    if n != len(fa):
        notes.append(f"received {n} of {len(fa)} frames")
    if dec.counters.errors:
        notes.append(f"decode errors {dec.counters.errors}")
    return wall, n, samples, t_est, notes


class _InlineSink:
    """A ``bus`` for :func:`replay_messages` that processes each frame where it is sent."""

    def __init__(self, dec, sampler, est) -> None:
        self.decode, self.feed, self.update = dec.decode, sampler.feed_frame, est.update
        self.frames = self.samples = 0

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self.frames += 1
        for s in self.feed(self.decode(msg), msg.timestamp):
            self.update(s.current_a, s.cell_voltage_v, s.valid)
            self.samples += 1


def _bench_inline(fa: FrameArrays, ocv: OcvCurve, q: float, n_cells: int) -> tuple[float, int, int, list[str]]:
    from bms_estimator.can.dbc import load_project_db
    from bms_estimator.can.decoder import FrameDecoder
    from bms_estimator.can.sampler import SampleAssembler
    from bms_estimator.core.soc import SocEstimator

    dec = FrameDecoder(load_project_db(), "default", n_cells)
    sink = _InlineSink(dec, SampleAssembler(n_cells, period_s=1.0, staleness_s=5.0),
                       SocEstimator(n_cells, ocv, q, 1.0, initial_soc=None))
    t0 = time.perf_counter()
    replay_messages(fa.iter_messages(), sink, "max")  # type: ignore[arg-type]
    wall = time.perf_counter() - t0
    notes = [f"decode errors {dec.counters.errors}"] if dec.counters.errors else []
    return wall, sink.frames, sink.samples, notes


def _bench_daemon(fa: FrameArrays, ocv_path: str, q: float, n_cells: int) -> tuple[float, int, int, list[str]]:
    from bms_estimator.service.config import ServiceConfig

    channel = f"bms-bench-{os.getpid()}-{time.monotonic_ns()}"
    with tempfile.TemporaryDirectory(prefix="bms-replay-bench-") as tmp:
        cfg = ServiceConfig(
            pack={"pack_id": "bench", "n_cells": n_cells, "capacity_ah": q, "ocv_csv": ocv_path},
            can={"interface": "virtual", "channel": channel, "output": {"enabled": False}},
            mqtt={"enabled": False},
            health={"enabled": False},
            state={"path": str(Path(tmp) / "state.json")},
        )
        return asyncio.run(_run_daemon(cfg, fa, channel))


async def _run_daemon(cfg: Any, fa: FrameArrays, channel: str) -> tuple[float, int, int, list[str]]:
    from bms_estimator.service.daemon import Service

    svc = Service(cfg)
    stop = asyncio.Event()
    task = asyncio.create_task(svc.run(stop))
    await asyncio.wait_for(svc.ready.wait(), 10)
    tx = open_replay_bus("virtual", channel)
    window = 20_000

    def gate(msgs):
        # flow control on the service's public receive counter: never more than `window` in flight
        sent = 0
        for m in msgs:
            if sent & 0x3FF == 0:
                while sent - svc.bus.counters.rx_frames - svc.bus.counters.rx_dropped > window:
                    time.sleep(0.0005)
            sent += 1
            yield m

    out: dict = {}
    th = _sender(fa, tx, out, gate)
    total = len(fa)
    t0 = time.perf_counter()
    th.start()
    try:
        # done when the service has decoded every frame (the bus counts frames when the estimator
        # loop takes them from the receive queue, a batch at a time, before it decodes them)
        while svc.decoder.counters.frames + svc.bus.counters.rx_dropped < total:
            if not th.is_alive() and "error" in out:
                break
            await asyncio.sleep(0.05)
            if not th.is_alive() and svc.decoder.counters.frames + svc.bus.counters.rx_dropped < total:
                # the sender is done: give the service a moment to drain, then stop waiting
                await asyncio.sleep(0.05)
                if svc.decoder.counters.frames >= total:
                    break
        wall = time.perf_counter() - t0
    finally:
        th.join(5)
        stop.set()
        await asyncio.wait_for(task, 30)
        tx.shutdown()
    if "error" in out:
        raise RuntimeError("replay thread failed") from out["error"]
    notes = []
    frames = svc.decoder.counters.frames
    if frames != total:
        notes.append(f"service decoded {frames} of {total} frames")
    if svc.bus.counters.rx_dropped:
        notes.append(f"service receive queue dropped {svc.bus.counters.rx_dropped} frames")
    if svc.decoder.counters.errors:
        notes.append(f"decode errors {svc.decoder.counters.errors}")
    return wall, frames, int(svc.pipeline.counters.samples), notes


def daemon_available() -> bool:
    try:
        from bms_estimator.service.daemon import Service  # noqa: F401
    except ImportError:
        return False
    return True


def bench_replay_speedup(hours: float = 4.0, n_cells: int = 96, *, via: str = "auto", cell: str = "lg-hg2",
                         cycle: str = "udds", seed: int = 0, frames: tuple | None = None) -> ReplayBenchResult:
    """Times faster than real time (see the module docstring). ``via``: ``auto`` (the daemon when
    it exists, else direct), ``daemon`` or ``direct``. ``frames``: the output of
    :func:`prepare_frames` to reuse between calls."""
    if via == "auto":
        via = "daemon" if daemon_available() else "direct"
    if via not in ("daemon", "direct", "inline"):
        raise ValueError("via must be 'auto', 'daemon', 'direct' or 'inline'")
    t = time.perf_counter()
    fa, ocv, q, ocv_path = frames if frames is not None else prepare_frames(hours, n_cells, cell=cell, cycle=cycle,
                                                                          seed=seed)
    prep = time.perf_counter() - t
    log_s = (fa.t_us[-1] - fa.t_us[0]) / 1e6 + 0.01
    t_est = None
    if via == "direct":
        wall, n, samples, t_est, notes = _bench_direct(fa, ocv, q, n_cells)
    elif via == "inline":
        wall, n, samples, notes = _bench_inline(fa, ocv, q, n_cells)
    else:
        wall, n, samples, notes = _bench_daemon(fa, ocv_path, q, n_cells)
    return ReplayBenchResult(
        speedup=log_s / wall if wall > 0 else math.inf, via=via, hours=hours, n_cells=n_cells, frames=n,
        frames_per_s=n / wall if wall > 0 else math.inf, samples=samples, wall_s=wall, log_s=log_s,
        prepare_s=prep, estimator_s=t_est, notes=notes,
    )


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--hours", type=float, default=4.0)
    p.add_argument("--cells", type=int, default=96)
    p.add_argument("--via", choices=("auto", "daemon", "direct", "inline", "all"), default="all")
    p.add_argument("--one-core", action="store_true", help="pin the process to one core")
    p.add_argument("--json", action="store_true")
    args = p.parse_args(argv)
    from bms_estimator.service.logging import configure_logging

    configure_logging(level="WARNING", fmt="console")
    if args.one_core:
        try:
            os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})
        except (AttributeError, OSError):
            pass
    frames = prepare_frames(args.hours, args.cells)
    vias = ["inline", "direct", "daemon"] if args.via == "all" else [args.via]
    results = []
    for via in vias:
        if via == "daemon" and not daemon_available():
            print("daemon: bms_estimator/service/daemon.py not available")
            continue
        r = bench_replay_speedup(args.hours, args.cells, via=via, frames=frames)
        results.append(r)
        if not args.json:
            extra = f", estimator {r.estimator_s:.1f} s" if r.estimator_s is not None else ""
            print(f"{r.via:6s}: {r.hours:g} h x {r.n_cells} cells = {r.frames:,} frames in {r.wall_s:.1f} s "
                  f"-> {r.speedup:.0f}x real time ({r.frames_per_s:,.0f} frames/s, {r.samples} samples{extra})"
                  + (f"; {'; '.join(r.notes)}" if r.notes else ""))
    if args.json:
        print(json.dumps([r.as_dict() for r in results]))
    return 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
