"""How much faster than real time `batch` re-estimates recorded drives, and how it scales on Dask.

Input (prepared once, untimed): the shipped LG HG2 UDDS drive cycle encoded as the CAN
traffic of a ``n_cells`` pack (:func:`benchmarks.replay_speedup.prepare_frames`: 10 ms
current, 100 ms cell voltages, 1 s temperatures; 436 frames/s at 96 cells), written as a
candump ``.log`` (python-can's writer) and as an MF4 bus-logging file
(:func:`bms_estimator.fleet.frames.write_mf4`).

Figures:

``batch_speedup_log`` / ``batch_speedup_mf4``
    log seconds / wall seconds of one drive (4 h, 96 cells) through bulk read, decode,
    sample assembly and the estimator on one worker (this process; Parquet writing not
    included), i.e. what one Dask task costs.  The best of ``repeats`` (3) runs of the
    same drive, as ``timeit`` reports: on a shared 2-core machine a single run's figure
    moved by 30 % from run to run (1,660-2,199x from ``.log`` on one idle machine, one
    after the other), and the best is what the code costs without a neighbour's job in
    it.  Every run's figure is kept (``speedups_log``, ``speedups_mf4``) and printed.
``batch_speedup_cpu`` / ``batch_speedup_mf4_cpu``
    the same against this process's CPU seconds (``time.process_time``): what the drive
    costs on a core of its own; on a machine that other jobs load, wall time also holds
    the waits for a core.
``batch_speedup_stack4`` / ``batch_speedup_stack4_cpu``
    throughput of one worker when its task holds 4 such drives (``batch``'s default
    ``--stack 4``): 4 x log seconds / the wall (CPU) seconds of :func:`~bms_estimator.fleet.drive.run_drives`
    on them (each drive read, decoded and assembled on its own, the estimation stacked;
    Parquet writing not included). The 4 drives are copies of the same log: equal lengths,
    the best case; drives of different lengths run the longest one's steps.
``batch_scaling_2_workers``
    drives per second of ``run_batch`` on a ``LocalCluster`` of 2 worker processes over
    the same with 1 worker (4 drives of ``scaling_hours`` each, cluster start-up excluded).
``batch_10k_drives_h_per_worker``
    a measured estimate: 10,000 drives of 4 h cost ``10,000 x`` (one drive's wall time on
    one worker, the median of the runs) worker-hours; on N workers divide by ``N x efficiency`` (efficiency =
    scaling / 2, as measured here). Printed for a few N by :func:`estimate_text`.

``batch_speedup_sox`` / ``batch_speedup_sox_cpu``
    ``batch_speedup`` / ``_cpu`` with ``batch --sox`` (the service's SOP/SOE/SOH part after the
    estimator), one drive alone: :func:`bench_batch_sox`, the best of ``repeats``
    runs, each run with SOX right after one without on the same input, so that both figures (and
    their ratio, printed) are measured at the same load.
``batch_speedup_sox_stack4`` / ``batch_speedup_sox_stack4_cpu``
    ``batch_speedup_stack4`` / ``_cpu`` with ``batch --sox``: one task of 4 copies of the drive, their
    estimation and SOX part stacked (``SoxEstimator.set_groups``), in the same :func:`bench_batch_sox`
    run, right after the same task without SOX (both printed).

This process's allocator is set as a batch worker's (:func:`bms_estimator.fleet.memory.keep_freed_memory`:
freed memory kept for the next array, as ``batch``'s ``LocalCluster`` starts its workers), so the
figures are what a worker's task costs.

Run: ``python -m benchmarks.batch_speedup [--hours H] [--cells N]``. Nothing is asserted.
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

__all__ = ["BatchBenchResult", "SoxBenchResult", "bench_batch", "bench_batch_sox", "estimate_text"]

_CACHE: dict[tuple, "BatchBenchResult"] = {}


@dataclass
class BatchBenchResult:
    hours: float
    n_cells: int
    frames: int
    speedup_log: float
    speedup_mf4: float
    seconds_log: dict[str, float]
    seconds_mf4: dict[str, float]
    scaling_2_workers: float
    scaling_drives: int
    scaling_hours: float
    wall_1_worker_s: float
    wall_2_workers_s: float
    drive_s_one_worker: float  # wall time of one (hours, n_cells) drive on one worker (.log)
    speedup_log_cpu: float = 0.0  # log seconds / CPU seconds of this process (.log): the figure on a core of its own
    speedup_mf4_cpu: float = 0.0
    stack: int = 4
    speedup_stack: float = 0.0  # stack x log seconds / wall seconds of one task of `stack` drives (.log)
    speedup_stack_cpu: float = 0.0
    seconds_stack: dict[str, float] | None = None  # summed over the stacked drives
    speedups_log: list[tuple[float, float]] | None = None  # (wall, CPU) figure of every .log run
    speedups_mf4: list[tuple[float, float]] | None = None

    def as_dict(self) -> dict:
        return asdict(self)

    def hours_for(self, drives: int, workers: int) -> float:
        """Estimated wall hours of ``drives`` such drives on ``workers`` workers (measured efficiency)."""
        eff = min(1.0, self.scaling_2_workers / 2.0) if workers > 1 else 1.0
        return drives * self.drive_s_one_worker / (workers * eff) / 3600.0


def estimate_text(r: BatchBenchResult, drives: int = 10_000) -> str:
    parts = [f"{n} worker(s) {r.hours_for(drives, n):,.1f} h" for n in (1, 2, 16, 64)]
    cpu_h = drives * r.hours * 3600 / r.speedup_log_cpu / 3600 if r.speedup_log_cpu else float("nan")
    return (f"{drives:,} drives of {r.hours:g} h x {r.n_cells} cells: {drives * r.drive_s_one_worker / 3600:,.1f} "
            f"worker-hours of wall time here; " + ", ".join(parts) + f" (efficiency "
            f"{min(1.0, r.scaling_2_workers / 2):.2f} measured on 2 workers, assumed for more); {cpu_h:,.1f} "
            f"CPU-hours (on workers with a core each: {cpu_h / 16:,.1f} h on 16, {cpu_h / 64:,.1f} h on 64)"
            + (f"; stacked {r.stack} drives per task: {drives * r.hours / r.speedup_stack:,.1f} worker-hours of wall "
               f"time, {drives * r.hours / r.speedup_stack_cpu:,.1f} CPU-hours" if r.speedup_stack else ""))


def _frame_table(fa):
    """encode-log's FrameArrays as a FrameTable (for the MF4 writer)."""
    from bms_estimator.fleet.frames import EXTENDED_FLAG, FrameTable

    ids = fa.arbitration_id.astype(np.int64)
    extended = [i for i in np.unique(ids).tolist() if fa.extended.get(int(i), True)]
    key = np.where(np.isin(ids, extended), ids | EXTENDED_FLAG, ids)
    m = len(fa)
    data = fa.data.astype("<u8").view(np.uint8).reshape(m, 8)
    return FrameTable(fa.timestamps, key.astype(np.int64), np.full(m, 8, np.int16), data, np.zeros(m, bool))


def _write_inputs(tmp: Path, hours: float, n_cells: int) -> tuple[Path, Path, Path, int]:
    from benchmarks.replay_speedup import prepare_frames
    from bms_estimator.fleet.frames import write_mf4
    from bms_estimator.replay.encode_log import write_messages

    fa, _ocv, q, ocv_path = prepare_frames(hours, n_cells)
    log = tmp / "bench" / "drive.log"
    log.parent.mkdir(parents=True, exist_ok=True)
    write_messages(fa.iter_messages(), log)
    mf4 = write_mf4(_frame_table(fa), tmp / "bench" / "drive.mf4")
    cfg = tmp / "config.toml"
    cfg.write_text(f'[pack]\nn_cells = {n_cells}\ncapacity_ah = {q}\nocv_csv = "{ocv_path}"\n'
                   '[can]\ninterface = "virtual"\n[mqtt]\nenabled = false\n')
    return log, mf4, cfg, len(fa)


def _one_worker(path: Path, cfg: Path, sox: bool = False) -> tuple[float, dict[str, float]]:
    from bms_estimator.fleet.drive import run_drive

    res, _, _ = run_drive(path, str(cfg), path.parent, "bench", write=False, sox=sox)
    if res.status != "ok":
        raise RuntimeError(res.error)
    secs = {k: v for k, v in res.seconds.items() if k != "write"}
    wall = sum(v for k, v in secs.items() if k != "cpu")
    return res.duration_s / wall, secs


def _stacked(path: Path, cfg: Path, stack: int, sox: bool = False) -> tuple[float, float, dict[str, float]]:
    """(log seconds / wall seconds, log seconds / CPU seconds, summed stage seconds) of ``stack`` copies of
    ``path`` in one stacked task (:func:`~bms_estimator.fleet.drive.run_drives`, no Parquet; ``sox``: with
    the SOP/SOE/SOH part)."""
    from bms_estimator.fleet.drive import run_drives

    results = run_drives([(str(path), "bench")] * stack, str(cfg), path.parent, write=False, sox=sox)
    bad = [r.error for r in results if r.status != "ok"]
    if bad or any(r.counters.get("stacked_with") != stack for r in results):
        raise RuntimeError(bad[0] if bad else "the drives did not run stacked")
    secs: dict[str, float] = {}
    for r in results:
        for k, v in r.seconds.items():
            if k != "write":
                secs[k] = secs.get(k, 0.0) + v
    wall = sum(v for k, v in secs.items() if k != "cpu")
    log_s = sum(r.duration_s for r in results)
    return log_s / wall, log_s / secs["cpu"], secs


def _scaling(tmp: Path, cfg: Path, hours: float, n_cells: int, drives: int) -> tuple[float, float]:
    """Wall seconds of ``drives`` drives on 1 and on 2 worker processes (cluster start excluded)."""
    from dask.distributed import Client, LocalCluster

    from benchmarks.replay_speedup import prepare_frames
    from bms_estimator.fleet.batch import run_batch
    from bms_estimator.replay.encode_log import write_messages

    fa, *_ = prepare_frames(hours, n_cells)
    logs = []
    for i in range(drives):
        p = tmp / "scaling" / f"car{i}" / "drive.log"
        p.parent.mkdir(parents=True, exist_ok=True)
        if i == 0:
            write_messages(fa.iter_messages(), p)
        else:
            p.write_bytes(logs[0].read_bytes())
        logs.append(p)
    walls = []
    try:  # `bench` pins itself to one core; the workers of this figure get them all
        saved = os.sched_getaffinity(0)
        os.sched_setaffinity(0, set(range(os.cpu_count() or 1)))
    except (AttributeError, OSError):
        saved = None
    try:
        for n in (1, 2):
            with LocalCluster(n_workers=n, threads_per_worker=1, processes=True, host="127.0.0.1",
                              dashboard_address=None) as cluster, Client(cluster) as client:
                client.run(lambda: __import__("bms_estimator.fleet.drive"))  # imports outside the timing
                t0 = time.perf_counter()
                res = run_batch([str(p) for p in logs], str(cfg), tmp / f"out{n}", client=client)
                walls.append(time.perf_counter() - t0)
                if res.failed:
                    raise RuntimeError(res.failed[0].error)
    finally:
        if saved is not None:
            os.sched_setaffinity(0, saved)
    return walls[0], walls[1]


def _best_of(path: Path, cfg: Path, repeats: int, log_s: float) -> tuple[float, float, dict[str, float], float,
                                                                        list[tuple[float, float]]]:
    """(best wall figure, best CPU figure, the best wall run's stage seconds, the median run's wall
    seconds, every run's (wall, CPU) figure) of ``repeats`` runs of one drive."""
    runs = [_one_worker(path, cfg) for _ in range(max(1, repeats))]
    figures = [(sp, log_s / secs["cpu"]) for sp, secs in runs]
    best = max(range(len(runs)), key=lambda k: runs[k][0])
    median_wall_s = float(np.median([log_s / sp for sp, _ in runs]))
    return runs[best][0], max(c for _, c in figures), runs[best][1], median_wall_s, figures


def bench_batch(hours: float = 4.0, n_cells: int = 96, scaling_drives: int = 4,
                scaling_hours: float = 0.5, stack: int = 4, repeats: int = 3) -> BatchBenchResult:
    from bms_estimator.fleet.memory import keep_freed_memory

    key = (hours, n_cells, scaling_drives, scaling_hours, stack, repeats)
    if key in _CACHE:
        return _CACHE[key]
    keep_freed_memory()  # the allocator of a batch worker (its LocalCluster starts them so): a task's cost here
    with tempfile.TemporaryDirectory(prefix="bms-batch-bench-") as tmpdir:
        tmp = Path(tmpdir)
        log, mf4, cfg, frames = _write_inputs(tmp, hours, n_cells)
        _one_worker(log, cfg)  # warm: imports, the configuration's Service (cached per process)
        sp_log, cpu_log, s_log, median_log_s, runs_log = _best_of(log, cfg, repeats, hours * 3600)
        sp_mf4, cpu_mf4, s_mf4, _, runs_mf4 = _best_of(mf4, cfg, repeats, hours * 3600)
        sp_stack, sp_stack_cpu, s_stack = _stacked(log, cfg, stack)
        w1, w2 = _scaling(tmp, cfg, scaling_hours, n_cells, scaling_drives)
    r = BatchBenchResult(hours, n_cells, frames, sp_log, sp_mf4, s_log, s_mf4, w1 / w2, scaling_drives,
                         scaling_hours, w1, w2, median_log_s, cpu_log, cpu_mf4, stack, sp_stack, sp_stack_cpu,
                         s_stack, runs_log, runs_mf4)
    _CACHE[key] = r
    return r


@dataclass
class SoxBenchResult:
    hours: float
    n_cells: int
    speedup: float  # best wall figure without SOX (log seconds / wall seconds)
    speedup_cpu: float
    speedup_sox: float  # best wall figure with SOX
    speedup_sox_cpu: float
    estimate_s: float  # the estimate stage's seconds of the best run without SOX
    estimate_s_sox: float  # and with it
    runs: list[tuple[float, float]]  # (without, with) wall figure of every pair of runs
    stack: int = 4
    speedup_stack: float = 0.0  # one task of `stack` copies, stacked, without SOX (wall; CPU below)
    speedup_stack_cpu: float = 0.0
    speedup_stack_sox: float = 0.0  # and with SOX, right after it
    speedup_stack_sox_cpu: float = 0.0

    def as_dict(self) -> dict:
        return asdict(self)


def bench_batch_sox(hours: float = 4.0, n_cells: int = 96, repeats: int = 3, stack: int = 4) -> SoxBenchResult:
    """``batch --sox``'s cost on one drive (the ``.log`` of :func:`bench_batch`): pairs of runs, without
    SOX then with it, the best of ``repeats`` of each; then one task of ``stack`` copies stacked, without
    SOX then with it (no Parquet)."""
    from bms_estimator.fleet.memory import keep_freed_memory

    key = ("sox", hours, n_cells, repeats, stack)
    if key in _CACHE:
        return _CACHE[key]
    keep_freed_memory()
    with tempfile.TemporaryDirectory(prefix="bms-batch-sox-bench-") as tmpdir:
        log, _mf4, cfg, _frames = _write_inputs(Path(tmpdir), hours, n_cells)
        _one_worker(log, cfg, sox=True)  # warm
        pairs = [(_one_worker(log, cfg), _one_worker(log, cfg, sox=True)) for _ in range(max(1, repeats))]
        st_plain, st_sox = _stacked(log, cfg, stack), _stacked(log, cfg, stack, sox=True)
    log_s = hours * 3600.0
    plain = max((r for r, _ in pairs), key=lambda r: r[0])
    sox = max((r for _, r in pairs), key=lambda r: r[0])
    r = SoxBenchResult(hours, n_cells, plain[0], max(log_s / a[1]["cpu"] for a, _ in pairs), sox[0],
                       max(log_s / b[1]["cpu"] for _, b in pairs), plain[1]["estimate"], sox[1]["estimate"],
                       [(a[0], b[0]) for a, b in pairs], stack, st_plain[0], st_plain[1], st_sox[0], st_sox[1])
    _CACHE[key] = r
    return r


def bench_read_cost(hours: float = 0.1, n_cells: int = 96) -> dict[str, float]:
    """Microseconds per frame of :func:`~bms_estimator.fleet.frames.read_frames` by format (and python-can's
    candump reader, which the bulk .log parser replaces)."""
    import can

    from benchmarks.replay_speedup import prepare_frames
    from bms_estimator.fleet.frames import FrameTable, read_frames, write_mf4
    from bms_estimator.replay.encode_log import write_messages

    fa, *_ = prepare_frames(hours, n_cells)
    out: dict[str, float] = {}
    with tempfile.TemporaryDirectory(prefix="bms-read-bench-") as tmpdir:
        tmp = Path(tmpdir)
        paths = {}
        for suffix in (".log", ".asc", ".blf"):
            paths[suffix] = tmp / f"d{suffix}"
            write_messages(fa.iter_messages(), paths[suffix])
        paths[".mf4"] = write_mf4(_frame_table(fa), tmp / "d.mf4")
        for suffix, path in paths.items():
            t0 = time.perf_counter()
            read_frames(path)
            out[suffix] = (time.perf_counter() - t0) / len(fa) * 1e6
        t0 = time.perf_counter()
        FrameTable.from_messages(can.LogReader(str(paths[".log"])))
        out[".log python-can"] = (time.perf_counter() - t0) / len(fa) * 1e6
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--hours", type=float, default=4.0)
    ap.add_argument("--cells", type=int, default=96)
    ap.add_argument("--scaling-drives", type=int, default=4)
    ap.add_argument("--scaling-hours", type=float, default=0.5)
    ap.add_argument("--stack", type=int, default=4)
    ap.add_argument("--read-cost", action="store_true", help="only the per-frame read cost of each format")
    ap.add_argument("--sox", action="store_true", help="only the cost of batch --sox on one drive")
    a = ap.parse_args()
    if a.read_cost:
        print(json.dumps(bench_read_cost(), indent=1))
        return
    if a.sox:
        print(json.dumps(bench_batch_sox(a.hours, a.cells).as_dict(), indent=1))
        return
    r = bench_batch(a.hours, a.cells, a.scaling_drives, a.scaling_hours, a.stack)
    print(json.dumps(r.as_dict(), indent=1))
    print(estimate_text(r))


if __name__ == "__main__":
    main()
