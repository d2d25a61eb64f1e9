"""Throughput of the CAN input path: decode + sample assembly on one core.

The synthetic bus follows the mapping's own layout (so it works for any
preset/DBC pair): the pack current every 10 ms, every cell voltage every
100 ms (as many cells per frame as the DBC carries: 3 in the project's DBC, 4
in foxBMS), every cell temperature every 1 s, and the pack voltage every
10 ms when mapped. Frames are made with cantools ``encode`` from raw values
before the clock starts and carry the mapping's end-to-end checks (alive counter,
CRC; :class:`~bms_estimator.can.e2e.E2EStamper`) as a sender would; the timed loop is
``FrameDecoder.decode`` + ``SampleAssembler.feed_frame`` only, replaying the stream with
shifted timestamps until ``seconds`` of wall time have passed. The replayed stream is
16 s long, so every message's frame count per lap is a multiple of the 4-bit counter's
16 values and the counters run on seamlessly from lap to lap.
"""

from __future__ import annotations

import math
import time
from collections import defaultdict
from dataclasses import dataclass

import can
from cantools.database.can import Database

from bms_estimator.can.dbc import load_project_db
from bms_estimator.can.decoder import EventKind, FrameDecoder
from bms_estimator.can.e2e import E2EStamper
from bms_estimator.can.mapping import CanMapping, load_mapping
from bms_estimator.can.sampler import SampleAssembler

__all__ = ["BenchResult", "bench", "bench_frames_per_s", "synth_frames"]


def _raw_for(si: float, a: float, b: float) -> int:
    return int(round((si - b) / a))


def _frame_data(db_msg, mux: int | None, mux_signal: str | None, values: dict[str, int]) -> bytes:
    raws: dict[str, int] = {}
    for sig in db_msg.signals:
        if sig.multiplexer_ids and (mux is None or mux not in sig.multiplexer_ids):
            continue
        raws[sig.name] = 0
    if mux_signal is not None and mux is not None:
        raws[mux_signal] = mux
    raws.update(values)
    return db_msg.encode(raws, scaling=False, strict=False, padding=False)


def synth_frames(
    db: Database,
    mapping: CanMapping | str,
    n_cells: int,
    seconds: float,
    *,
    t0: float = 1000.0,
    current_period_s: float = 0.01,
    voltage_period_s: float = 0.1,
    temperature_period_s: float = 1.0,
) -> list[can.Message]:
    """A time-ordered synthetic stream of ``seconds`` of bus traffic (see the module docstring)."""
    mapping = load_mapping(mapping)
    dec = FrameDecoder(db, mapping, n_cells)
    # group mapped signals by (message, mux)
    groups: dict[tuple[str, int | None], list] = defaultdict(list)
    for ms in dec.layout():
        groups[(ms.message, ms.mux)].append(ms)
    frames: list[tuple[float, can.Message]] = []

    def add(t: float, name: str, mux: int | None, values: dict[str, int]) -> None:
        m = db.get_message_by_name(name)
        muxes = [s.name for s in m.signals if s.is_multiplexer]
        data = _frame_data(m, mux, muxes[0] if muxes else None, values)
        frames.append(
            (t, can.Message(timestamp=t, arbitration_id=m.frame_id, is_extended_id=m.is_extended_frame, data=data))
        )

    cell_groups = {
        EventKind.CELL_VOLTAGE: [(k, v) for k, v in groups.items() if any(s.kind == EventKind.CELL_VOLTAGE for s in v)],
        EventKind.CELL_TEMPERATURE: [
            (k, v) for k, v in groups.items() if any(s.kind == EventKind.CELL_TEMPERATURE for s in v)
        ],
    }
    # current (and pack voltage) frames
    scalar_groups = [(k, v) for k, v in groups.items() if any(s.kind in (EventKind.CURRENT, EventKind.PACK_VOLTAGE) for s in v)]
    n_cur = int(round(seconds / current_period_s))
    for i in range(n_cur):
        t = t0 + i * current_period_s
        current = 20.0 * math.sin(2 * math.pi * t / 30.0) + 5.0
        for (name, mux), sigs in scalar_groups:
            values = {}
            for s in sigs:
                if s.kind == EventKind.CURRENT:
                    values[s.signal] = _raw_for(current, s.a, s.b)
                elif s.kind == EventKind.PACK_VOLTAGE:
                    values[s.signal] = _raw_for(3.7 * n_cells, s.a, s.b)
            add(t, name, mux, values)
    for kind, period, value_of in (
        (EventKind.CELL_VOLTAGE, voltage_period_s, lambda cell, k: 3.6 + 0.0005 * (cell % 50) + 0.001 * (k % 7)),
        (EventKind.CELL_TEMPERATURE, temperature_period_s, lambda cell, k: 25.0 + 0.5 * (cell % 10)),
    ):
        grp = _cover(cell_groups[kind], kind)
        if not grp:
            continue
        n_rounds = int(round(seconds / period))
        for k in range(n_rounds):
            for j, ((name, mux), sigs) in enumerate(grp):
                t = t0 + k * period + period * j / len(grp)
                values = {s.signal: _raw_for(value_of(s.cell, k), s.a, s.b) for s in sigs if s.kind == kind}
                add(t, name, mux, values)
    frames.sort(key=lambda tf: tf[0])
    stamper = E2EStamper(db, mapping)  # counters in sending order
    out = []
    for _, m in frames:
        m.data = bytearray(stamper.stamp(m.arbitration_id, m.data))
        out.append(m)
    return out


def _cover(groups: list, kind: EventKind) -> list:
    """Frames (message, mux) that send every cell once: disjoint groups first, then fill the gaps.

    (In the project's DBC every multiplexer value 0..1999 is legal and overlaps its neighbours.)
    """

    def cells(sigs) -> set[int]:
        return {s.cell for s in sigs if s.kind == kind}

    ordered = sorted(groups, key=lambda kv: (min(cells(kv[1])), kv[0][1] if kv[0][1] is not None else -1))
    chosen, covered = [], set()
    for key, sigs in ordered:
        c = cells(sigs)
        if not (c & covered):
            chosen.append((key, sigs))
            covered |= c
    for key, sigs in ordered:
        c = cells(sigs)
        if c - covered:
            chosen.append((key, sigs))
            covered |= c
    return sorted(chosen, key=lambda kv: min(cells(kv[1])))


@dataclass
class BenchResult:
    frames_per_s: float
    frames: int
    wall_s: float
    samples: int
    frames_per_bus_second: float  # frames of the synthetic bus per second of bus time
    n_cells: int


def bench(
    n_cells: int = 200,
    seconds: float = 3.0,
    *,
    db: Database | None = None,
    mapping: CanMapping | str = "default",
    stream_s: float = 16.0,
) -> BenchResult:
    """Measure decode + sample assembly throughput (see the module docstring)."""
    db = db if db is not None else load_project_db()
    mapping = load_mapping(mapping)
    frames = synth_frames(db, mapping, n_cells, stream_s)
    dec = FrameDecoder(db, mapping, n_cells)
    sampler = SampleAssembler(n_cells, period_s=1.0, staleness_s=max(2.5, 1.5 * (mapping.cell_cycle_s or 0.0)))
    decode, feed = dec.decode, sampler.feed_frame
    n = 0
    samples = 0
    lap = 0
    start = time.perf_counter()
    deadline = start + seconds
    while True:
        shift = lap * stream_s
        for msg in frames:
            samples += len(feed(decode(msg), msg.timestamp + shift))
        n += len(frames)
        lap += 1
        if time.perf_counter() >= deadline:
            break
    wall = time.perf_counter() - start
    return BenchResult(
        frames_per_s=n / wall,
        frames=n,
        wall_s=wall,
        samples=samples,
        frames_per_bus_second=len(frames) / stream_s,
        n_cells=n_cells,
    )


def bench_frames_per_s(n_cells: int = 200, seconds: float = 3.0, **kwargs) -> float:
    """Frames per second of decode + sample assembly on one core (project DBC by default)."""
    return bench(n_cells, seconds, **kwargs).frames_per_s
