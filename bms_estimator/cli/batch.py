"""``bms-estimator batch``: recorded logs of many drives -> per-drive Parquet and a summary, on Dask."""

from __future__ import annotations

import argparse
import csv
import math
import sys
import time
from pathlib import Path

from ..errors import DataError, UsageError
from ..fleet.batch import DEFAULT_STACK
from ..fleet.memory import MALLOC_ENV
from .outputs import check_outputs, folder_output

#: what a batch writes at the top of --out, beside drives/<vehicle>/*.parquet
SUMMARY_FILES = ("summary.csv", "summary.parquet", "errors.csv")


def _workers(text: str) -> int:
    try:
        n = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
    if n < 1:
        raise argparse.ArgumentTypeError(f"{text!r} must be >= 1")
    return n


def add_parser(sub) -> None:
    p = sub.add_parser(
        "batch",
        help="re-estimate recorded drives in bulk on Dask: per-drive Parquet of per-cell SOC and parameters, a summary",
        description="Each log (.log, .asc, .blf, optionally .gz, or .mf4) is decoded in bulk with the configuration's "
                    "DBC and mapping into the service's 1 s samples and run through the service's estimator; the "
                    "results equal a replay through the service. A log's vehicle is its directory's name. Writes "
                    "OUT/drives/<vehicle>/<log>.parquet (per cell and sample: soc, r0_ohm, r1_ohm, c1_f, r2_ohm, "
                    "c2_f, tau1_s, tau2_s, c0_v, capacity_ah, temperature_c, voltage_v, valid). A single-cell recording "
                    "(.csv/.csv.gz, time_s,current_a,voltage_v[,temperature_c]) is a one-cell drive. OUT/summary.csv and "
                    ".parquet (per vehicle, drive and cell) and OUT/errors.csv (every skipped log and why). A corrupt, "
                    "empty, foreign-DBC or rewinding log is reported and skipped. The summary's "
                    "capacity_at_bound_final is -1 / +1 where a cell's capacity estimate ended at its low / high "
                    "bound (estimator.core.capacity_bounds x pack.capacity_ah, 0.6 / 1.4 by default): the stated capacity is wrong for that cell and its SOC "
                    "unreliable; the last line counts them. capacity_voltage_ah_final: on the c0 SOC method, the "
                    "capacity its voltage line reads (empty: none yet, or ekf). Details: bms_estimator/fleet/.",
    )
    p.add_argument("logs", nargs="+", metavar="LOG_OR_GLOB",
                   help="log files, globs (quote them; ** recurses) or directories (their logs, recursively)")
    p.add_argument("--config", required=True, type=Path, help="the service's configuration (TOML): pack, CAN DBC and "
                   "mapping, estimator settings")
    p.add_argument("--out", required=True, type=Path, help="output directory (created)")
    p.add_argument("--chain", action="store_true",
                   help="chain each vehicle's drives in time order (first timestamp, then name), the estimator "
                        "state carried from one to the next; one task per vehicle")
    p.add_argument("--scheduler", default=None, metavar="ADDR",
                   help="Dask scheduler address (tcp://host:8786); default: a local cluster, one worker process per core "
                        "(start a cluster's workers with " + " ".join(f"{k}={v}" for k, v in MALLOC_ENV.items())
                        + ", as the local one does: see README, Fleet re-estimation)")
    p.add_argument("--workers", type=_workers, default=None, help="local cluster size (default: the machine's cores)")
    p.add_argument("--diagnose", action="store_true",
                   help="also name each cell's model error with 'diagnose' (summary column 'cause'; on the cell's "
                        "longest stretch of valid samples, at least 30 min; slow: seconds per cell-hour)")
    p.add_argument("--sox", action="store_true",
                   help="also the service's power limits, energy and health (SOP/SOE/SOH, as it publishes them per "
                        "cell): the Parquet gets every per-cell SOX output (i_discharge_max_10s_a, energy_left_wh, "
                        "soh_capacity, soh_resistance, ...), the summary per cell soh_capacity_final (with "
                        "soh_capacity_sigma_final), soh_resistance_final, energy_left_wh_final and the drive's "
                        "energy_discharged_wh and energy_charged_wh; the pack figures the service publishes (its pack "
                        "payload's keys) per sample in OUT/drives/<vehicle>/<log>.pack.parquet, and per drive the "
                        "summary columns pack_energy_left_wh_final, pack_soh_capacity_min_final, "
                        "pack_soh_resistance_max_final, pack_i_discharge_max_10s_a_min, "
                        "pack_p_discharge_max_10s_w_min, pack_energy_discharged_wh, pack_energy_charged_wh; "
                        "with --chain the SOX state is carried like the "
                        "SOC's. Its drives are stacked like the others (--stack; the SOX part kept per drive, "
                        "each drive's figures its own, bit for bit, one-cell drives too); "
                        "see README, Fleet re-estimation, for its cost")
    p.add_argument("--stack", type=_workers, default=DEFAULT_STACK, metavar="S",
                   help="unchained drives per task, estimated side by side as one vectorised estimator (each drive's "
                        f"results are its own, bit for bit; it shares the per-sample overhead; default {DEFAULT_STACK}, "
                        "1 = one drive per task)")
    p.add_argument("--overwrite", action="store_true",
                   help="--out may hold an earlier batch's results: delete them first (its summary.csv, "
                        "summary.parquet, errors.csv and the Parquet files under drives/); without it such an --out "
                        "is refused")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def _earlier_results(out: Path) -> list[Path]:
    """The files of an earlier batch in ``out``: its summary and error list, and its drives' Parquet."""
    found = [out / name for name in SUMMARY_FILES if (out / name).is_file()]
    drives = out / "drives"
    if drives.is_dir():
        found += sorted(p for p in drives.rglob("*") if p.is_file() and p.name.endswith((".parquet", ".parquet.tmp")))
    return found


def _clear_out(out: Path, overwrite: bool) -> None:
    """Refuse an ``out`` that holds an earlier batch's results, or (``overwrite``) delete them.

    A batch into such a folder rewrote summary.csv for its own drives and left the earlier batch's Parquet
    of other drives beside it, as if they were its own."""
    earlier = _earlier_results(out)
    if not earlier:
        return
    if not overwrite:
        shown = ", ".join(str(p.relative_to(out)) for p in earlier[:3]) + (", ..." if len(earlier) > 3 else "")
        raise UsageError(f"--out {out}: holds an earlier batch's results ({len(earlier)} files: {shown}), which this "
                         "batch's would be mixed with: choose an empty directory, or give --overwrite to delete them")
    for path in earlier:
        path.unlink()
    drives = out / "drives"
    if drives.is_dir():  # the vehicle folders left empty (anything else in them is not the batch's: kept)
        for folder in sorted((p for p in drives.rglob("*") if p.is_dir()), key=lambda p: len(p.parts), reverse=True):
            if not any(folder.iterdir()):
                folder.rmdir()


def _check_config(path: Path) -> None:
    """Everything the service would refuse, refused here before any worker starts (exit 2/3)."""
    from ..fleet.drive import service_for

    if not path.is_file():
        raise UsageError(f"--config {path}: no such file")
    service_for(str(path))


def _write_csv(path: Path, rows: list[dict], columns) -> None:
    with path.open("w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(columns))
        w.writeheader()
        w.writerows(rows)


def run(args: argparse.Namespace) -> int:
    from ..fleet.batch import expand_inputs, run_batch, summary_columns, summary_rows

    if args.scheduler and args.workers:
        raise UsageError("--workers sizes the local cluster; with --scheduler the cluster has its own workers")
    _check_config(args.config)
    logs, skipped = expand_inputs(args.logs)
    check_outputs([("--config", args.config), ("LOG_OR_GLOB", logs)],
                  [folder_output("--out", args.out, *SUMMARY_FILES)])
    try:
        args.out.mkdir(exist_ok=True)
    except OSError as exc:
        raise UsageError(f"--out {args.out}: cannot create it: {exc.strerror or exc}") from None
    _clear_out(args.out, args.overwrite)
    show = sys.stderr.isatty() and not args.no_progress
    bar = task = None
    if show:
        from rich.console import Console
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

        bar = Progress(TextColumn("batch {task.description}"), BarColumn(), MofNCompleteColumn(),
                       TimeRemainingColumn(), console=Console(stderr=True), transient=True)
        task = bar.add_task("drives", total=len(logs))
        bar.start()

    def progress(done: int, total: int, last) -> None:
        if bar is not None:
            bar.update(task, completed=done, total=total,
                       description=f"{last.vehicle}/{Path(last.path).name}" if last is not None else "drives")

    t0 = time.perf_counter()
    try:
        result = run_batch(logs, str(args.config.resolve()), args.out, chain=args.chain, scheduler=args.scheduler,
                           workers=args.workers, progress=progress, diagnose=args.diagnose,
                           stack=args.stack, sox=args.sox) if logs else None
    finally:
        if bar is not None:
            bar.stop()
    wall = time.perf_counter() - t0
    drives = (result.drives if result is not None else []) + skipped
    rows = summary_rows(drives, sox=args.sox)
    _write_csv(args.out / "summary.csv", rows, summary_columns(args.sox))
    import pyarrow as pa
    import pyarrow.parquet as pq

    pq.write_table(pa.Table.from_pylist(rows), args.out / "summary.parquet")
    failed = [d for d in drives if d.status != "ok"]
    _write_csv(args.out / "errors.csv", [{"vehicle": d.vehicle, "log": d.path, "error": d.error} for d in failed],
               ("vehicle", "log", "error"))
    ok = [d for d in drives if d.status == "ok"]
    hours = sum(d.duration_s for d in ok) / 3600.0
    workers = result.workers if result is not None else 0
    no_data = [r for r in rows if r["status"] == "no data"]
    print(f"batch: {len(ok)} of {len(drives)} drives estimated ({hours:.2f} h of logs, "
          f"{sum(len(d.cells.get('soc_final', [])) for d in ok) - len(no_data)} cell-drives) in {wall:.1f} s on "
          f"{workers} worker(s): {hours * 3600 / wall if wall > 0 else 0:.0f}x real time; {args.out}/summary.csv")
    for d in failed:
        print(f"  skipped: {d.error}")
    if no_data:
        print(f"  {len(no_data)} cell-drive(s) without a valid sample (status 'no data' in summary.csv), e.g. "
              f"{no_data[0]['drive']}: {no_data[0]['error']}")
    at_bound = [r for r in rows if r["status"] == "ok" and r.get("capacity_at_bound_final")]
    if at_bound:
        q_v = at_bound[0].get("capacity_voltage_ah_final")  # the c0 method's voltage line: what the voltage says
        says = f", its voltage saying {q_v:.3f} Ah" if q_v is not None and math.isfinite(q_v) else ""
        print(f"  warning: {len(at_bound)} cell-drive(s) ended with the capacity estimate at a bound "
              f"(capacity_at_bound_final in summary.csv), e.g. {at_bound[0]['drive']} cell {at_bound[0]['cell']} at "
              f"{at_bound[0]['capacity_ah_final']:.3f} Ah{says}: the stated pack.capacity_ah is likely wrong for these "
              "cells and their SOC unreliable")
    if not ok:
        raise DataError("no drive could be estimated:", [d.error for d in failed] or ["no input"])
    return 0
