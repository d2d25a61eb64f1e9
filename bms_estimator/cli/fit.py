"""``bms-estimator fit``: identify the 2-RC model online over one recording."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from ..analysis import (
    IDENTIFICATION_METHOD, one_step_ahead, output_error_capacity, reference_soc, rmse_mv, run_identification,
    simulate_with_params, soc_lookup_table,
)
from .common import (RECORDING_HELP, add_c0_prior_option, add_cell_options, add_method_option, add_tuning_options, load, load_ocv,
                     soc_config, warn_if_capacity_at_search_end, warn_if_nothing_identified, warn_if_count_does_not_close, warn_if_start_is_not_initial_soc,
                     write_json)
from .outputs import check_outputs, figure_output, file_output

#: the second figure --plot writes, beside the first
SIMULATION_FIGURE = "{stem}_simulation.png"


def mohm(r_ohm: float) -> str:
    """A resistance in mOhm with at least three significant digits (and at least one decimal): a 57 Ah
    cell's R1 of 0.325 mOhm printed "0.3" with one fixed decimal, 8 % off, and a 0.04 mOhm one "0.0";
    an 18650's 20.3 and 6.5 mOhm print as before, 20.3 and 6.47."""
    v = float(r_ohm) * 1e3
    if not np.isfinite(v) or v == 0.0:
        return f"{v:.1f}"
    return f"{v:.{max(1, 2 - int(np.floor(np.log10(abs(v)))))}f}"


def add_parser(sub) -> None:
    p = sub.add_parser("fit", help="identify R0/R1/C1/R2/C2/c0 online over a recording",
                       description="Estimates the effective capacity as the output-error capacity of the model "
                                   "along the coulomb-counted SOC path from the known start, then runs the chosen "
                                   "identifier along that path (with the known-SOC c0 prior, --c0-prior) and "
                                   "simulates the file with the identified parameter trajectory.")
    p.add_argument("data", type=Path, help=RECORDING_HELP)
    add_cell_options(p)
    add_method_option(p, IDENTIFICATION_METHOD)
    p.add_argument("--json", type=Path, default=None)
    p.add_argument("--plot", type=Path, default=None, help="PNG of the parameter trajectories and the errors")
    add_c0_prior_option(p)
    add_tuning_options(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    check_outputs([("DATA", args.data), ("--ocv", args.ocv)],
                  [file_output("--json", args.json, stdout=True),
                   figure_output("--plot", args.plot, SIMULATION_FIGURE)])
    rec = load(args.data, args)
    ocv = load_ocv(args.ocv, rec, capacity_ah=args.capacity_ah)
    warn_if_start_is_not_initial_soc(rec, ocv, args)
    warn_if_count_does_not_close(rec, ocv, args)
    ident = soc_config(args).identifier.with_(c0_prior_weight=args.c0_prior)
    dt = rec.dt_s
    q_eff, profile = output_error_capacity(rec.current_a, rec.voltage_v, ocv, args.capacity_ah, args.initial_soc, dt,
                                           ident)
    warn_if_capacity_at_search_end(q_eff, profile["capacity_ah"], rec.source, args.capacity_ah)
    soc = reference_soc(rec.current_a, dt, q_eff, args.initial_soc)
    run_ = run_identification(rec.current_a, rec.voltage_v, soc, ocv, args.capacity_ah, dt, ident)
    prior_only = bool(warn_if_nothing_identified({args.method: run_.identified}, rec))
    sim = simulate_with_params(rec.current_a, soc, ocv, run_.params, dt)
    osa = one_step_ahead(rec.current_a, rec.voltage_v, soc, ocv, run_.params, dt)
    inside = (soc >= 0.2) & (soc <= 0.9)
    mid = run_.identified & inside
    out = {
        "method": args.method,
        "capacity_ah_estimated": q_eff,
        "final": {k: float(v[-1]) for k, v in run_.params.items()},
        "median_soc_20_90": {k: float(np.median(v[mid])) if mid.any() else None for k, v in run_.params.items()},
        "sim_rmse_mv": rmse_mv(sim, rec.voltage_v, inside),
        "osa_rmse_mv": rmse_mv(osa, rec.voltage_v, inside),
        "sim_rmse_mv_full_range": rmse_mv(sim, rec.voltage_v),
        "rejections": run_.rejections,
        "soc_table": soc_lookup_table(run_),
    }
    if args.plot:
        from ..plots import plot_errors, plot_parameters

        base = Path(args.plot)
        plot_parameters(rec.time_s, {args.method: run_.params}, base, f"{args.data.name}: online parameters")
        simulation = base.with_name(SIMULATION_FIGURE.format(stem=base.stem))
        plot_errors(rec.time_s, rec.voltage_v, {args.method: sim}, simulation,
                    f"{args.data.name}: simulation", "simulation error [mV]", inside)
    if args.json is not None:
        write_json(out, args.json)
    if args.json is None or str(args.json) != "-":
        f, where = out["median_soc_20_90"], "median over 20-90 % SOC"
        if prior_only:  # (it said the prior's were final values, for want of an identified sample in 20-90 %)
            f, where = out["final"], "nothing identified: the identifier's prior"
        elif f["r0_ohm"] is None:  # (it printed no parameters and 'simulation RMSE nan mV')
            f, where = out["final"], (f"final values: the counted SOC, {soc.min():.2f}..{soc.max():.2f}, has no "
                                      "identified sample in 20-90 %")
        print(f"{args.method.upper()}: R0 {mohm(f['r0_ohm'])} mOhm, R1 {mohm(f['r1_ohm'])} mOhm tau1 "
              f"{f['tau1_s']:.1f} s, R2 {mohm(f['r2_ohm'])} mOhm tau2 {f['tau2_s']:.0f} s ({where})")
        if f.get("k1_ohm") is not None:
            print(f"kinetic term: K1 {mohm(f['k1_ohm'])}, K2 {mohm(f['k2_ohm'])} mOhm "
                  f"at i0 {f['i0_a']:.2f} A (a resistance R_j - K_j (1 - asinh(i/i0) / (i/i0)))")
        if f.get("ct_vt_v") is not None:
            print(f"charge-transfer fast branch: {f['ct_fraction']*100:.0f} % of R1 at V_T {f['ct_vt_v']*1e3:.1f} mV "
                  f"(its overpotential V_T asinh(i f R1 / V_T))")
        sim_mv, osa_mv, over = out["sim_rmse_mv"], out["osa_rmse_mv"], ""
        if not inside.any():
            sim_mv, osa_mv, over = out["sim_rmse_mv_full_range"], rmse_mv(osa, rec.voltage_v), " over the whole file"
        print(f"simulation RMSE {sim_mv:.1f} mV, one-step-ahead {osa_mv:.1f} mV{over}; "
              f"capacity {q_eff:.3f} Ah; {run_.rejections} non-physical updates rejected")
    return 0
