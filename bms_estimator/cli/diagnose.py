"""``bms-estimator diagnose``: what does the 2-RC model get wrong on this recording?

Identifies the paper's 2-RC model (LIF warm start, batch output-error fit), fits
one model extension per candidate cause (hysteresis, temperature, SOC
dependence, current nonlinearity, direction asymmetry, slow diffusion, current
offset, capacity error), scores each out of sample and names the cause
(:mod:`bms_estimator.diagnose`).
"""

from __future__ import annotations

import argparse
import warnings
from pathlib import Path

from ..errors import DataError, UsageError
from .outputs import check_outputs, file_output, folder_output
from .common import (RECORDING_HELP, add_cell_options, add_method_option, load, load_ocv, positive_float,
                     warn_if_count_does_not_close, warn_if_start_is_not_initial_soc, write_json)


def add_parser(sub) -> None:
    from ..diagnose import CAUSES, DiagnoseConfig

    p = sub.add_parser(
        "diagnose", help="name what the 2-RC model gets wrong on a recording (hysteresis, temperature, ...)",
        description="Fits the 2-RC baseline and one extension per candidate cause, scores them out of sample "
                    "(4-fold cross-validation over interleaved time blocks, or on --validate) with a penalty for "
                    "extra parameters, and names the cause with the largest significant gain ('none' when no "
                    "extension earns its parameters).")
    p.add_argument("data", type=Path, help=RECORDING_HELP)
    add_cell_options(p)
    p.add_argument("--validate", type=Path, default=None,
                   help="score on this recording instead of cross-validating on DATA "
                        "(same cell, starts at --initial-soc)")
    p.add_argument("--json", type=Path, default=None, help="write the result as JSON ('-' for stdout)")
    p.add_argument("--report", type=Path, default=None, help="folder for report.md and the PNG figures")
    p.add_argument("--causes", default=",".join(CAUSES),
                   help="comma-separated candidate causes (default: all)")
    p.add_argument("--no-lif", action="store_true",
                   help="skip the online LIF run that warm-starts the baseline (faster; a grid start is always tried)")
    add_method_option(p, DiagnoseConfig.method, "of the online run that warm-starts the baseline")
    p.add_argument("--no-pairs", action="store_true", help="skip the pair stage (two effects at once)")
    p.add_argument("--soc-min", type=float, default=None,
                   help="fit and score only where the counted SOC is at least this (e.g. 0.1 leaves out the "
                        "voltage collapse before a 2.5 V cut-off); default: the whole file")
    p.add_argument("--soc-max", type=float, default=None, help="fit and score only up to this counted SOC")
    p.add_argument("--resample-s", type=positive_float, default=1.0,
                   help="sample period; finer data is averaged (default 1 s)")
    p.set_defaults(func=run)


def _series(series_type, rec, ocv, args: argparse.Namespace, cfg, *, cross_validated: bool):
    """The file as the diagnosis reads it; too few samples in its SOC window, or (``cross_validated``: the
    file both fitted and scored) too few of them after its first block, which is never scored, is the
    file's fault (exit 3, named), said before the fits run."""
    from ..diagnose.decide import scored_folds, window_mask

    s = series_type.from_recording(rec, ocv, args.capacity_ah, args.initial_soc)
    try:
        window_mask(s, cfg)
        if cross_validated:
            scored_folds(s, cfg, validation=False)
    except ValueError as exc:  # (it read "only 60 samples inside the SOC window -1..2", exit 2, no file)
        raise DataError(f"{rec.source}: {exc}") from None
    return s


def run(args: argparse.Namespace) -> int:
    from ..diagnose import CAUSES, DiagnoseConfig, Series, diagnose, write_report
    from ..diagnose.report import REPORT_FILES

    check_outputs([("DATA", args.data), ("--validate", args.validate), ("--ocv", args.ocv)],
                  [file_output("--json", args.json, stdout=True),
                   folder_output("--report", args.report, *REPORT_FILES)])
    causes = tuple(c.strip() for c in args.causes.split(",") if c.strip())
    if not causes:  # (it ran the baseline alone, and named its cause 'none')
        raise UsageError(f"--causes {args.causes!r} names no cause; choose from {', '.join(CAUSES)}")
    cfg = DiagnoseConfig(candidates=causes, lif=not args.no_lif, method=args.method, pairs=not args.no_pairs,
                         soc_window=(-1.0 if args.soc_min is None else args.soc_min,
                                     2.0 if args.soc_max is None else args.soc_max))  # ValueError: an unknown cause
    rec = load(args.data, args)
    ocv = load_ocv(args.ocv, rec, capacity_ah=args.capacity_ah)
    warn_if_start_is_not_initial_soc(rec, ocv, args)
    warn_if_count_does_not_close(rec, ocv, args)
    data = _series(Series, rec, ocv, args, cfg, cross_validated=args.validate is None)
    val = None
    if args.validate is not None:
        rv = load(args.validate, args)
        warn_if_start_is_not_initial_soc(rv, ocv, args)
        warn_if_count_does_not_close(rv, ocv, args)
        val = _series(Series, rv, ocv, args, cfg, cross_validated=False)
    d = diagnose(data, validate=val, config=cfg)
    if cfg.lif and not d.lif:  # (it left the report's LIF line out without a word)
        warnings.warn(f"{rec.source}: the online {args.method} run that warm-starts the baseline identified fewer than "
                      f"10 of its {len(rec)} samples (at {rec.dt_s:g} s): the baseline started from the grid alone, "
                      "and the report has no online identification to show", UserWarning, stacklevel=2)
    if d.non_physical:
        fit = f"the {d.cause} extension" if d.cause != "none" else "the baseline"
        warnings.warn(f"{rec.source}: {fit} fitted {'; '.join(d.non_physical)}: no cell has it, the fit absorbs "
                      "what it does not model there (an SOC knot with few samples, an SOC path that misses charge, "
                      "another cell's OCV table)", UserWarning, stacklevel=2)
    out = d.to_json()
    out["data"] = str(args.data)
    if args.validate is not None:
        out["validate"] = str(args.validate)
    if args.report is not None:
        md = write_report(d, args.report, title=f"diagnose {args.data.name}")
        out["report"] = str(md)
    if args.json is not None:
        write_json(out, args.json)
    if args.json is None or str(args.json) != "-":
        print(f"cause: {d.cause}" + (f" (then {d.secondary})" if d.secondary else ""))
        print(f"baseline {d.baseline_rmse_mv:.2f} mV -> extended {d.extended_rmse_mv:.2f} mV "
              f"({d.gain_pct:.1f} % gain, {d.scoring}); noise {d.noise_mv:.2f} mV; {d.seconds:.1f} s")
        for c in d.ranking():
            if c.rmse_mv == c.rmse_mv:  # not NaN
                print(f"  {c.cause:22s} {c.rmse_mv:8.2f} mV  gain {c.gain_pct:6.1f} %  score {c.score:7.3f}  "
                      f"t {c.t_stat:6.1f}  {'significant' if c.significant else ''}")
            else:
                print(f"  {c.cause:22s}        -     ({c.note})")
        if args.report is not None:
            print(f"report: {out['report']}")
    return 0
