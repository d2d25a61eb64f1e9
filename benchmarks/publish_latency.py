"""Latency of the whole service path: closing CAN frame -> MQTT message, through a real broker.

:func:`bench_publish_latency_ms_p99` runs the real :class:`~bms_estimator.service.daemon.Service`
(virtual CAN bus, MQTT QoS 1 to a Mosquitto started on a free loopback port,
CAN output on, health server off) on the synthetic bus traffic of
:func:`benchmarks.can_frames.synth_frames` (current every 10 ms, every cell
voltage every 100 ms). For each 1 s sample it first sends the frames inside
the period and waits until the service has read them, then sends the frame
that closes the period and measures the time until a subscriber has received
the states of *all* cells for that sample. That covers the bus hand-over,
decode, sample assembly, the estimator update, the CAN output encoding, the
MQTT publishing (QoS 1, acknowledged) and the broker.

Returns ``None`` when no Mosquitto binary is found (``$MOSQUITTO``,
``mosquitto`` on ``PATH``, ``/usr/sbin/mosquitto``) or it does not start.
"""

from __future__ import annotations

import asyncio
import contextlib
import gc
import sys
import tempfile
import time
import uuid
from pathlib import Path
import numpy as np
import structlog

from bms_estimator.mosquitto import Mosquitto, find_mosquitto

__all__ = ["bench_publish_latency", "bench_publish_latency_ms_p99", "find_mosquitto"]

log = structlog.get_logger("bms.bench")


_SUBSCRIBER = r"""
import json, sys, time
import paho.mqtt.client as mqtt

port, topic, n = int(sys.argv[1]), sys.argv[2], int(sys.argv[3])
counts = {}

def on_connect(client, userdata, flags, reason, props=None):
    client.subscribe(topic, qos=1)

def on_subscribe(client, userdata, mid, reasons, props=None):
    print("subscribed", flush=True)

def on_message(client, userdata, message):
    t = time.perf_counter()
    t_s = json.loads(message.payload)["t_s"]
    counts[t_s] = counts.get(t_s, 0) + 1
    if counts[t_s] == n:
        print(repr(t_s), repr(t), flush=True)
        del counts[t_s]

client = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2)
client.on_connect, client.on_subscribe, client.on_message = on_connect, on_subscribe, on_message
client.connect("127.0.0.1", port)
client.loop_forever()
"""


@contextlib.contextmanager
def _broker(workdir: Path):
    with Mosquitto(workdir) as broker:
        yield broker.port


async def _measure(port: int, workdir: Path, n_cells: int, samples: int, warmup: int, freeze_gc: bool = True) -> list[float]:
    import can

    from benchmarks.can_frames import synth_frames
    from bms_estimator.can.dbc import load_project_db
    from bms_estimator.can.decoder import FrameDecoder
    from bms_estimator.can.sampler import SampleAssembler
    from bms_estimator.service.config import ServiceConfig
    from bms_estimator.service.daemon import Service

    db = load_project_db()
    total = samples + warmup
    frames = synth_frames(db, "default", n_cells, total + 2.0)
    # which frame closes which sample: the same decoder + sampler, offline
    dec, smp = FrameDecoder(db, "default", n_cells), SampleAssembler(n_cells, 1.0, 2.5)
    closers: list[tuple[int, float]] = []
    for idx, m in enumerate(frames):
        for s in smp.feed_frame(dec.decode(m), m.timestamp):
            closers.append((idx, s.t_s))
    closers = closers[:total]

    ch = f"bms-bench-{uuid.uuid4().hex[:8]}"
    pack = "bench"
    cfg = ServiceConfig(
        pack={"pack_id": pack, "n_cells": n_cells, "capacity_ah": 3.0},
        can={"interface": "virtual", "channel": ch},
        estimator={"sample_period_s": 1.0, "staleness_s": 2.5},
        mqtt={"host": "127.0.0.1", "port": port, "qos": 1, "reconnect_min_s": 0.05, "reconnect_max_s": 0.5},
        state={"path": str(workdir / "state.npz"), "save_interval_s": 3600.0},
        health={"enabled": False},
    )
    # The consumer is another process (as on a vehicle: a broker client elsewhere), so its
    # receiving does not compete with the service's event loop. CLOCK_MONOTONIC is shared.
    sub = await asyncio.create_subprocess_exec(
        sys.executable, "-c", _SUBSCRIBER, str(port), f"{cfg.mqtt.base_topic}/{pack}/cell/+/state", str(n_cells),
        stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.DEVNULL,
    )
    svc = Service(cfg)
    if freeze_gc:
        gc.collect()
        gc.freeze()  # as `bms-estimator run` does after building the service
    stop = asyncio.Event()
    run = asyncio.create_task(svc.run(stop))
    tx = can.Bus(interface="virtual", channel=ch, preserve_timestamps=True)
    latencies: list[float] = []
    try:
        assert sub.stdout is not None
        if (await asyncio.wait_for(sub.stdout.readline(), 20)).strip() != b"subscribed":
            raise RuntimeError("subscriber did not start")
        deadline = time.monotonic() + 20
        while not (svc.ready.is_set() and svc.publisher.connected):
            if run.done() or time.monotonic() > deadline:
                raise RuntimeError("service did not come up")
            await asyncio.sleep(0.01)
        sent = 0
        for k, (idx, t_s) in enumerate(closers):
            for m in frames[sent:idx]:
                tx.send(m)
            sent = idx
            while svc.decoder.counters.frames < sent:  # let the service read the period's frames
                await asyncio.sleep(0.0005)
            t0 = time.perf_counter()
            tx.send(frames[idx])
            sent = idx + 1
            while True:  # "<t_s> <perf_counter>" once the subscriber has every cell of t_s
                line = (await asyncio.wait_for(sub.stdout.readline(), 10)).split()
                if not line:
                    raise RuntimeError("subscriber ended")
                if float(line[0]) == t_s:
                    break
            if k >= warmup:
                latencies.append(float(line[1]) - t0)
    finally:
        stop.set()
        with contextlib.suppress(BaseException):
            await asyncio.wait_for(run, 20)
        tx.shutdown()
        if sub.returncode is None:
            sub.terminate()
            with contextlib.suppress(BaseException):
                await asyncio.wait_for(sub.wait(), 5)
    return latencies


def bench_publish_latency(
    n_cells: int = 200, samples: int = 100, warmup: int = 5, *, freeze_gc: bool = True
) -> dict[str, float] | None:
    """``{"p50_ms", "p99_ms", "max_ms", "samples"}`` of closing frame -> all cell states on MQTT, or None.

    ``freeze_gc`` (as the daemon does) moves everything alive after start-up out of the
    cyclic GC; without it a full collection over the DBC's objects adds ~100 ms every
    few seconds. It is process-wide: tests pass False.
    """
    binary = find_mosquitto()
    if binary is None:
        log.info("mosquitto not found: publish latency not measured")
        return None
    try:
        with tempfile.TemporaryDirectory(prefix="bms-bench-") as d, _broker(Path(d)) as port:
            lat = asyncio.run(_measure(port, Path(d), n_cells, samples, warmup, freeze_gc))
    except (RuntimeError, OSError, asyncio.TimeoutError) as exc:
        log.warning("publish latency not measured", error=f"{type(exc).__name__}: {exc}")
        return None
    ms = np.asarray(lat) * 1e3
    return {
        "p50_ms": float(np.percentile(ms, 50)),
        "p99_ms": float(np.percentile(ms, 99)),
        "max_ms": float(ms.max()),
        "samples": int(ms.size),
    }


def bench_publish_latency_ms_p99(n_cells: int = 200, samples: int = 100) -> float | None:
    """99th percentile, in ms, from the CAN frame that closes a 1 s sample to the MQTT
    message of the last of ``n_cells`` cells for that sample (real Mosquitto); None without one."""
    res = bench_publish_latency(n_cells, samples)
    return None if res is None else res["p99_ms"]
