"""``bms-estimator bench``: speed figures, printed (never asserted in tests).

Figures (one core, this machine, one run):

* ``cell_updates_per_s``: full SOC estimator updates (LIF identification, c0
  compensation, capacity estimation) of a 2000-cell pack, cells x samples / s.
* ``tick_ms_200_cells``: median wall time of one 1 s update of a 200-cell pack.
* ``frames_per_s``: CAN decode + sample assembly (when the CAN layer is present).
"""

from __future__ import annotations

import argparse
import json
import os
import time

import numpy as np

from ..core.ocv import OcvCurve
from ..core.soc import SocEstimator


def add_parser(sub) -> None:
    p = sub.add_parser("bench", help="print speed figures (estimator throughput, tick time, CAN frames/s)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--seconds", type=float, default=3.0, help="time budget per figure (default 3 s)")
    p.set_defaults(func=run)


def _synthetic_curve() -> OcvCurve:
    soc = np.linspace(0, 1, 101)
    return OcvCurve(soc, 3.0 + 1.2 * soc - 0.15 * np.sin(3 * soc))


def _pack_inputs(n_cells: int, n_steps: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    current = np.repeat(rng.uniform(-3, 1, size=n_steps // 20 + 1), 20)[:n_steps]
    spread = rng.normal(1.0, 0.05, size=n_cells)
    volts = 3.7 + 0.02 * current[:, None] * spread[None, :] + 0.001 * rng.standard_normal((n_steps, n_cells))
    return current, volts


def bench_cell_updates(n_cells: int = 2000, seconds: float = 3.0) -> float:
    est = SocEstimator(n_cells, _synthetic_curve(), 3.0, 1.0, initial_soc=0.8)
    current, volts = _pack_inputs(n_cells, 4000)
    for k in range(700):  # past the block-LS start, so the steady-state path is measured
        est.update(current[k], volts[k])
    k, t0 = 700, time.perf_counter()
    while time.perf_counter() - t0 < seconds and k < len(current):
        est.update(current[k], volts[k])
        k += 1
    return n_cells * (k - 700) / (time.perf_counter() - t0)


def bench_tick_ms(n_cells: int = 200, ticks: int = 300) -> float:
    est = SocEstimator(n_cells, _synthetic_curve(), 3.0, 1.0, initial_soc=0.8)
    current, volts = _pack_inputs(n_cells, 700 + ticks)
    for k in range(700):
        est.update(current[k], volts[k])
    times = []
    for k in range(700, 700 + ticks):
        t0 = time.perf_counter()
        est.update(current[k], volts[k])
        times.append(time.perf_counter() - t0)
    return float(np.median(times) * 1e3)


def run(args: argparse.Namespace) -> int:
    try:
        os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})  # one core, as the goals state
    except (AttributeError, OSError):
        pass
    out: dict[str, float] = {
        "cell_updates_per_s": bench_cell_updates(2000, args.seconds),
        "tick_ms_200_cells": bench_tick_ms(200),
    }
    try:
        from ..can.bench import bench_frames_per_s
    except ImportError:
        pass
    else:
        out["frames_per_s"] = float(bench_frames_per_s(n_cells=200))
    try:
        from ..service.bench import bench_publish_latency_ms_p99
    except ImportError:
        pass
    else:
        latency = bench_publish_latency_ms_p99(n_cells=200)
        if latency is not None:  # None without a Mosquitto to measure through
            out["publish_latency_ms_p99"] = float(latency)
    if args.json:
        print(json.dumps(out))
    else:
        for k, v in out.items():
            print(f"{k:24s} {v:,.3f}")
    return 0
