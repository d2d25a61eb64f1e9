"""``bms-estimator compare``: CT (LIF, LS and IV) against DT (ARX) on a training and a validation file (paper IV-A)."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..analysis import DEFAULT_METHODS, compare_methods
from ..core.arrhenius import RESISTANCE_ACTIVATION_K
from ..core.identifier import METHODS
from ..errors import UsageError
from .common import (RECORDING_HELP, METHOD_HELP, add_c0_prior_option, add_cell_options, add_tuning_options, load, load_ocv,
                     non_negative_float, soc_config, warn_if_capacity_at_search_end, warn_if_nothing_identified,
                     warn_if_count_does_not_close, warn_if_start_is_not_initial_soc,
                     write_json)
from .outputs import check_outputs, file_output, folder_output

#: the figures --plots writes in its folder
PLOTS = ("parameters_train.png", "osa_train.png", "simulation_train.png", "osa_validate.png",
         "simulation_validate.png")


def add_parser(sub) -> None:
    p = sub.add_parser("compare", help="the paper's Section IV-A: CT vs DT identification on any two files",
                       description="The SOC path of both files is coulomb counting from the known start with the "
                                   "training file's output-error capacity (of the first method's model). Every method "
                                   "runs online over the training file; its parameters simulate the "
                                   "training file (online trajectory) and the validation file (training parameters "
                                   "looked up by SOC). RMSEs cover the 20-90 % SOC part unless --full-range.")
    p.add_argument("--train", type=Path, required=True, help=f"the recording to identify on: {RECORDING_HELP}")
    p.add_argument("--validate", type=Path, required=True, help=f"the recording to score on: {RECORDING_HELP}")
    add_cell_options(p)
    p.add_argument("--soc-min", type=float, default=0.2, help="lower end of the scored SOC window (default 0.2)")
    p.add_argument("--soc-max", type=float, default=0.9, help="upper end of the scored SOC window (default 0.9)")
    p.add_argument("--full-range", action="store_true", help="score the whole file (both are reported anyway)")
    p.add_argument("--method", dest="methods", action="append", choices=METHODS, default=None,
                   help=f"{METHOD_HELP}; repeat to compare several, the first one's model sets the effective "
                        f"capacity (default: {' '.join(DEFAULT_METHODS)})")
    p.add_argument("--activation-k", type=non_negative_float, default=RESISTANCE_ACTIVATION_K,
                   help="E_a/R [K] bringing the training resistances to the validation file's cell temperature "
                        "(temperature_c of both files; 0 = no correction; default %(default)g, the measured "
                        "cells' Arrhenius line)")
    p.add_argument("--json", type=Path, default=None)
    p.add_argument("--plots", type=Path, default=None, help="folder for the figures (paper Figs 5-9)")
    add_c0_prior_option(p)
    add_tuning_options(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    check_outputs([("--train", args.train), ("--validate", args.validate), ("--ocv", args.ocv)],
                  [file_output("--json", args.json, stdout=True), folder_output("--plots", args.plots, *PLOTS)])
    tr, va = load(args.train, args), load(args.validate, args)
    if abs(tr.dt_s - va.dt_s) > 1e-9:  # (it named neither file nor the way out)
        raise UsageError(f"--train {args.train} is sampled every {tr.dt_s:g} s, --validate {args.validate} every "
                         f"{va.dt_s:g} s: give --resample-s {max(tr.dt_s, va.dt_s):g} to average both to one period")
    ocv = load_ocv(args.ocv, tr, capacity_ah=args.capacity_ah)
    for rec in (tr, va):
        warn_if_start_is_not_initial_soc(rec, ocv, args)
        warn_if_count_does_not_close(rec, ocv, args)
    window = (0.0, 1.0) if args.full_range else (args.soc_min, args.soc_max)
    if not 0.0 <= window[0] < window[1] <= 1.0:
        raise ValueError(f"SOC window {window} must satisfy 0 <= min < max <= 1")
    res = compare_methods(
        (tr.current_a, tr.voltage_v), (va.current_a, va.voltage_v), ocv, args.capacity_ah,
        dt_s=tr.dt_s, initial_soc=args.initial_soc, soc_window=window, config=soc_config(args),
        names=(args.train.name, args.validate.name), c0_prior_weight=args.c0_prior,
        methods=tuple(dict.fromkeys(args.methods or DEFAULT_METHODS)),
        temperatures_c=(tr.temperature_c, va.temperature_c), activation_k=args.activation_k,
    )
    m = res.metrics
    prior_only = warn_if_nothing_identified({method: run_.identified for method, run_ in res.runs.items()}, tr)
    for method in res.runs:
        m["train"][method]["identified"] = method not in prior_only
    warn_if_capacity_at_search_end(res.capacity_ah, m["capacity_profile"]["capacity_ah"], tr.source, args.capacity_ah)
    m["files"] = {"train": str(args.train), "validate": str(args.validate)}
    if args.plots:
        _plots(res, tr, va, args.plots, window)
        m["plots"] = str(args.plots)
    if args.json is not None:
        write_json(m, args.json)
    if args.json is None or str(args.json) != "-":
        print(f"effective capacity {res.capacity_ah:.3f} Ah (stated {args.capacity_ah:g}); "
              f"RMSE in SOC {window[0]:.0%}-{window[1]:.0%}, simulation / one-step-ahead [mV]:")
        for part in ("train", "validate"):
            figs, note = m[part], ""
            if all(f["sim_rmse_mv"] != f["sim_rmse_mv"] for f in figs.values()):  # NaN: no sample in the window
                figs, note = m["full_range"][part], "  (whole file: its counted SOC never enters the window)"
            row = "  ".join(f"{meth.upper()} {f['sim_rmse_mv']:6.1f} / {f['osa_rmse_mv']:5.1f}"
                            for meth, f in figs.items())
            print(f"  {part:9s} {row}{note}")
    return 0


def _plots(res, tr, va, folder: Path, window) -> None:
    from ..plots import plot_errors, plot_parameters

    folder.mkdir(exist_ok=True)  # (its parent checked before the run: check_outputs)
    plot_parameters(tr.time_s, res.train.params, folder / "parameters_train.png", f"{res.train.name}: online parameters")
    for part, rec in (("train", res.train), ("validate", res.validate)):
        t = (tr if part == "train" else va).time_s
        inside = (rec.soc >= window[0]) & (rec.soc <= window[1])
        plot_errors(t, rec.voltage_v, rec.osa_v, folder / f"osa_{part}.png", f"{rec.name}: one-step-ahead error",
                    "OSA error [mV]", inside)
        plot_errors(t, rec.voltage_v, rec.simulated_v, folder / f"simulation_{part}.png",
                    f"{rec.name}: simulation error", "simulation error [mV]", inside)
