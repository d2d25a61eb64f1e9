"""Many drives on Dask distributed: one task per few drives (stacked), or per vehicle when its drives are chained.

``run_batch`` submits :func:`~.drive.run_drive` (or :func:`~.drive.run_vehicle`) to a
``dask.distributed`` client: by default a ``LocalCluster`` of single-threaded worker
processes, one per core (``os.cpu_count()``; the estimator holds the GIL), started with
:data:`.memory.MALLOC_ENV` (freed memory kept for the next drive's arrays); with
``scheduler`` an existing cluster (then every worker must see the log files and the
output directory at the same paths: a shared file system). No other pool is made here.

Unchained drives go to the workers in groups of up to ``stack`` (fewer when there are
fewer drives than ``stack`` per worker), and a task runs its group's estimation stacked
(:func:`~.drive.run_drives`, :mod:`.stack`): the results are each drive's own, bit for
bit, the estimator's per-sample overhead shared. Chained drives stay one task per vehicle,
in order (each drive starts from the state the one before left).

Results do not depend on the number of workers: each task is a pure function of its
files (a drive's estimate depends only on its log, the configuration and, when chained,
the vehicle's earlier drives, which run in the same task, in order); the summary is
sorted by vehicle, drive and cell.

Vehicles: a log's vehicle is its parent directory's name (``fleet/<vehicle>/<drive>.log``).
"""

from __future__ import annotations

import gc
import glob
import logging
import os
import sys
from collections import defaultdict
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..errors import UsageError, one_line_error
from ..service.logging import configure_logging
from .drive import PACK_SUMMARY, SOX_SUMMARY, DriveResult, run_drives, run_vehicle
from .frames import FRAME_SUFFIXES
from .memory import MALLOC_ENV

__all__ = ["BatchResult", "DEFAULT_STACK", "PACK_SUMMARY_COLUMNS", "SOX_SUMMARY_COLUMNS", "expand_inputs",
           "run_batch", "stack_groups", "summary_columns", "summary_rows", "vehicle_of"]


def vehicle_of(path: str | Path) -> str:
    return Path(path).resolve().parent.name or "vehicle"


def expand_inputs(items: Iterable[str]) -> tuple[list[str], list[DriveResult]]:
    """Files named or matched (globs, ``**`` allowed; a directory = its logs, recursively; a file that exists is
    itself, whatever its name), and the skipped: what matched nothing, and a log whose results would overwrite an
    earlier one's (the same vehicle folder name and file name: :func:`~.drive.parquet_path`)."""
    found: list[str] = []
    seen: set[str] = set()
    owners: dict[tuple[str, str], str] = {}  # (vehicle, file name) -> the log whose Parquet that is
    skipped: list[DriveResult] = []
    for item in items:
        p = Path(item)
        if p.is_dir():
            hits = [str(f) for f in sorted(p.rglob("*")) if f.is_file() and _is_log(f)]
        elif not p.is_file() and any(ch in item for ch in "*?["):
            hits = [h for h in sorted(glob.glob(item, recursive=True)) if Path(h).is_file()]
        else:
            hits = [item]
        if not hits:
            skipped.append(DriveResult(vehicle=vehicle_of(item), path=item, status="skipped",
                                       error=f"{item}: matches no file"))
        for h in hits:
            real = str(Path(h).resolve())
            if real in seen:
                continue
            seen.add(real)
            vehicle, name = vehicle_of(h), Path(h).name
            owner = owners.setdefault((vehicle, name), h)
            if owner != h:
                skipped.append(DriveResult(vehicle=vehicle, path=h, status="skipped", error=(
                    f"{h}: drives/{vehicle}/{name}.parquet is already {owner}'s (a vehicle folder and a file of the "
                    "same names): rename one, or batch them separately")))
                continue
            found.append(h)
    return found, skipped


def _is_log(path: Path) -> bool:
    name = path.name.lower()
    if name.endswith(".gz"):
        name = name[:-3]
    return name.endswith(FRAME_SUFFIXES) or name.endswith(".csv")


#: unchained drives per task by default (estimated stacked; see bms_estimator/fleet/stack.py)
DEFAULT_STACK = 4


def stack_groups(logs: list[str], stack: int, workers: int) -> list[list[tuple[str, str]]]:
    """The logs as (log, vehicle) groups of at most ``stack``, and no more than keep every worker busy:
    ``min(stack, ceil(len(logs) / workers))`` each, in the given order."""
    if not logs:
        return []
    size = max(1, min(int(stack), -(-len(logs) // max(1, workers))))
    return [[(log, vehicle_of(log)) for log in logs[i:i + size]] for i in range(0, len(logs), size)]


@dataclass
class BatchResult:
    drives: list[DriveResult]
    workers: int
    scheduler: str
    notes: list[str] = field(default_factory=list)

    @property
    def failed(self) -> list[DriveResult]:
        return [d for d in self.drives if d.status != "ok"]


def scheduler_problem(address: str) -> str | None:
    """Why Dask cannot use ``address`` as a scheduler to reach, told before a ``Client`` is made (None: it
    may): a ``Client`` whose start fails is closed by its ``__del__`` whenever the garbage collector gets to
    it, which can be in the middle of the next ``Client``'s start, and there it deadlocks (seen in a test
    process that made three in a row).  An unreachable but well-formed address is still the ``Client``'s
    to find (an ``OSError`` after its timeout)."""
    import dask
    from distributed.comm.addressing import parse_address, parse_host_port

    try:
        scheme, location = parse_address(address)
    except ValueError as exc:
        return f"ValueError: {exc}"
    if scheme == "inproc":
        return "inproc:// is an address inside one process, not a scheduler to reach"
    if scheme not in ("tcp", "tls"):
        return f"the scheme {scheme}:// is not one batch reaches a scheduler by (tcp:// or tls://)"
    if scheme == "tls" and not dask.config.get("distributed.comm.tls.ca-file", None):
        return "tls:// without Dask's TLS settings (distributed.comm.tls.ca-file, .client.cert, .client.key)"
    try:
        parse_host_port(location)
    except ValueError as exc:
        return f"ValueError: {exc}"
    return None


def _client(scheduler: str | None, workers: int | None):
    import dask
    from dask.distributed import Client, LocalCluster

    # the scheduler and nannies of a local cluster run in this process: their INFO lines are not the user's
    logging.getLogger("distributed").setLevel(logging.ERROR)

    if scheduler:
        return Client(scheduler, timeout="10s"), None
    n = workers or os.cpu_count() or 1
    # worker processes that keep freed memory for the next drive's arrays (memory.py: values unaffected)
    environ = {**dask.config.get("distributed.nanny.pre-spawn-environ", {}), **MALLOC_ENV}
    # and that leave Ctrl-C to this process (worker_setup.py: they died of it, printing tracebacks)
    preload = [*dask.config.get("distributed.worker.preload", []), "bms_estimator.fleet.worker_setup"]
    with dask.config.set({"distributed.nanny.pre-spawn-environ": environ, "distributed.worker.preload": preload}):
        cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True, host="127.0.0.1",
                               dashboard_address=None, silence_logs=logging.ERROR)
    return Client(cluster), cluster


def run_batch(logs: list[str], config: str | None, out_dir: str | Path, *, chain: bool = False,
              scheduler: str | None = None, workers: int | None = None,
              progress: Callable[[int, int, DriveResult | None], None] | None = None,
              client: Any = None, diagnose: bool = False, stack: int = DEFAULT_STACK, sox: bool = False,
              ) -> BatchResult:
    """Every log through bulk decode and the estimator on Dask; never raises for a bad log.

    ``stack``: at most this many unchained drives per task, estimated side by side (1: one per task).
    ``sox``: also the service's SOP/SOE/SOH part (:mod:`.drive`), stacked with the estimator (its
    cells grouped per drive, :meth:`~bms_estimator.core.sox.SoxEstimator.set_groups`).

    ``progress(done_drives, total_drives, last_result)`` is called as tasks finish.
    ``client``: an existing ``dask.distributed.Client`` (then ``scheduler``/``workers`` are unused).
    """
    from dask.distributed import as_completed

    out_dir = str(Path(out_dir).resolve())
    logs = [str(Path(p).resolve()) for p in logs]
    by_vehicle: dict[str, list[str]] = defaultdict(list)
    for log in logs:
        by_vehicle[vehicle_of(log)].append(log)
    own = None
    own_client = client is None
    if client is None:
        problem = scheduler_problem(scheduler) if scheduler else None
        if problem is not None:
            raise UsageError(f"cannot reach the Dask scheduler {scheduler!r}: {problem} (an address is "
                             "tcp://host:port; tls:// needs Dask's TLS settings)")
        try:
            client, own = _client(scheduler, workers)
        except OSError as exc:
            # the half-made Client is closed by its __del__: let that run now, not inside a later Client's start
            # (scheduler_problem's docstring)
            gc.collect()
            raise UsageError(f"cannot reach the Dask scheduler {scheduler!r}: {exc}") from None
        except (ValueError, TypeError) as exc:  # an address Dask cannot use (tls:// without its TLS settings)
            if not scheduler:
                raise
            raise UsageError(f"cannot reach the Dask scheduler {scheduler!r}: {one_line_error(exc)} (an address is "
                             "tcp://host:port; tls:// needs Dask's TLS settings)") from None
    try:
        n_workers = len(client.scheduler_info().get("workers", {}))
        if chain:
            futures = [client.submit(_vehicle_task, sorted(paths), config, out_dir, vehicle, diagnose, sox,
                                     key=f"vehicle-{vehicle}-{i}", pure=False)
                       for i, (vehicle, paths) in enumerate(sorted(by_vehicle.items()))]
        else:
            futures = [client.submit(_drives_task, group, config, out_dir, diagnose, sox,
                                     key=f"drives-{i}-{Path(group[0][0]).name}", pure=False)
                       for i, group in enumerate(stack_groups(logs, stack, max(n_workers, 1)))]
        results: list[DriveResult] = []
        total = len(logs)
        if progress is not None:
            progress(0, total, None)
        for fut in as_completed(futures):
            try:
                got = fut.result()
            except Exception as exc:  # noqa: BLE001 - a worker died (out of memory, killed): report the task
                got = [DriveResult(vehicle="?", path=str(fut.key), status="skipped",
                                   error=f"task {fut.key} failed: {one_line_error(exc)}")]
            got = got if isinstance(got, list) else [got]
            for r in got:
                results.append(r)
                if progress is not None:
                    progress(len(results), total, r)
    finally:
        if own_client:
            client.close()
        if own is not None:
            own.close()
    results.sort(key=lambda r: (r.vehicle, r.path))
    return BatchResult(results, n_workers, scheduler or "LocalCluster")


def _quiet_worker() -> None:
    """In a Dask worker process: the library's log lines at WARNING and above, on stderr (stdout is the user's)."""
    try:
        from dask.distributed import get_worker

        get_worker()
    except (ImportError, ValueError):
        return  # not in a worker (a test calling the task directly): leave the caller's logging alone
    configure_logging(level="WARNING", fmt="console", stream=sys.stderr)


def _drives_task(group: list[tuple[str, str]], config: str | None, out_dir: str,
                 diagnose: bool = False, sox: bool = False) -> list[DriveResult]:
    _quiet_worker()
    return run_drives(group, config, out_dir, diagnose=diagnose, sox=sox)


def _vehicle_task(logs: list[str], config: str | None, out_dir: str, vehicle: str,
                  diagnose: bool = False, sox: bool = False) -> list[DriveResult]:
    _quiet_worker()
    return run_vehicle(logs, config, out_dir, vehicle, chain=True, diagnose=diagnose, sox=sox)


SUMMARY_COLUMNS = ("vehicle", "drive", "cell", "status", "samples", "soc_final", "capacity_ah_final",
                   "capacity_at_bound_final", "capacity_voltage_ah_final", "r0_ohm_final",
                   "r0_ohm_median", "temperature_c_mean", "soc_error_final_pct", "soc_rmse_pct", "cause", "backward_frames",
                   "decode_errors", "rested_s", "chain", "error")
#: with ``--sox`` (fleet/drive.py's SOX_SUMMARY per cell, then its PACK_SUMMARY per drive), after SUMMARY_COLUMNS
SOX_SUMMARY_COLUMNS = tuple(SOX_SUMMARY)
PACK_SUMMARY_COLUMNS = tuple(PACK_SUMMARY)


def summary_columns(sox: bool = False) -> tuple[str, ...]:
    return SUMMARY_COLUMNS + (SOX_SUMMARY_COLUMNS + PACK_SUMMARY_COLUMNS if sox else ())


def summary_rows(drives: list[DriveResult], sox: bool = False) -> list[dict[str, Any]]:
    """One row per drive and cell (one row per skipped drive, cell = -1, with its error); a cell without
    a valid sample in its drive has status ``no data``, not ``ok``. ``sox``: with the SOX columns
    (:data:`SOX_SUMMARY_COLUMNS`, and the drive's pack figures :data:`PACK_SUMMARY_COLUMNS`, the same on
    each of its cell rows; empty for a drive without them)."""
    columns = summary_columns(sox)
    rows: list[dict[str, Any]] = []
    for d in drives:
        base = {"vehicle": d.vehicle, "drive": Path(d.path).name, "status": d.status, "samples": d.samples,
                "backward_frames": d.counters.get("backward_frames", 0), "decode_errors": d.counters.get("errors", 0),
                "rested_s": d.rested_s, "chain": d.chain, "error": d.error, **d.pack}
        n = len(d.cells.get("soc_final", []))
        if d.status != "ok" or n == 0:
            rows.append({**base, "cell": -1})
            continue
        valid = d.cells.get("valid_samples")
        for c in range(n):
            row = {**base, "cell": c}
            for key in columns:
                if key in d.cells:
                    row[key] = d.cells[key][c]
            if valid is not None and valid[c] == 0:  # a cell the log never carried: not an estimate
                row["status"] = "no data"
                row["error"] = _no_data_reason(d, c, n)
            rows.append(row)
    return [{k: r.get(k) for k in columns} for r in rows]


def _no_data_reason(d: DriveResult, cell: int, n: int) -> str:
    """Why ``cell`` has no valid sample in drive ``d`` of ``n`` cells: no valid current at all (every cell's
    samples need one), else the cell never came (the configuration's pack larger than the logged one)."""
    samples = d.counters.get("samples", 0)
    if samples and d.counters.get("current_invalid_samples", 0) >= samples:
        return (f"no sample of the log has a valid current ({samples} without one: its current message missing, "
                "or flagged invalid?)")
    return f"no valid sample of cell {cell} in the log (pack.n_cells {n}: more cells than the log's pack?)"
