"""Options shared by the offline subcommands and their translation to the core's configs."""

from __future__ import annotations

import argparse
import json
import math
import re
import warnings
from pathlib import Path
from typing import Sequence

import numpy as np

from ..core.identifier import METHODS, IdentifierConfig
from ..core.ocv import median_temperature_c
from ..core.ocv_surface import REFERENCE_TEMPERATURE_C, OcvSurface, stated_capacity_ratio, table_capacities_ah
from ..core.soc import SocConfig
from ..data import CellRecording, check_charge_span, load_recording
from ..errors import DataError, UsageError
from ..gaps import MAX_GAP_S
from ..jsonsafe import to_jsonable
from ..ocv_table import read_ocv_tables

_ID = IdentifierConfig()
_SOC = SocConfig()

#: a first sample below this C-rate is read on the OCV table as the file's start SOC ...
START_REST_C = 0.05
#: ... and one this far from --initial-soc is warned about (at rest the data set's files read 0.993-1.001)
START_SOC_TOLERANCE = 0.1
#: a current that never moves by this C-rate (peak, or max - min) excites no model to identify; well below a
#: C/20 test's (the slowest load of the data set) and above a rest's sensor noise (mA)
EXCITATION_C = 0.01
#: An --ocv table within this of a recording's median cell temperature is "the same ambient"; a recording
#: further than this outside the tables' temperatures is read on the nearest table, and warned about.
SAME_AMBIENT_K = 5.0
#: what a recording given to an offline command holds (its --help)
RECORDING_HELP = ("CSV or .csv.gz with a header row: time_s in s, current_a in A (positive = charge), voltage_v in V, "
                  "optionally temperature_c in degC; other columns are ignored")


def _number(text: str, *, allow_zero: bool) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not math.isfinite(value) or value < 0 or (value == 0 and not allow_zero):
        raise argparse.ArgumentTypeError(f"{text!r} must be a number >= 0" if allow_zero else
                                         f"{text!r} must be a positive number")
    return value


def positive_float(text: str) -> float:
    return _number(text, allow_zero=False)


def _fraction(text: str, low: float) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not low <= value <= 1.0:  # NaN fails too
        raise argparse.ArgumentTypeError(f"{text!r} must be a fraction in [{low:g}, 1]")
    return value


def soc_fraction(text: str) -> float:
    """An SOC option's value: a fraction in [0, 1]."""
    return _fraction(text, 0.0)


def soc_difference(text: str) -> float:
    """A difference of two SOCs: a fraction in [-1, 1]."""
    return _fraction(text, -1.0)


def add_cell_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--ocv", required=True, type=Path, action="append",
                   help="OCV CSV (soc,ocv_v[,hysteresis_v][,temperature_c]), e.g. from 'bms-estimator ocv'; give it "
                        "once per table (one per test and temperature, each with its temperature_c column)")
    p.add_argument("--capacity-ah", required=True, type=positive_float,
                   help="the capacity you state (nominal); the effective one is estimated from the data and reported")
    p.add_argument("--initial-soc", type=soc_fraction, default=1.0,
                   help="SOC at the file's start (default 1.0: the drive cycles of ../shared/data start full)")


METHOD_HELP = ("identification method: lif = continuous time, LIF + RLS (the paper's); lif-iv = LIF + "
               "recursive instrumental variables; lif-iv-bv = lif-iv with a kinetic (Butler-Volmer-like) term, a "
               "resistance that falls with current; lif-iv-ct = lif-iv whose fast RC branch is "
               "charge transfer (Butler-Volmer shape from R1 and the temperature, no fitted gain); arx = the discrete-time baseline")


def add_method_option(p: argparse.ArgumentParser, default: str, what: str = "") -> None:
    p.add_argument("--method", choices=METHODS, default=default,
                   help=f"{METHOD_HELP}{' ' + what if what else ''} (default {default})")


def add_rest_over_gaps_option(p: argparse.ArgumentParser, then: str) -> None:
    """``--no-rest-over-gaps`` (``args.rest_over_gaps``): the file's logging gaps fed as samples instead of rested
    over (:mod:`bms_estimator.gaps`); ``then`` says what resting does to the command's output."""
    p.add_argument("--no-rest-over-gaps", dest="rest_over_gaps", action="store_false",
                   help="feed the file's logging gaps (no sample for longer than the service bridges, "
                        f"{MAX_GAP_S:g} s; load_recording fills them) as contiguous samples, instead of resting the "
                        f"estimator over them as the service does at a time jump (default: rest; {then})")


def non_negative_float(text: str) -> float:
    return _number(text, allow_zero=True)


def add_c0_prior_option(p: argparse.ArgumentParser) -> None:
    from ..analysis import KNOWN_SOC_C0_PRIOR_WEIGHT

    p.add_argument("--c0-prior", type=non_negative_float, default=KNOWN_SOC_C0_PRIOR_WEIGHT,
                   help="weight of the prior c0 = 0 when the SOC path is known, per sample relative to one data "
                        f"sample (default {KNOWN_SOC_C0_PRIOR_WEIGHT}; 0 = the paper's plain estimate)")


def add_tuning_options(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("estimator tuning (defaults serve both cells of ../shared/data)")
    g.add_argument("--window", type=int, default=_ID.window, help=f"LIF window L in samples (default {_ID.window})")
    g.add_argument("--forgetting", type=float, default=_ID.forgetting,
                   help=f"RLS forgetting factor per sample (default {_ID.forgetting})")
    g.add_argument("--error-on-mv", type=float, default=None,
                   help="turn adaptation on above this windowed RMS equation error, mV (default "
                        f"{_ID.error_on_v * 1e3:g}: always on); give --error-off-mv below it with it (the paper: 3 "
                        "and 1.5)")
    g.add_argument("--error-off-mv", type=float, default=None,
                   help=f"turn adaptation off below this windowed RMS equation error, mV (default "
                        f"{_ID.error_off_v * 1e3:g}: never off); at most --error-on-mv")
    g.add_argument("--tau-max-s", type=float, default=_ID.tau_max_s,
                   help=f"admissible slow time constant bound, s (default {_ID.tau_max_s:g})")
    g.add_argument("--soc-error-threshold", type=float, default=_SOC.soc_error_threshold,
                   help=f"c0 compensation threshold as an SOC error (default {_SOC.soc_error_threshold})")
    g.add_argument("--no-capacity-estimation", action="store_true", help="trust the stated capacity")
    g.add_argument("--no-hysteresis", action="store_true",
                   help="read SOC on the mean OCV curve, ignoring the OCV table's hysteresis_v column")
    g.add_argument("--resample-s", type=positive_float, default=1.0, help="sample period; finer data is averaged (default 1 s)")


#: the tuning options' config fields, so that a bound a field states is reported under the option's name
_TUNING_OPTION = {"window": ("--window", 1.0), "forgetting": ("--forgetting", 1.0),
                  "error_on_v": ("--error-on-mv", 1e3), "error_off_v": ("--error-off-mv", 1e3),
                  "tau_max_s": ("--tau-max-s", 1.0), "soc_error_threshold": ("--soc-error-threshold", 1.0)}


def adaptation_thresholds_mv(args: argparse.Namespace) -> tuple[float, float]:
    """``(--error-on-mv, --error-off-mv)``, the identifier's default for one not given.

    Adaptation starts on, turns off when the windowed RMS error falls below the off threshold and on again
    when it rises above the on threshold (:mod:`bms_estimator.core.rls`). An off threshold above the on
    one is refused naming both options (it was clamped to the on one without a word), and so is an on
    threshold without an off one above 0: adaptation would never turn off and the threshold change nothing
    (``--error-on-mv 50`` alone gave the default's result). A negative or NaN value is left to the
    config's bounds, which name its option.
    """
    on = _ID.error_on_v * 1e3 if args.error_on_mv is None else args.error_on_mv
    off = _ID.error_off_v * 1e3 if args.error_off_mv is None else args.error_off_mv
    if not (on >= 0 and off >= 0):  # (NaN too)
        return on, off
    said_on = f"--error-on-mv {on:g}" + (" (the default)" if args.error_on_mv is None else "")
    said_off = f"--error-off-mv {off:g}" + (" (the default)" if args.error_off_mv is None else "")
    if off > on:
        raise UsageError(f"{said_off} is above {said_on}: adaptation turns off below the one and on above the "
                         "other; give --error-off-mv at most --error-on-mv")
    if on > 0 and off == 0:
        raise UsageError(f"{said_on} with {said_off} changes nothing: adaptation starts on and never turns off "
                         "below 0 mV; give --error-off-mv above 0 and at most --error-on-mv (the paper: 3 and 1.5)")
    return on, off


def soc_config(args: argparse.Namespace, method: str | None = None) -> SocConfig:
    if args.window < 1:  # (IdentifierConfig refuses it too, but by its field's name, not the option's)
        raise ValueError(f"--window must be at least 1 sample, got {args.window}")
    on_mv, off_mv = adaptation_thresholds_mv(args)
    try:
        ident = IdentifierConfig(
            method=method or getattr(args, "method", None) or _ID.method,
            window=args.window,
            forgetting=args.forgetting,
            error_on_v=on_mv / 1e3,
            error_off_v=off_mv / 1e3,
            tau_max_s=args.tau_max_s,
        )
        return SocConfig(
            identifier=ident,
            soc_error_threshold=args.soc_error_threshold,
            estimate_capacity=not args.no_capacity_estimation,
            hysteresis=not args.no_hysteresis,
        )
    except ValueError as exc:  # the config's bounds name its fields: say the option the user gave
        field = str(exc).split(" ", 1)[0]
        if field not in _TUNING_OPTION:
            raise
        option, scale = _TUNING_OPTION[field]
        value = {"error_on_v": on_mv, "error_off_v": off_mv}.get(field, getattr(args, option[2:].replace("-", "_")))
        rest = str(exc).split(" must ", 1)[1].rsplit(", got", 1)[0] if " must " in str(exc) else str(exc)
        if scale != 1.0:  # a bound in volts, the option in mV
            rest = re.sub(r"(-?\d+(?:\.\d+)?(?:e-?\d+)?)", lambda m: f"{float(m.group(1)) * scale:g}", rest)
        raise UsageError(f"{option} must {rest}, got {value:g}") from None


def load(path: Path, args: argparse.Namespace, *, identifies: bool = True) -> CellRecording:
    """The recording at ``--resample-s``; with ``--capacity-ah``, one whose charge fits that capacity
    (:func:`~bms_estimator.data.check_charge_span`) and, for a command that ``identifies`` the model from
    the file, one with a current that moves (:func:`check_excitation`)."""
    rec = load_recording(path, resample_s=args.resample_s)
    if len(rec) < MIN_SAMPLES:
        raise DataError(f"{path}: only {len(rec)} samples after resampling; too short to estimate anything"
                        f"{_time_unit_hint(path, len(rec), args.resample_s)}")
    capacity_ah = getattr(args, "capacity_ah", None)
    if capacity_ah:
        check_charge_span(rec, capacity_ah, "--capacity-ah")
        if identifies:
            check_excitation(rec, capacity_ah, args.command)
    return rec


#: a recording resampled to fewer samples than this is too short for any command
MIN_SAMPLES = 10


def _time_unit_hint(path: Path, samples: int, resample_s: float) -> str:
    """``': its N rows span only S s of time_s ...'`` when the file holds many more rows than the samples they
    averaged into: a time column in hours (a 3 h drive's 10,984 rows read as 3.05 s, 4 samples) or minutes,
    which the message 'only 4 samples ... too short' sent looking for a short file."""
    with warnings.catch_warnings():  # (the first read said its warnings)
        warnings.simplefilter("ignore")
        native = load_recording(path, resample_s=None)
    if len(native) < MIN_SAMPLES * max(samples, 1):
        return ""
    return (f": its {len(native):,} rows span only {native.duration_s:.4g} s of time_s (a median step of "
            f"{native.dt_s:.3g} s, averaged to --resample-s {resample_s:g}): is time_s in seconds, not hours or "
            "minutes? convert it to seconds")


def check_excitation(rec: CellRecording, capacity_ah: float, command: str) -> None:
    """Refuse a recording whose current never moves by ``EXCITATION_C`` x ``capacity_ah`` (C/100).

    The model is identified from the voltage's response to the current (``dv = R0 di`` and the RC
    branches' relaxation after a step): a file at rest throughout, or at one constant current, gives
    the identifier's prior back as "identified" parameters and, on a rest file, a diagnosis whose
    t-statistics divide by a zero noise (1e14). ``max |i|`` and ``max i - min i`` must both reach C/100.
    """
    i = rec.current_a
    step_a = EXCITATION_C * capacity_ah
    peak, spread = float(np.max(np.abs(i))), float(np.ptp(i))
    if peak < step_a:
        what = f"at rest throughout (|current| at most {peak:.3g} A"
    elif spread < step_a:
        what = f"at one constant current (within {float(np.min(i)):.4g}..{float(np.max(i)):.4g} A"
    else:
        return
    raise DataError(f"{rec.source}: {what}; the model needs steps of C/100 = {step_a:.3g} A of --capacity-ah "
                    f"{capacity_ah:g}): {command} identifies it from the voltage's response to changes of the current")


def load_ocv(paths: Path | Sequence[Path], rec: CellRecording | None = None, *,
             capacity_ah: float | None = None) -> OcvSurface:
    """The ``--ocv`` tables as one :class:`OcvSurface` (one path: that table, at every temperature).

    Calls without a temperature read the tables at the recording's median cell
    temperature when ``rec`` logs one, else at 25 degC: the commands that
    identify on a whole file (fit, compare, diagnose) use one OCV per file.
    With ``capacity_ah`` (the stated ``--capacity-ah``), a capacity more than
    ``core.ocv_surface.STATED_CAPACITY_RATIO_MAX`` times away from the tables' C/20 capacity is a
    usage error: it is not the capacity of the cell the tables were measured on.
    """
    t = median_temperature_c(rec.temperature_c) if rec is not None else None
    path_list = [paths] if isinstance(paths, (str, Path)) else list(paths)
    try:
        surface = read_ocv_tables(path_list, default_temperature_c=REFERENCE_TEMPERATURE_C if t is None else t)
    except ValueError as exc:  # a malformed table is a data error (exit 3); the message names the file
        raise DataError(f"OCV table: {exc}") from None
    if surface.mixed_cells:  # each table fine, the set doubtful (core.ocv_surface, item 9)
        warnings.warn(f"--ocv: {surface.mixed_cells}", stacklevel=2)
    if t is not None:
        _warn_if_outside_the_tables(rec, t, surface)
    ratio = stated_capacity_ratio(capacity_ah, surface) if capacity_ah else None
    if ratio is not None:
        table_ah = float(np.median(table_capacities_ah(surface)))
        # 1000 times off: rather a table built from a test logged in mA (its OCV is right, its capacity_ah not)
        table_hint = (f", or rebuild the table: its capacity_ah {table_ah:.4g} Ah reads like a test whose current_a "
                      "was in mA" if ratio < 0.01 else "")
        raise UsageError(
            f"--capacity-ah {capacity_ah:g} is {ratio:.3g} times the C/20 capacity "
            f"{table_ah:.3f} Ah of the --ocv table(s) "
            f"({', '.join(Path(p).name for p in path_list)}): state one cell's capacity in Ah{table_hint}")
    return surface


def _warn_if_outside_the_tables(rec: CellRecording, median_c: float, surface: OcvSurface) -> None:
    """Warn when the recording's median cell temperature is more than ``SAME_AMBIENT_K`` outside the tables'.

    The surface holds the end tables outside their temperatures (``core.ocv_surface``, 1.): the LG
    cell's four 0 degC drives read on its 25 degC table alone ran without a word to an SOC RMSE of
    2.5-3.0 % (``soc``, default method), against 0.2-2.7 % on their own ambient's table.
    """
    temps = np.asarray(surface.temperatures_c, dtype=float)
    temps = temps[np.isfinite(temps)]
    if temps.size == 0 or not math.isfinite(median_c):
        return
    lo, hi = float(temps.min()), float(temps.max())
    off = max(lo - median_c, median_c - hi)
    if off > SAME_AMBIENT_K:
        span = f"{lo:.1f}" if hi - lo < 0.05 else f"{lo:.1f}..{hi:.1f}"
        warnings.warn(f"{rec.source}: its median cell temperature {median_c:.1f} degC is {off:.0f} K outside the "
                      f"--ocv table(s) at {span} degC, read there (held, not extrapolated): give a table measured "
                      f"near {round(median_c)} degC{fahrenheit_hint(median_c, lo, hi)}", UserWarning,
                      stacklevel=3)  # an int: -0.3 reads 0, not -0


def fahrenheit_hint(median_c: float, lo: float, hi: float) -> str:
    """``'; or is temperature_c in degF? ...'`` when the median read as Fahrenheit lies within ``SAME_AMBIENT_K`` of
    the tables' ``lo..hi`` degC, else ``''``: a column in degF (77 at 25 degC, 32 at 0 degC) lies inside a cell's
    range and was read as a 52 K warmer cell, the warning asking for a table 'measured near 76 degC'."""
    as_c = (median_c - 32.0) * 5.0 / 9.0
    if lo - SAME_AMBIENT_K <= as_c <= hi + SAME_AMBIENT_K:
        return (f"; or is temperature_c in degF? {median_c:.1f} degF is {as_c:.1f} degC, the tables' ambient: "
                "convert the column to degC")
    return ""


def warn_if_start_is_not_initial_soc(rec: CellRecording, ocv: OcvSurface, args: argparse.Namespace) -> None:
    """Warn when the file's first sample, at rest, reads an SOC on the OCV table far from ``--initial-soc``.

    The identification counts SOC from ``--initial-soc`` (default 1.0, the data set's full starts); a
    file that starts elsewhere runs without complaint to a wrong capacity and wrong parameters.
    """
    i0, v0 = float(rec.current_a[0]), float(rec.voltage_v[0])
    if abs(i0) > START_REST_C * args.capacity_ah:  # under load the terminal voltage is not the OCV
        _warn_if_first_rest_is_not_counted_soc(rec, ocv, args)
        return
    s0 = _soc_read(ocv, v0, None if rec.temperature_c is None else float(rec.temperature_c[0]))
    if abs(s0 - args.initial_soc) > START_SOC_TOLERANCE:
        warnings.warn(f"{rec.source}: its first voltage {v0:.3f} V (at rest) reads SOC {s0:.2f} on the --ocv "
                      f"table, not --initial-soc {args.initial_soc:g}: give the file's start SOC with --initial-soc",
                      UserWarning, stacklevel=2)


def _soc_read(ocv: OcvSurface, v: float, temperature_c: float | None) -> float:
    ok = temperature_c is not None and math.isfinite(temperature_c)
    return float(ocv.soc_from_ocv(v, temperature_c) if ok else ocv.soc_from_ocv(v))


def _read_and_counted(rec: CellRecording, ocv: OcvSurface, args: argparse.Namespace, k: int) -> tuple[float, float]:
    """At sample ``k`` (at rest): the SOC its voltage reads on the OCV table, and the SOC counted there from
    ``--initial-soc`` with ``--capacity-ah``."""
    counted = args.initial_soc + float(np.sum(rec.current_a[:k])) * rec.dt_s / 3600.0 / args.capacity_ah
    t = None if rec.temperature_c is None else float(rec.temperature_c[k])
    return _soc_read(ocv, float(rec.voltage_v[k]), t), counted


#: A file that starts under load is checked at its first rest of at least this long ...
FIRST_REST_S = 30.0
#: ... ending within this of its start ...
FIRST_REST_WITHIN_S = 1800.0
#: ... and warned about when the SOC read there is this far from the one counted from --initial-soc: the data set's
#: drives, all started full, read within 0.10 there; the same drives cut 4000 s in (mid-drive logs), 0.23-0.86
FIRST_REST_SOC_TOLERANCE = 0.2


def _warn_if_first_rest_is_not_counted_soc(rec: CellRecording, ocv: OcvSurface, args: argparse.Namespace) -> None:
    """A file that starts under load (a log from mid-drive): the SOC read at its first rest against the SOC counted
    there from ``--initial-soc``. Counted from 1.0, the LG la92 drive from its 4000th second (SOC 0.63) fitted R2
    133 mOhm for 30 and a simulation RMSE of 86 mV for 11, without a word."""
    cap = args.capacity_ah
    rest = np.abs(rec.current_a) < START_REST_C * cap
    edges = np.diff(np.r_[0, rest.astype(np.int8), 0])
    starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    dt = rec.dt_s
    long_enough = (ends - starts) * dt >= FIRST_REST_S
    if not long_enough.any():
        return
    k = int(ends[np.argmax(long_enough)]) - 1  # the first long rest's last sample
    if (k + 1) * dt > FIRST_REST_WITHIN_S:
        return
    read, counted = _read_and_counted(rec, ocv, args, k)
    if abs(read - counted) > FIRST_REST_SOC_TOLERANCE:
        warnings.warn(f"{rec.source}: it starts under load, and at its first rest ({rec.time_s[k] - rec.time_s[0]:.0f} "
                      f"s in) its voltage {rec.voltage_v[k]:.3f} V reads SOC {read:.2f} on the --ocv table, where "
                      f"counting from --initial-soc {args.initial_soc:g} gives {counted:.2f}: a log from mid-drive? "
                      "give the file's start SOC with --initial-soc", UserWarning, stacklevel=3)


#: A file that ends at rest for at least this long is read there ...
END_REST_S = 30.0
#: ... and warned about when the SOC read at its last sample is this far from the one counted from --initial-soc
#: with --capacity-ah: the data set's drives (the stated 2.9 / 3.0 Ah, the ambient's own or nearest table) close
#: within 0.30 (Panasonic 0 degC, whose cells give 2.2 Ah there), its HPPC files, whose discharge steps between the
#: pulse sets are not logged, 0.50-0.81
END_SOC_TOLERANCE = 0.4


def warn_if_count_does_not_close(rec: CellRecording, ocv: OcvSurface, args: argparse.Namespace) -> None:
    """Warn when the SOC read at the file's final rest is far from the SOC counted there from ``--initial-soc``.

    ``fit``, ``compare`` and ``diagnose`` take the SOC path from that count; a file that misses charge (an HPPC
    test whose discharge steps fall in its logging gaps), or a ``--capacity-ah`` or ``--ocv`` of another cell,
    gives a path the voltage contradicts, and fitted parameters that are the path's error: the Panasonic 25 degC
    HPPC file given as a drive ends counted at SOC 0.53 where its last rest reads 0.03, and was fitted to
    160 mV with R2 near 200 mOhm, without a word."""
    cap = args.capacity_ah
    rest = np.abs(rec.current_a) < START_REST_C * cap
    n = len(rest) - int(np.flatnonzero(~rest)[-1]) - 1 if not rest.all() else len(rest)
    if n * rec.dt_s < END_REST_S or n == len(rest):
        return
    k = len(rest) - 1
    read, counted = _read_and_counted(rec, ocv, args, k)
    if abs(read - counted) <= END_SOC_TOLERANCE:
        return
    gaps = int(np.count_nonzero(rec.filled)) if rec.filled is not None else 0
    why = (f"its {gaps} samples in logging gaps (filled at zero current) may hide charge that moved, as an HPPC "
           "test's discharge steps do" if gaps else "the file misses charge")
    warnings.warn(f"{rec.source}: at its final rest its voltage {rec.voltage_v[k]:.3f} V reads SOC {read:.2f} on the "
                  f"--ocv table, where counting from --initial-soc {args.initial_soc:g} with --capacity-ah {cap:g} "
                  f"gives {counted:.2f}: {why}, or --capacity-ah or the --ocv table is not this cell's; the fitted "
                  "parameters follow that SOC path", UserWarning, stacklevel=2)


def warn_if_capacity_at_search_end(capacity_ah: float, searched_ah, source: str, stated_ah: float) -> None:
    """Warn when the output-error capacity is an end of the grid it was searched on.

    :func:`~bms_estimator.analysis.output_error_capacity` returns the grid point with the least
    simulation error; at an end of the grid (0.8 or 1.1 x the stated capacity) the minimum was not
    found, and the capacity, the SOC path and every figure along it are the grid's, not the file's:
    a file too short to move its SOC, or one the model does not fit (the LG cell's -10 degC US06:
    175 mV).
    """
    lo, hi = float(searched_ah[0]), float(searched_ah[-1])
    if lo + 1e-9 < capacity_ah < hi - 1e-9:
        return
    side = "low" if capacity_ah <= lo + 1e-9 else "high"
    warnings.warn(f"{source}: the effective capacity {capacity_ah:.3f} Ah is the {side} end of its search "
                  f"({lo / stated_ah:.2g}..{hi / stated_ah:.2g} x --capacity-ah {stated_ah:g}): the file does not "
                  "identify it (too short, or a model that does not fit it), and its parameters and figures are "
                  "along that end's SOC path", UserWarning, stacklevel=2)


def warn_if_nothing_identified(identified: dict[str, np.ndarray], rec: CellRecording) -> set[str]:
    """Warn, once, naming the methods whose online identification identified no sample of ``rec``
    (``identified``: each method's per-sample flags); returns those methods.

    The identifier's block-LS start needs ``init_samples`` samples (``IdentifierConfig``), and one that
    comes out non-physical grows up to ``init_max_samples``: a file that never gives an admissible start
    keeps the identifier's prior throughout. The Panasonic cycle_1 drive logged every 10 s (1099 samples)
    did: ``fit`` printed the prior (R0 20.7 mOhm, tau1 15 s, tau2 200 s) as 'final values: the counted SOC,
    -0.00..1.00, has no identified sample in 20-90 %', ``compare`` three identical rows for LIF-IV, LIF and
    ARX, without a word.
    """
    none = [m for m, flags in identified.items() if not np.any(flags)]
    if none:
        names = " and ".join([", ".join(none[:-1]), none[-1]] if len(none) > 1 else none)
        warnings.warn(f"{rec.source}: {names} identified no sample of its {len(rec)} ({len(rec) * rec.dt_s / 3600:.2g} "
                      f"h at {rec.dt_s:g} s): no admissible model came out of the identifier's start (at least "
                      f"{_ID.init_samples} samples), so the parameters and figures are its prior, not the file's; a "
                      "log coarser than 1 s, or a short one, gives it too few samples to start from",
                      UserWarning, stacklevel=2)
    return set(none)


def write_json(data: dict, path: Path | None) -> None:
    """``data`` as indented JSON to ``path``, or to standard output for ``None`` or ``-``; the path's folder
    must exist (the commands check their outputs first: :mod:`.outputs`)."""
    text = json.dumps(to_jsonable(data), indent=2)
    if path is None or str(path) == "-":
        print(text)
    else:  # (its folder is there: check_outputs refused a missing one before the command ran)
        Path(path).write_text(text + "\n")
