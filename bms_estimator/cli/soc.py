"""``bms-estimator soc``: SOC from a wrong start, against coulomb counting from full (the paper's Fig. 10)."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..analysis import measured_capacity, reference_soc, run_soc, soc_errors
from ..core.identifier import IdentifierConfig
from .common import add_cell_options, add_method_option, add_tuning_options, load, load_ocv, soc_config, write_json


def add_parser(sub) -> None:
    p = sub.add_parser("soc", help="estimate SOC from a wrong initial SOC and score it against the reference",
                       description="Runs the online SOC estimator (LIF identification, c0 compensation, capacity "
                                   "estimation) from initial SOC = reference start - error. The reference SOC is "
                                   "coulomb counting from the known start (full) with the reference capacity: the "
                                   "one measured from the file's end-of-test rest when it ends relaxed, else the output-"
                                   "error capacity of the model fitted from the known start (never the stated one), "
                                   "unless --reference-capacity-ah is given.")
    p.add_argument("data", type=Path, help="drive-cycle CSV(.gz) in the ../shared/data layout")
    add_cell_options(p)
    p.add_argument("--initial-soc-error", type=float, default=0.2,
                   help="estimator starts at reference start - this (default 0.2 = 20 %% low)")
    p.add_argument("--reference-capacity-ah", type=float, default=None, help="capacity of the reference SOC")
    add_method_option(p, IdentifierConfig().method, "(the SOC estimator's identification)")
    p.add_argument("--json", type=Path, default=None, help="write the figures as JSON here ('-' = stdout)")
    p.add_argument("--plot", type=Path, default=None, help="write the SOC figure (PNG) here")
    add_tuning_options(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    rec = load(args.data, args)
    ocv = load_ocv(args.ocv)
    dt = rec.dt_s
    if args.reference_capacity_ah is not None:
        q_ref, source = float(args.reference_capacity_ah), "given"
    else:
        q_ref, source = measured_capacity(rec.current_a, rec.voltage_v, dt, ocv, args.capacity_ah, args.initial_soc)
    soc_ref = reference_soc(rec.current_a, dt, q_ref, args.initial_soc)
    start = min(max(args.initial_soc - args.initial_soc_error, 0.0), 1.0)
    run_ = run_soc(rec.current_a, rec.voltage_v, ocv, args.capacity_ah, start, dt, soc_config(args))
    out = soc_errors(run_.soc, soc_ref, rec.time_s - rec.time_s[0])
    out.update(
        capacity_ah_estimated=float(run_.capacity_ah[-1]),
        capacity_ah_stated=args.capacity_ah,
        capacity_ah_reference=q_ref,
        reference_capacity_source=source,
        initial_soc_estimate=start,
        soc_corrections=run_.corrections,
        estimator_rejections=run_.rejections,
        samples=len(rec),
    )
    if args.plot:
        from ..plots import plot_soc

        plot_soc(rec.time_s, run_.soc, soc_ref, run_.capacity_ah, args.plot,
                 f"{args.data.name}: SOC from {args.initial_soc_error*100:.0f} % initial error")
    if args.json is not None:
        write_json(out, args.json)
    if args.json is None or str(args.json) != "-":
        print(f"SOC RMSE {out['soc_rmse_pct']:.2f} % (after 1 h {out['soc_rmse_pct_after_3600s']:.2f} %, "
              f"max {out['soc_max_abs_error_pct_after_3600s']:.2f} %); capacity estimated "
              f"{out['capacity_ah_estimated']:.3f} Ah (stated {args.capacity_ah:g}, reference {q_ref:.3f} from {source})")
    return 0
