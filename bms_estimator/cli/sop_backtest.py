"""``bms-estimator sop-backtest``: the online SOP's voltage prediction and limits against a recording."""

from __future__ import annotations

import argparse
import sys
import warnings
from pathlib import Path

import numpy as np

from ..core.identifier import IdentifierConfig
from ..core.ocv_surface import REFERENCE_TEMPERATURE_C
from ..core.sop import SopConfig, default_ratings_note
from ..errors import UsageError
from ..sop_backtest import run_backtest, summary
from .common import (RECORDING_HELP, add_cell_options, add_method_option, add_rest_over_gaps_option, add_tuning_options, load,
                     load_ocv, positive_float, soc_config, warn_if_start_is_not_initial_soc, write_json)
from .outputs import check_outputs, file_output

_SOP = SopConfig()
#: from this many samples on, the command says at its start that it will take a while
LONG_RUN_SAMPLES = 30_000


def add_parser(sub) -> None:
    p = sub.add_parser(
        "sop-backtest", help="check the state-of-power prediction and limits against what the cell did",
        description="Runs the online estimator over DATA. At the start of every window (each pulse of an HPPC "
                    "file, otherwise every --horizon-s of a drive cycle) it predicts the voltage at the window's end "
                    "from the window's own mean current (Plett's model-based method on the identified 2-RC model), "
                    "and checks the computed current limits against what the cell then did: 'limit exceeded' = the "
                    "voltage went past --v-min/--v-max while every sample's current stayed within the limits. The "
                    "HPPC static-resistance method is scored alongside as the baseline.")
    p.add_argument("data", type=Path, help=f"an HPPC test or a drive: {RECORDING_HELP}")
    add_cell_options(p)
    p.add_argument("--horizon-s", type=positive_float, default=10.0, help="prediction horizon = window length (default 10 s)")
    p.add_argument("--v-min", type=positive_float, default=_SOP.v_min, help=f"cell discharge cut-off, V (default {_SOP.v_min:g})")
    p.add_argument("--v-max", type=positive_float, default=_SOP.v_max, help=f"cell charge cut-off, V (default {_SOP.v_max:g})")
    p.add_argument("--i-discharge-max-a", type=positive_float, default=None,
                   help=f"the cell's discharge current rating, A (default {_SOP.i_discharge_max_a:g}, an 18650's)")
    p.add_argument("--i-charge-max-a", type=positive_float, default=None,
                   help=f"the cell's charge current rating, A (default {_SOP.i_charge_max_a:g}, an 18650's)")
    p.add_argument("--mode", choices=("auto", "hppc", "drive"), default="auto",
                   help="windows at the pulses (hppc), every horizon (drive), or whichever the file is (default auto)")
    add_method_option(p, IdentifierConfig().method, "(the online estimator's identification)")
    add_rest_over_gaps_option(p, "a window across a gap is then not scored")
    p.add_argument("--json", type=Path, default=None, help="write the figures as JSON here ('-' = stdout)")
    add_tuning_options(p)
    p.set_defaults(func=run)


def check_voltage_limits(v_min: float, v_max: float, ocv) -> None:
    """Refuse --v-min / --v-max that leave no room inside the cell's OCV range (0..100 % SOC at 25 degC):
    every window would break them, and the back-test would score a limit no cell can keep."""
    lo, hi = (float(v) for v in np.asarray(ocv.ocv(np.array([0.0, 1.0]), REFERENCE_TEMPERATURE_C), dtype=float))
    if v_min >= hi or v_max <= lo:
        raise UsageError(f"--v-min {v_min:g} V / --v-max {v_max:g} V leave no room inside the --ocv tables' "
                         f"OCV range {lo:.3f}..{hi:.3f} V: give the cell's cut-off voltages")


def current_ratings(args: argparse.Namespace) -> tuple[float, float]:
    """The cell's current ratings: as given, else the defaults (an 18650's), with a warning where those are not
    this cell's size (--capacity-ah more than 2 times from the 3 Ah cell they are for): on a 60 Ah cell they
    are 0.33 C / 0.1 C, every limit sat at them and the back-test scored a cap, not the model."""
    i_dis, i_chg = args.i_discharge_max_a, args.i_charge_max_a
    defaulted = [name for name, v in (("--i-discharge-max-a", i_dis), ("--i-charge-max-a", i_chg)) if v is None]
    i_dis = _SOP.i_discharge_max_a if i_dis is None else i_dis
    i_chg = _SOP.i_charge_max_a if i_chg is None else i_chg
    note = default_ratings_note(args.capacity_ah, defaulted, "--capacity-ah")
    if note is not None:
        warnings.warn(note, stacklevel=2)
    return i_dis, i_chg


def run(args: argparse.Namespace) -> int:
    check_outputs([("DATA", args.data), ("--ocv", args.ocv)], [file_output("--json", args.json, stdout=True)])
    if not args.v_min < args.v_max:
        raise ValueError(f"--v-min {args.v_min:g} must be below --v-max {args.v_max:g}")
    rec = load(args.data, args)
    ocv = load_ocv(args.ocv, rec, capacity_ah=args.capacity_ah)
    check_voltage_limits(args.v_min, args.v_max, ocv)
    warn_if_start_is_not_initial_soc(rec, ocv, args)
    if len(rec) >= LONG_RUN_SAMPLES:  # minutes of silence otherwise (27 h of HPPC: 2 min 18 s on 2 shared cores)
        print(f"bms-estimator sop-backtest: {len(rec):,} samples ({rec.duration_s / 3600:.1f} h) through the "
              "estimator and the SOP, one at a time: this takes minutes", file=sys.stderr, flush=True)
    i_dis, i_chg = current_ratings(args)
    sop = SopConfig(v_min=args.v_min, v_max=args.v_max, i_discharge_max_a=i_dis, i_charge_max_a=i_chg)
    res = run_backtest(rec.current_a, rec.voltage_v, rec.temperature_c, rec.dt_s, ocv, args.capacity_ah,
                       horizon_s=args.horizon_s, initial_soc=args.initial_soc, soc_config=soc_config(args),
                       sop_config=sop, mode=args.mode, time_s=rec.time_s, unlogged=rec.filled,
                       rest_over_gaps=args.rest_over_gaps)
    out = summary(res, args.capacity_ah)
    if args.json is not None:
        write_json(out, args.json)
    if args.json is None or str(args.json) != "-":
        e = out["voltage_error_mv"]
        print(f"{out['windows']} {out['mode']} windows of {res.horizon_s:g} s: |voltage error| median "
              f"{e['median']:.1f} mV, p95 {e['p95']:.1f} mV; limit exceeded in {out['limit_exceeded']} "
              f"({out['limit_exceeded_pct']:.2f} %) of them, {out['windows_within_limit']} stayed within the limit "
              f"(HPPC method: {out['hppc_method']['limit_exceeded']} exceeded)")
        if res.logging_gaps:
            print(f"rested over {res.logging_gaps} logging gaps ({res.rested_s / 3600:.1f} h without samples); "
                  f"{res.windows_across_gaps} windows across them not scored")
    return 0
