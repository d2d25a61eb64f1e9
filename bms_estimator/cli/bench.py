"""``bms-estimator bench``: speed figures, printed (never asserted in tests).

Figures (one core, this machine, one run):

* ``cell_updates_per_s``: full SOC estimator updates of a 2000-cell pack with the
  defaults (LIF identification, the EKF SOC method, capacity estimation), the OCV
  interpolated between three tables by each cell's own temperature, cells x samples / s.
* ``cell_updates_per_s_c0``: the same with the paper's c0 SOC method.
* ``cell_updates_per_s_lif_iv``: the same as the first with the recursive-IV LIF identifier (``lif-iv``).
* ``cell_updates_per_s_lif_iv_bv``: the same with the kinetic-term identifier (``lif-iv-bv``).
* ``cell_updates_per_s_lif_iv_ct``: the same with the charge-transfer identifier (``lif-iv-ct``).
* ``tick_ms_200_cells``: median wall time of one 1 s update of a 200-cell pack.
* ``tick_ms_200_cells_sox``: the same with the state of power, energy and health
  (core.sox.SoxEstimator: SOP at 2/10/30 s, SOE, SOH) after it; ``sox_ms_200_cells`` that part alone.
* ``frames_per_s``: CAN decode + sample assembly, 200 cells.
* ``publish_latency_ms_p99``: from the CAN frame that closes a 1 s sample to the MQTT
  message for it, 200 cells, through a real Mosquitto (left out without one).
* ``replay_speedup``: times faster than real time that a 4-hour drive cycle of a 96-cell
  pack goes through replay + the service at ``max`` (in-process virtual bus).
* ``diagnose_4h_s``: wall time of ``diagnose`` on the 4.4 h LG UDDS sample (goal: under 60 s).
* ``batch_speedup`` / ``batch_speedup_mf4``: times faster than real time that a 4-hour,
  96-cell log (candump ``.log`` / MF4) goes through ``batch``'s bulk decode and the
  estimator on one worker (goal: 2000x); ``batch_speedup_cpu`` / ``batch_speedup_mf4_cpu``
  the same against the process's CPU time (the figure on a core of its own);
  ``batch_speedup_stack4`` / ``batch_speedup_stack4_cpu``: one worker's throughput (times real
  time) when its task holds 4 such drives, their estimation stacked (``batch --stack 4``).
* ``batch_speedup_sox`` / ``batch_speedup_sox_cpu``: ``batch_speedup`` / ``_cpu`` with ``batch --sox``
  (SOP/SOE/SOH too; one drive alone), measured in pairs with runs without it (the ratio on stderr);
  ``batch_speedup_sox_stack4`` / ``_cpu``: ``batch_speedup_stack4`` / ``_cpu`` with ``batch --sox`` (4
  drives stacked, SOX part included), right after the same task without SOX (on stderr).
* ``batch_scaling_2_workers``: ``batch`` throughput on a 2-process Dask LocalCluster over
  1 process; ``batch_10k_drives_worker_h``: the measured cost of 10,000 such 4-hour drives
  in worker-hours (the estimate for N workers is printed on stderr).
"""

from __future__ import annotations

import argparse
import json
import os
import time

import numpy as np

from ..core.identifier import IdentifierConfig
from ..core.ocv import OcvCurve
from ..core.ocv_surface import OcvSurface
from ..core.soc import SocConfig, SocEstimator
from ..core.sox import SoxEstimator
from .common import positive_float


def add_parser(sub) -> None:
    p = sub.add_parser("bench", help="print speed figures (estimator throughput, tick time, CAN frames/s)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--seconds", type=positive_float, default=3.0, help="time budget of the estimator figure (default 3 s)")
    p.add_argument("--figures", default=None,
                   help="comma-separated subset (default all: " + ", ".join(FIGURES)
                   + "); replay_speedup and the batch figures take a few minutes each, saturation_loss_pct 30 s")
    p.set_defaults(func=run)


def _synthetic_surface() -> OcvSurface:
    """Three tables (-10, 0 and 25 degC) with hysteresis and C/20 capacities, as a cell's tests give."""
    soc = np.linspace(0, 1, 101)
    curves = [OcvCurve(soc, 3.0 + 1.2 * soc - 0.15 * np.sin(3 * soc) + 0.02 * k, 0.015 + 0.01 * (1 - soc) + 0.01 * k,
                       capacity_discharge_ah=3.0 - 0.1 * k) for k in range(3)]
    return OcvSurface(curves, [25.0, 0.0, -10.0])


def _pack_inputs(n_cells: int, n_steps: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    current = np.repeat(rng.uniform(-3, 1, size=n_steps // 20 + 1), 20)[:n_steps]
    spread = rng.normal(1.0, 0.05, size=n_cells)
    volts = 3.7 + 0.02 * current[:, None] * spread[None, :] + 0.001 * rng.standard_normal((n_steps, n_cells))
    return current, volts


def _warm_up(est: SocEstimator) -> int:
    """Samples past the longest block-LS start (a block that is not yet physical keeps
    growing and is solved again each sample), so that the steady-state path is measured."""
    cfg = est.config.identifier
    return max(cfg.init_samples, cfg.init_max_samples) + 2 * cfg.window + 100


def bench_cell_updates(n_cells: int = 2000, seconds: float = 3.0, method: str = "lif",
                       soc_method: str | None = None) -> float:
    cfg = SocConfig(identifier=IdentifierConfig(method=method))
    if soc_method is not None:
        cfg = cfg.with_(soc_method=soc_method)
    est = SocEstimator(n_cells, _synthetic_surface(), 3.0, 1.0, initial_soc=0.8, config=cfg)
    warm = _warm_up(est)
    current, volts = _pack_inputs(n_cells, warm + 4000)
    # each cell at its own temperature, drifting: the tables are blended per cell every sample
    temps = np.random.default_rng(1).uniform(-15.0, 35.0, n_cells)
    for k in range(warm):
        est.update(current[k], volts[k], temperature_c=temps + 1e-3 * k)
    k, t0 = warm, time.perf_counter()
    while time.perf_counter() - t0 < seconds and k < len(current):
        est.update(current[k], volts[k], temperature_c=temps + 1e-3 * k)
        k += 1
    return n_cells * (k - warm) / (time.perf_counter() - t0)


def bench_tick_ms(n_cells: int = 200, ticks: int = 300, *, sox: str = "off") -> float:
    """Median ms of one tick: the SOC estimator (``sox="off"``), it and the SOP/SOE/SOH
    (``"with"``), or the SOP/SOE/SOH alone (``"only"``)."""
    est = SocEstimator(n_cells, _synthetic_surface(), 3.0, 1.0, initial_soc=0.8)
    sx = SoxEstimator(n_cells, 1.0) if sox != "off" else None
    warm = _warm_up(est)
    current, volts = _pack_inputs(n_cells, warm + ticks)
    for k in range(warm):
        est.update(current[k], volts[k])
        if sx is not None:
            sx.update(est, current[k], volts[k])
    times = []
    for k in range(warm, warm + ticks):
        t0 = time.perf_counter()
        if sox != "only":
            est.update(current[k], volts[k])
        else:
            est.update(current[k], volts[k])
            t0 = time.perf_counter()
        if sx is not None:
            sx.update(est, current[k], volts[k])
        times.append(time.perf_counter() - t0)
    return float(np.median(times) * 1e3)


def _benchmarks():
    """The ``benchmarks`` package of the source checkout (not installed with the package)."""
    import importlib
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[2]
    if not (root / "benchmarks" / "__init__.py").is_file():
        from ..errors import UsageError

        raise UsageError("this figure's benchmark is in the source checkout (benchmarks/): run "
                         "'bms-estimator bench' from a clone installed with 'pip install -e .'")
    if str(root) not in sys.path:
        sys.path.insert(0, str(root))
    return importlib.import_module("benchmarks")


def _frames_per_s() -> float | None:
    _benchmarks()
    from benchmarks.can_frames import bench_frames_per_s

    return float(bench_frames_per_s(n_cells=200))


def _publish_latency() -> float | None:
    _benchmarks()
    from benchmarks.publish_latency import bench_publish_latency_ms_p99

    return bench_publish_latency_ms_p99(n_cells=200)  # None without a Mosquitto to measure through


def _replay_speedup() -> float | None:
    _benchmarks()
    from benchmarks.replay_speedup import bench_replay_speedup

    return float(bench_replay_speedup(hours=4.0, n_cells=96, via="daemon").speedup)


def _diagnose_s() -> float | None:
    _benchmarks()
    from benchmarks.diagnose_speed import bench_diagnose_s

    return float(bench_diagnose_s())


def _saturation_loss_pct() -> float | None:
    _benchmarks()
    from benchmarks.saturation import SaturationResult, bench_saturation

    res = bench_saturation(n_cells=200, seconds=30.0)
    if not isinstance(res, SaturationResult):
        print(f"saturation_loss_pct: not measured here ({res})")
        return None
    print(f"saturation: {res.sent:,} frames at {res.frames_per_s:,.0f}/s, {res.received:,} received, "
          f"counted lost {res.counted_lost}, uncounted {res.uncounted}, MQTT {'on' if res.mqtt else 'off'}, "
          f"tick p99 <= {res.tick_p99_ms} ms, loop lag p99 <= {res.loop_lag_p99_ms} ms (histogram buckets)")
    return res.loss_pct
def _batch(figure: str) -> float:
    """The batch figures share one run (inputs are written once): see benchmarks/batch_speedup.py."""
    import sys

    _benchmarks()
    from benchmarks.batch_speedup import bench_batch, estimate_text

    r = bench_batch()
    runs = {"batch_speedup": r.speedups_log, "batch_speedup_mf4": r.speedups_mf4}.get(figure)
    if runs:
        print(f"{figure}: the best of {len(runs)} runs of one drive; every run (wall / CPU): "
              + ", ".join(f"{w:,.0f}x / {c:,.0f}x" for w, c in runs), file=sys.stderr)
    if figure == "batch_10k_drives_worker_h":
        print(estimate_text(r), file=sys.stderr)
        return 10_000 * r.drive_s_one_worker / 3600.0
    return {"batch_speedup": r.speedup_log, "batch_speedup_mf4": r.speedup_mf4,
            "batch_speedup_cpu": r.speedup_log_cpu, "batch_speedup_mf4_cpu": r.speedup_mf4_cpu,
            "batch_speedup_stack4": r.speedup_stack, "batch_speedup_stack4_cpu": r.speedup_stack_cpu,
            "batch_scaling_2_workers": r.scaling_2_workers}[figure]


def _batch_sox(cpu: bool, stacked: bool = False) -> float:
    """``batch --sox`` on one drive, paired with runs without it: see benchmarks/batch_speedup.py."""
    import sys

    _benchmarks()
    from benchmarks.batch_speedup import bench_batch_sox

    r = bench_batch_sox()
    print(f"batch_speedup_sox: {r.hours:g} h x {r.n_cells} cells, best of {len(r.runs)}: "
          f"{r.speedup_sox:,.0f}x with SOX, {r.speedup:,.0f}x without (CPU {r.speedup_sox_cpu:,.0f}x / "
          f"{r.speedup_cpu:,.0f}x); estimate stage "
          f"{r.estimate_s_sox:.1f} s against {r.estimate_s:.1f} s; every pair (without / with): "
          + ", ".join(f"{a:,.0f}x / {b:,.0f}x" for a, b in r.runs)
          + f"; {r.stack} drives stacked: {r.speedup_stack_sox:,.0f}x with SOX, {r.speedup_stack:,.0f}x without "
          f"(CPU {r.speedup_stack_sox_cpu:,.0f}x / {r.speedup_stack_cpu:,.0f}x)", file=sys.stderr)
    if stacked:
        return r.speedup_stack_sox_cpu if cpu else r.speedup_stack_sox
    return r.speedup_sox_cpu if cpu else r.speedup_sox


#: figure name -> how to measure it (each prints on its own; slow ones can be left out)
FIGURES = {
    "cell_updates_per_s": lambda args: bench_cell_updates(2000, args.seconds),
    "cell_updates_per_s_c0": lambda args: bench_cell_updates(2000, args.seconds, soc_method="c0"),
    "cell_updates_per_s_lif_iv": lambda args: bench_cell_updates(2000, args.seconds, "lif-iv"),
    "cell_updates_per_s_lif_iv_bv": lambda args: bench_cell_updates(2000, args.seconds, "lif-iv-bv"),
    "cell_updates_per_s_lif_iv_ct": lambda args: bench_cell_updates(2000, args.seconds, "lif-iv-ct"),
    "tick_ms_200_cells": lambda args: bench_tick_ms(200),
    "tick_ms_200_cells_sox": lambda args: bench_tick_ms(200, sox="with"),
    "sox_ms_200_cells": lambda args: bench_tick_ms(200, sox="only"),
    "frames_per_s": lambda args: _frames_per_s(),
    "publish_latency_ms_p99": lambda args: _publish_latency(),
    "replay_speedup": lambda args: _replay_speedup(),
    "diagnose_4h_s": lambda args: _diagnose_s(),
    "saturation_loss_pct": lambda args: _saturation_loss_pct(),
    "batch_speedup": lambda args: _batch("batch_speedup"),
    "batch_speedup_mf4": lambda args: _batch("batch_speedup_mf4"),
    "batch_speedup_cpu": lambda args: _batch("batch_speedup_cpu"),
    "batch_speedup_mf4_cpu": lambda args: _batch("batch_speedup_mf4_cpu"),
    "batch_speedup_stack4": lambda args: _batch("batch_speedup_stack4"),
    "batch_speedup_stack4_cpu": lambda args: _batch("batch_speedup_stack4_cpu"),
    "batch_speedup_sox": lambda args: _batch_sox(False),
    "batch_speedup_sox_cpu": lambda args: _batch_sox(True),
    "batch_speedup_sox_stack4": lambda args: _batch_sox(False, stacked=True),
    "batch_speedup_sox_stack4_cpu": lambda args: _batch_sox(True, stacked=True),
    "batch_scaling_2_workers": lambda args: _batch("batch_scaling_2_workers"),
    "batch_10k_drives_worker_h": lambda args: _batch("batch_10k_drives_worker_h"),
}


def run(args: argparse.Namespace) -> int:
    try:
        os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})  # one core, as the goals state
    except (AttributeError, OSError):
        pass
    from ..errors import UsageError

    names = list(FIGURES) if args.figures is None else [f.strip() for f in args.figures.split(",") if f.strip()]
    if not names:  # ('--figures ""' printed nothing, exit 0)
        raise UsageError(f"--figures {args.figures!r} names no figure; choose from {', '.join(FIGURES)}")
    unknown = [n for n in names if n not in FIGURES]
    if unknown:
        raise UsageError(f"--figures: unknown figure(s) {', '.join(unknown)}; choose from {', '.join(FIGURES)}")
    out: dict[str, float] = {}
    for name in names:
        value = FIGURES[name](args)
        if value is not None:
            out[name] = float(value)
    if args.json:
        print(json.dumps(out))
    else:
        for k, v in out.items():
            print(f"{k:24s} {v:,.3f}")
    return 0
