"""``bms-estimator soc``: the online SOC estimator over a recording, from any start, against the reference."""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

from ..analysis import run_soc
from ..core.identifier import IdentifierConfig
from ..core.soc import SOC_METHODS, VOLTAGE_LINE_RATIO_MAX, SocConfig
from ..errors import DataError
from ..gaps import MAX_GAP_S, held_charge_in_gaps, recording_rest_plan
from ..scoring import counted_soc, soc_error_figures, soc_reference
from .common import (RECORDING_HELP, SAME_AMBIENT_K, add_cell_options, add_method_option, add_rest_over_gaps_option, add_tuning_options,
                     fahrenheit_hint, load, load_ocv, positive_float, soc_config, soc_difference, soc_fraction,
                     warn_if_start_is_not_initial_soc, write_json)
from .outputs import check_outputs, figure_output, file_output



def _start_soc(text: str) -> str | float:
    if text.strip().lower() == "ocv":
        return "ocv"
    try:
        return soc_fraction(text)
    except argparse.ArgumentTypeError:
        raise argparse.ArgumentTypeError(f"--start-soc {text!r} must be a fraction in [0, 1] (or 'ocv')") from None


def add_parser(sub) -> None:
    p = sub.add_parser(
        "soc", help="run the SOC estimator from any start and score it against the independent reference",
        description="Runs the online SOC estimator (identification, OCV correction, capacity estimation) over a "
                    "recording, starting at --start-s with --start-soc (or the reference there minus "
                    "--initial-soc-error). The reference is coulomb counting from the recording's start at --initial-soc "
                    "(default 1.0, full) with Q_ref = Ah_out(end) / (initial SOC - SOC_end), SOC_end read from the relaxed end-of-test voltage on the "
                    "discharge branch of the same cell's C/20 table at the same ambient (--reference-ocv; by default "
                    "the --ocv table with hysteresis within 5 K of the recording's temperature). A logging gap of the file "
                    f"(no sample for longer than {MAX_GAP_S:g} s) is rested over as the service rests over a time "
                    "jump (--no-rest-over-gaps: fed as samples); the scores count every sample of the file's time "
                    "base from the start, a gap's with the estimate held from before it.")
    p.add_argument("data", type=Path, help=f"the drive: {RECORDING_HELP}")
    add_cell_options(p)
    p.add_argument("--start-s", type=float, default=0.0,
                   help="the estimator begins this long after the file's first sample (s); inside a logging gap "
                        "it begins at the next logged sample (the JSON's start_s; start_time_s is that sample's "
                        "time_s, the time base of the file and of --trace)")
    p.add_argument("--start-soc", type=_start_soc, default=None,
                   help="SOC the estimator begins with (a fraction), or 'ocv' to read it from the first sample's "
                        "voltage as the service does after a rest (default: reference - --initial-soc-error)")
    p.add_argument("--initial-soc-error", type=soc_difference, default=0.2,
                   help="without --start-soc: start this far below the reference (default 0.2, the paper's Fig. 10)")
    p.add_argument("--soc-method", choices=SOC_METHODS, default=SocConfig().soc_method,
                   help=f"how the voltage corrects the count (default {SocConfig().soc_method}): c0 = the paper's "
                        "OCV-bias compensation, ekf = an extended Kalman filter on SOC, a diffusion branch and the "
                        "capacity, driven by the identified model (core/soc_ekf.py)")
    p.add_argument("--reference-ocv", type=Path, default=None,
                   help="the same cell's C/20 OCV table at the recording's ambient, for the reference")
    p.add_argument("--reference-capacity-ah", type=positive_float, default=None,
                   help="count the reference with this capacity instead (e.g. a recording without a final rest)")
    add_method_option(p, IdentifierConfig().method, "(the SOC estimator's identification)")
    add_rest_over_gaps_option(p, "the samples inside a gap are not fed and hold the last estimate")
    p.add_argument("--trace", type=Path, default=None,
                   help="write time_s,soc,soc_sigma,soc_reference,soc_counted,capacity_ah,temperature_c,fed (CSV) "
                        "here, one row per sample of the file's time base; fed = 0 in a logging gap rested over, "
                        "where the estimate is the one held from the last fed sample")
    p.add_argument("--json", type=Path, default=None, help="write the figures as JSON here ('-' = stdout)")
    p.add_argument("--plot", type=Path, default=None, help="write the SOC figure (PNG) here")
    add_tuning_options(p)
    p.set_defaults(func=run)


def curves_of(ocv) -> list:
    """The tables of an OCV surface (one curve: itself)."""
    return list(getattr(ocv, "curves", None) or [ocv])


def temperatures_of(ocv) -> list:
    """The tables' temperatures, ``None`` where unknown, one per :func:`curves_of`."""
    return list(getattr(ocv, "temperatures_c", [None] * len(curves_of(ocv))))


def _reference_table(args: argparse.Namespace, ocv, temp_c: float | None):
    """The C/20 table of the recording's ambient: --reference-ocv, else the nearest --ocv table with hysteresis."""
    if args.reference_ocv is not None:
        return load_ocv([args.reference_ocv]), "given"
    curves, temps = curves_of(ocv), temperatures_of(ocv)
    best = None
    for c, t in zip(curves, temps):
        if not c.has_hysteresis:
            continue  # an HPPC table has no branches to read a rest on
        if temp_c is not None and t is not None and abs(t - temp_c) > SAME_AMBIENT_K:
            continue
        d = 0.0 if temp_c is None or t is None else abs(t - temp_c)
        if best is None or d < best[0]:
            best = (d, c)
    return (best[1], "--ocv table at the recording's ambient") if best else (None, None)


def _reference(args: argparse.Namespace, rec, ocv) -> tuple[float, str, bool, np.ndarray]:
    """``(capacity, why, scored, soc)`` of the reference: counted with --reference-capacity-ah, else
    read from the end rest on the C/20 table of the recording's ambient (:func:`_reference_table`)."""
    if args.reference_capacity_ah is not None:
        q_ref = float(args.reference_capacity_ah)
        return q_ref, "given capacity", True, counted_soc(rec.current_a, rec.dt_s, q_ref, args.initial_soc)
    temp = rec.temperature_c
    temp_c = float(np.nanmedian(temp)) if temp is not None and np.isfinite(temp).any() else None
    table, _ = _reference_table(args, ocv, temp_c)
    if table is None:
        temps = [t for c, t in zip(curves_of(ocv), temperatures_of(ocv)) if c.has_hysteresis and t is not None]
        hint = "" if temp_c is None or not temps else fahrenheit_hint(temp_c, min(temps), max(temps))
        raise ValueError(f"{args.data}: no C/20 table (with hysteresis) within {SAME_AMBIENT_K:g} K of the "
                         f"recording's {'unknown' if temp_c is None else f'{temp_c:.1f}'} degC among --ocv: give "
                         f"--reference-ocv or --reference-capacity-ah{hint}")
    try:
        # from --initial-soc, the file's start (1.0: the data set's full starts); a log that starts mid-drive
        # was counted from full whatever --initial-soc said: the LG la92 drive from 0.63 read a 1.68 Ah
        # reference and scored the estimator's right 2.82 Ah run at 14 % SOC RMSE
        ref = soc_reference(rec.current_a, rec.voltage_v, rec.dt_s, table, soc0=args.initial_soc)
    except ValueError as exc:  # the file cannot carry its own reference (no discharge, ends full)
        raise DataError(f"{args.data}: no SOC reference from the file: {exc}; give --reference-capacity-ah "
                        "to count the reference with a known capacity") from None
    c20_ah = getattr(table, "capacity_discharge_ah", None)
    if c20_ah and not REFERENCE_C20_RATIO[0] <= ref.capacity_ah / c20_ah <= REFERENCE_C20_RATIO[1]:
        print(f"bms-estimator soc: warning: {args.data.name}: counted from --initial-soc {args.initial_soc:g} at "
              f"its start, the reference reads a capacity of {ref.capacity_ah:.3f} Ah, "
              f"{ref.capacity_ah / c20_ah:.2f} x its C/20 table's {c20_ah:.3f} Ah (the data set's drives 0.96-1.04): "
              "does the file start there (a log from mid-drive)? give its start SOC with --initial-soc",
              file=sys.stderr)
    return ref.capacity_ah, ref.why, ref.relaxed, ref.soc


def _estimator_start(args: argparse.Namespace, soc_ref_at_start: float) -> tuple[float | None, str]:
    """The estimator's start SOC (None: read from the OCV) and how it was chosen, for the plot's title."""
    if args.start_soc == "ocv":
        return None, "read from the OCV"
    if args.start_soc is not None:
        return float(args.start_soc), f"{args.start_soc:.3f}"
    s0 = float(np.clip(soc_ref_at_start - args.initial_soc_error, 0.0, 1.0))
    return s0, f"{s0:.3f} (reference {soc_ref_at_start:.3f} - {args.initial_soc_error:g})"


def _write_trace(path: Path, rec, run_, soc_ref: np.ndarray, counted: np.ndarray, fed: np.ndarray) -> None:
    """``--trace``: one CSV row per sample (``fed`` 0: in a logging gap, the estimate held)."""
    temp = rec.temperature_c
    cols = {"time_s": rec.time_s, "soc": run_.soc, "soc_sigma": run_.soc_sigma, "soc_reference": soc_ref,
            "soc_counted": counted, "capacity_ah": run_.capacity_ah,
            "temperature_c": temp if temp is not None else np.full(len(rec), np.nan), "fed": fed.astype(float)}
    # time_s to the microsecond, as the recordings are saved: at 6 significant digits a log stamped in Unix
    # time read 1.7e+09 on every row, and a 12 day one lost its seconds
    np.savetxt(path, np.column_stack(list(cols.values())), delimiter=",", header=",".join(cols),
               comments="", fmt=["%.6f"] + ["%.6g"] * (len(cols) - 1))


#: A reference capacity outside these times its C/20 table's is warned about: the data set's drives read 0.96-1.04
#: at their ambient; a log that starts mid-drive, counted from full, reads far less (the LG la92 drive from SOC
#: 0.63: 0.60).
REFERENCE_C20_RATIO = (0.8, 1.25)

#: a logging gap whose held current counts less than this SOC (a fraction) in the reference is not worth a word
HELD_SOC_NOTED = 1e-4


def _warn_held_charge(args: argparse.Namespace, rec, plan, q_ref: float, k0: int, out: dict) -> None:
    """The reference counts the current held over a logging gap rested over (gaps.py): say how much, once,
    naming the largest gap; the JSON's ``logging_gaps.reference_held_ah`` is their sum."""
    held = [g for g in held_charge_in_gaps(rec, plan) if g[0] >= rec.time_s[k0]]
    out["logging_gaps"]["reference_held_ah"] = float(sum(g[2] for g in held))
    noted = [g for g in held if abs(g[2]) >= HELD_SOC_NOTED * q_ref]
    if not noted:
        return
    t0, length, ah = max(noted, key=lambda g: abs(g[2]))
    print(f"bms-estimator soc: warning: {args.data.name}: the reference cannot know the charge inside "
          f"{len(noted)} logging gap(s) the estimator rests over (as parked, zero current); it counts the current "
          f"held from before each, {sum(g[2] for g in noted):+.4f} Ah in all, the largest {ah:+.4f} Ah "
          f"({100 * ah / q_ref:+.2f} % SOC) over the {length:.0f} s gap at {t0:.0f} s", file=sys.stderr)


def _score_text(figs: dict, base: dict, after_start_s: float, capacity_ah: float) -> str:
    """The scores' line; a recording that ends within 30 min (1 h) of the start has no figure from then
    (null in the JSON): it is scored from the start instead (it printed 'SOC RMSE nan %')."""
    if figs["rmse_30min_pct"] != figs["rmse_30min_pct"]:  # NaN
        return (f"SOC RMSE {figs['rmse_all_pct']:.2f} % from the start (the recording ends {after_start_s:.0f} s "
                f"after it, before the 30 min the other scores wait for); counting with the stated {capacity_ah:g} "
                f"Ah {base['rmse_all_pct']:.2f} %")
    one_h = f"after 1 h {figs['rmse_1h_pct']:.2f} %, " if figs["rmse_1h_pct"] == figs["rmse_1h_pct"] else ""
    return (f"SOC RMSE {figs['rmse_30min_pct']:.2f} % from 30 min after the start ({one_h}max "
            f"{figs['max_abs_pct']:.2f} %); counting with the stated {capacity_ah:g} Ah {base['rmse_30min_pct']:.2f} %")


def run(args: argparse.Namespace) -> int:
    check_outputs([("DATA", args.data), ("--ocv", args.ocv), ("--reference-ocv", args.reference_ocv)],
                  [file_output("--trace", args.trace), file_output("--json", args.json, stdout=True),
                   figure_output("--plot", args.plot)])
    rec = load(args.data, args, identifies=False)  # a rest file: the SOC read on the OCV, counted
    ocv = load_ocv(args.ocv, rec, capacity_ah=args.capacity_ah)
    warn_if_start_is_not_initial_soc(rec, ocv, args)  # the reference counts from --initial-soc
    dt = rec.dt_s
    t = rec.time_s - rec.time_s[0]
    k0 = int(np.searchsorted(t, args.start_s - 1e-9))
    if not 0 <= k0 < len(rec) or args.start_s < 0:
        raise ValueError(f"--start-s {args.start_s:g} is outside the recording (0..{t[-1]:.0f} s)")
    plan = recording_rest_plan(rec, args.rest_over_gaps)  # the logging gaps rested over (gaps.py)
    if not plan.fed[k0]:  # in a logging gap: the estimator begins at the next logged sample
        k_fed = plan.first_fed(k0)
        if k_fed is None:
            raise ValueError(f"--start-s {args.start_s:g} lies in a logging gap that runs to the end of the "
                             f"recording (no sample from {t[k0]:.0f} s on)")
        print(f"bms-estimator soc: --start-s {args.start_s:g} lies in a logging gap; the estimator begins at "
              f"the next logged sample, {t[k_fed]:.0f} s", file=sys.stderr)
        k0 = k_fed
    temp = rec.temperature_c
    q_ref, why, relaxed, soc_ref = _reference(args, rec, ocv)
    s0, start_text = _estimator_start(args, soc_ref[k0])
    cfg = soc_config(args).with_(soc_method=args.soc_method)
    run_ = run_soc(rec.current_a, rec.voltage_v, ocv, args.capacity_ah, s0, dt, cfg,
                   temperature_c=temp, start_index=k0, rest_s=plan.rest_before_s, fed=plan.fed)
    counted = np.full(len(rec), np.nan)
    s_count0 = run_.soc[k0] if s0 is None else s0
    counted[k0:] = counted_soc(rec.current_a[k0:], dt, args.capacity_ah, s_count0)
    figs = soc_error_figures(run_.soc, soc_ref, t, t[k0])
    base = soc_error_figures(counted, soc_ref, t, t[k0])
    q_v = run_.capacity_voltage_ah  # the c0 method's voltage-line capacity (NaN: none)
    out = dict(figs)
    out.update(
        counting_stated_capacity=base,
        soc_method=args.soc_method,
        start_s=float(t[k0]),  # from the file's first sample, as --start-s
        start_time_s=float(rec.time_s[k0]),  # on the file's own time base, as the trace's time_s
        start_soc=float(run_.soc[k0]),
        capacity_ah_estimated=float(run_.capacity_ah[-1]),
        capacity_ah_stated=args.capacity_ah,
        capacity_ah_reference=q_ref,
        capacity_at_bound=run_.capacity_at_bound,
        capacity_ah_voltage_line=q_v if math.isfinite(q_v) else None,
        reference=why,
        reference_scored=relaxed,
        soc_sigma_end=float(run_.soc_sigma[-1]) if run_.soc_sigma is not None else None,
        soc_corrections=run_.corrections,
        estimator_rejections=run_.rejections,
        samples=len(rec),
        logging_gaps={"rested": int(np.count_nonzero(plan.rest_before_s[k0 + 1:])),
                      "rested_s": float(plan.rest_before_s[k0 + 1:].sum()),
                      "samples_not_fed": int(np.count_nonzero(~plan.fed[k0:]))},
    )
    ratio = args.capacity_ah / q_v if math.isfinite(q_v) else None
    if ratio is not None and not 1 / VOLTAGE_LINE_RATIO_MAX <= ratio <= VOLTAGE_LINE_RATIO_MAX:
        print(f"bms-estimator soc: warning: {args.data.name}: the voltage says this cell's capacity is about "
              f"{q_v:.2f} Ah (the c0 method's voltage line), --capacity-ah {args.capacity_ah:g} is {ratio:.1f} x "
              "that: --capacity-ah is likely wrong for this cell and the SOC is unreliable", file=sys.stderr)
    elif run_.capacity_at_bound:
        side = "low" if run_.capacity_at_bound < 0 else "high"
        factor = cfg.capacity_bounds[0 if run_.capacity_at_bound < 0 else 1]
        print(f"bms-estimator soc: warning: the capacity estimate ended at its {side} bound, {factor:g} x "
              f"--capacity-ah {args.capacity_ah:g} = {factor * args.capacity_ah:.3f} Ah (the reference says "
              f"{q_ref:.3f} Ah): --capacity-ah is likely wrong for this cell and the SOC is unreliable",
              file=sys.stderr)
    _warn_held_charge(args, rec, plan, q_ref, k0, out)
    if args.trace is not None:
        _write_trace(args.trace, rec, run_, soc_ref, counted, plan.fed)
    if args.plot:
        from ..plots import plot_soc

        plot_soc(rec.time_s, run_.soc, soc_ref, run_.capacity_ah, args.plot,
                 f"{args.data.name}: SOC from {start_text} at {t[k0]:.0f} s ({args.soc_method})", counted=counted)
    if args.json is not None:
        write_json(out, args.json)
    if args.json is None or str(args.json) != "-":
        note = "" if relaxed else " [reference not scored: " + why + "]"
        print(f"{_score_text(figs, base, t[-1] - t[k0], args.capacity_ah)}; capacity estimated "
              f"{out['capacity_ah_estimated']:.3f} Ah (reference {q_ref:.3f}){note}")
        gaps = out["logging_gaps"]
        if gaps["rested"]:
            print(f"rested over {gaps['rested']} logging gaps ({gaps['rested_s'] / 3600:.1f} h without samples; "
                  "the estimate held there)")
    return 0
