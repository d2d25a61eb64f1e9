"""``bms-estimator encode-log``: a measured single-cell CSV -> the CAN log of an n-cell pack."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from .common import RECORDING_HELP, positive_float, soc_fraction
from .outputs import check_outputs, file_output


def add_parser(sub) -> None:
    p = sub.add_parser(
        "encode-log",
        help="turn a measured cell recording into the CAN traffic of an n-cell pack (.log/.asc/.blf)",
        description="Encodes the recording with the project DBC at the DBC's rates (current 10 ms, cell voltages "
                    "100 ms, temperatures 1 s). Cell 0 carries the measured voltage; the other cells are simulated "
                    "from the model identified on the data with a seeded cell-to-cell spread plus the measured "
                    "residual. The injected truth goes to OUT.truth.json. Details: "
                    "bms_estimator/replay/encode_log.py.",
    )
    p.add_argument("data", type=Path, help=RECORDING_HELP)
    p.add_argument("--cells", type=int, required=True, help="cells in series (1..2000)")
    p.add_argument("-o", "--output", type=Path, required=True,
                   help="output log; the suffix picks the format: .log (candump), .asc (Vector ASCII), .blf (Vector binary)")
    p.add_argument("--ocv", type=Path, default=None,
                   help="OCV CSV (default: the shipped table of the cell named in DATA's path)")
    p.add_argument("--capacity-ah", type=positive_float, default=None,
                   help="stated capacity (default: the nominal capacity of the cell named in DATA's path)")
    p.add_argument("--reference-capacity-ah", type=positive_float, default=None,
                   help="capacity of the reference SOC path (default: measured from the file's end-of-test rest, "
                        "else the online SOC estimator's)")
    p.add_argument("--initial-soc", type=soc_fraction, default=1.0, help="SOC at the file's start (default 1.0)")
    p.add_argument("--seed", type=int, default=0, help="seed of the cell-to-cell spread (default 0)")
    p.add_argument("--spread", default=None,
                   help="1-sigma spread: a factor on the defaults ('0' = identical cells, '2' = twice the defaults) "
                        "or key=value,... with keys capacity, r0, r1, tau1, r2, tau2, soc0, rc (= r1,tau1,r2,tau2); "
                        "defaults capacity=0.02,r0=0.05,rc=0.05,soc0=0")
    p.add_argument("--duration-s", type=positive_float, default=None,
                   help="encode only the first S seconds (the model is still identified on the whole file)")
    p.add_argument("--t0", type=float, default=0.0,
                   help="log time of the first frame, s (default 0: .log, .asc and .blf then read back alike)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ..replay.encode_log import check_cells, encode_log, parse_spread

    check_cells(args.cells)  # before the file and the OCV table are read (it was said after them)
    check_outputs([("DATA", args.data), ("--ocv", args.ocv)],
                  [file_output("-o/--output", args.output, "{name}.truth.json")])
    spread = parse_spread(args.spread)
    show = sys.stderr.isatty() and not args.no_progress
    progress = None
    bar = None
    if show:
        from rich.console import Console
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

        bar = Progress(TextColumn("encode-log {task.description}"), BarColumn(), MofNCompleteColumn(),
                       TimeRemainingColumn(), console=Console(stderr=True), transient=True)
        task = bar.add_task(args.output.name, total=None)

        def advance(done: int, total: int) -> None:
            bar.update(task, completed=done, total=total)

        progress = advance

        bar.start()
    try:
        res = encode_log(
            args.data, args.output, args.cells, ocv=args.ocv, capacity_ah=args.capacity_ah, seed=args.seed,
            spread=spread, initial_soc=args.initial_soc, reference_capacity_ah=args.reference_capacity_ah,
            duration_s=args.duration_s, t0_s=args.t0, progress=progress,
        )
    finally:
        if bar is not None:
            bar.stop()
    ref = res.truth["reference"]
    cells = res.truth["cells"]
    caps = [c["capacity_ah"] for c in cells]
    r0 = [c["r0_factor"] for c in cells]
    print(f"{res.path}: {res.frames} frames, {res.duration_s:.0f} s, {args.cells} cells "
          f"(reference capacity {ref['capacity_ah']:.3f} Ah from {ref['capacity_source']}; "
          f"model RMSE {ref['model_rmse_mv']:.1f} mV, residual added to cells 1..)")
    print(f"cell spread (seed {args.seed}): capacity {min(caps):.3f}..{max(caps):.3f} Ah, "
          f"R0 factor {min(r0):.3f}..{max(r0):.3f}; truth in {res.truth_path}")
    return 0
