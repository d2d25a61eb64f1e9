"""Helpers of the end-to-end tests (imported by module name): a Mosquitto broker and one run of
CAN log -> replay (python-can ``virtual``) -> the real service -> MQTT subscriber."""

from __future__ import annotations

import asyncio
import contextlib
import json
import math
import sys
import threading
import time
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import aiomqtt
import numpy as np

_SERVICE_TESTS = str(Path(__file__).resolve().parents[1] / "service")
if _SERVICE_TESTS not in sys.path:  # the shared broker and helpers, by module name
    sys.path.insert(0, _SERVICE_TESTS)

from service_helpers import MOSQUITTO, free_port, mosquitto_available  # noqa: E402,F401 - re-exported
from service_helpers import Broker as _ServiceBroker  # noqa: E402

PACK = "e2e"
#: the measured drive cycle of the pack logs (ends at a relaxed rest: a measured reference capacity)
CELL, CYCLE = "lg-hg2", "la92"
FLOW_WINDOW = 20_000


class Broker(_ServiceBroker):
    """Mosquitto on a free loopback port (its per-client queue is deep: a subscriber that falls
    behind a replay at full speed still gets the service's final states)."""


@dataclass
class ServiceRun:
    """What one replay through the service gave."""

    speed: float
    frames_sent: int
    frames_decoded: int
    decode_errors: int
    rx_dropped: int
    samples: int
    last_t_s: float
    wall_s: float
    state: dict[str, np.ndarray]  # the estimator's final state
    cells: dict[int, dict[float, str]] = field(default_factory=dict)  # cell -> t_s -> payload text
    pack: dict[float, str] = field(default_factory=dict)  # t_s -> pack payload text
    availability: list[str] = field(default_factory=list)

    def final(self, cell: int) -> dict[str, Any]:
        return json.loads(self.cells[cell][self.last_t_s])


async def replay_through_service(log: Path, *, n_cells: int, ocv_csv: str, capacity_ah: float, speed: float,
                                 port: int, state_dir: Path, core: dict[str, Any] | None = None,
                                 timeout_s: float = 300.0) -> ServiceRun:
    """Replay ``log`` (``bms-estimator replay``'s functions: ``read_log`` + ``replay_messages`` onto a
    ``virtual`` sender with ``preserve_timestamps``) into a running ``Service`` that publishes to
    the broker on ``port``; an aiomqtt subscriber records every state it receives. ``speed``
    ``math.inf`` = as fast as possible, flow-controlled on the service's receive counter."""
    from bms_estimator.replay.replay import open_replay_bus, read_log, replay_messages
    from bms_estimator.service.config import ServiceConfig
    from bms_estimator.service.daemon import Service

    channel = f"e2e-{uuid.uuid4().hex[:12]}"
    cfg = ServiceConfig(
        pack={"pack_id": PACK, "n_cells": n_cells, "capacity_ah": capacity_ah, "ocv_csv": ocv_csv},
        can={"interface": "virtual", "channel": channel, "output": {"enabled": False}},
        estimator={"core": core or {}},
        mqtt={"host": "127.0.0.1", "port": port, "discovery": False, "qos": 1,
              "client_id": f"bms-e2e-{uuid.uuid4().hex[:8]}"},
        health={"enabled": False},
        state={"path": str(state_dir / f"state-{channel}.npz")},
    )
    run = ServiceRun(speed, 0, 0, 0, 0, 0, math.nan, math.nan, {})
    cell_prefix = f"bms/{PACK}/cell/"

    async with aiomqtt.Client("127.0.0.1", port, identifier=f"e2e-sub-{channel}") as client:
        await client.subscribe(f"bms/{PACK}/#", qos=1)

        async def read() -> None:
            async for m in client.messages:
                topic = m.topic.value
                text = bytes(m.payload).decode()
                if topic.endswith("/availability"):
                    run.availability.append(text)
                    continue
                t_s = json.loads(text)["t_s"]
                if topic.startswith(cell_prefix):
                    run.cells.setdefault(int(topic[len(cell_prefix):].split("/")[0]), {})[t_s] = text
                elif topic.endswith("/pack/state"):
                    run.pack[t_s] = text

        reader = asyncio.create_task(read())
        svc = Service(cfg)
        stop = asyncio.Event()
        task = asyncio.create_task(svc.run(stop))
        try:
            await asyncio.wait_for(svc.ready.wait(), 10)
            tx = open_replay_bus("virtual", channel)
            counters = svc.bus.counters
            out: dict[str, Any] = {}

            def gate(msgs):
                sent = 0
                for m in msgs:
                    if not sent & 0x3FF:
                        while sent - counters.rx_frames - counters.rx_dropped > FLOW_WINDOW:
                            time.sleep(0.0005)
                    sent += 1
                    yield m

            def send() -> None:
                try:
                    msgs = read_log(log)
                    out["stats"] = replay_messages(gate(msgs) if math.isinf(speed) else msgs, tx, speed)
                except BaseException as exc:  # noqa: BLE001 - re-raised below
                    out["error"] = exc

            th = threading.Thread(target=send, daemon=True)
            t0 = time.perf_counter()
            th.start()
            deadline = time.monotonic() + timeout_s
            while True:
                if "error" in out:
                    raise out["error"]
                if "stats" in out and svc.decoder.counters.frames >= out["stats"].sent:
                    break
                assert time.monotonic() < deadline, "replay through the service timed out"
                await asyncio.sleep(0.02)
            run.wall_s = time.perf_counter() - t0
            th.join(5)
            tx.shutdown()
        finally:
            stop.set()
            await asyncio.wait_for(task, 30)
        run.frames_sent = out["stats"].sent
        run.frames_decoded = svc.decoder.counters.frames
        run.decode_errors = svc.decoder.counters.errors
        run.rx_dropped = svc.bus.counters.rx_dropped
        run.samples = int(svc.pipeline.counters.samples)
        run.last_t_s = float(svc.pipeline.last.t_s) if svc.pipeline.last is not None else float("nan")
        run.state = {k: np.array(v, copy=True) for k, v in svc.estimator.state_dict().items()}
        # the service publishes its final states on shutdown: wait for every cell's
        deadline = time.monotonic() + 30
        while not all(run.last_t_s in run.cells.get(i, {}) for i in range(n_cells)):
            assert time.monotonic() < deadline, "the final cell states did not arrive over MQTT"
            await asyncio.sleep(0.02)
        reader.cancel()
        with contextlib.suppress(BaseException):
            await reader
    return run
