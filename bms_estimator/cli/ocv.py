"""``bms-estimator ocv``: OCV(SOC) table from a C/20 test, or from HPPC rest points."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from ..core.ocv import CELL_TEMPERATURE_RANGE_C, OcvCurve
from ..data import load_recording
from ..errors import DataError
from ..ocv_table import write_ocv_table
from .common import RECORDING_HELP
from .outputs import check_outputs, file_output


def add_parser(sub) -> None:
    p = sub.add_parser("ocv", help="build an OCV table (soc,ocv_v,hysteresis_v,temperature_c,capacity_ah) "
                                   "from a C/20 or HPPC test",
                       description="C/20 discharge + charge: both branches by coulomb counting, their mean as "
                                   "the OCV, half their gap as the hysteresis. With --hppc-steps the input is an "
                                   "HPPC test and the OCV comes from its rest points. The table records the test's "
                                   "temperature (temperature_c) and discharge capacity (capacity_ah): give several "
                                   "tables to --ocv, one per temperature.")
    p.add_argument("data", type=Path, help=f"a C/20 test (or an HPPC test with --hppc-steps): {RECORDING_HELP}")
    p.add_argument("-o", "--output", type=Path, required=True, help="OCV CSV to write")
    p.add_argument("--hppc-steps", type=Path, default=None, help="the hppc_steps CSV that goes with an hppc file")
    p.add_argument("--temperature-c", type=_cell_temperature, default=None,
                   help="the table's temperature in degC, written to its temperature_c column (default: the test's "
                        "median cell temperature, from the data's temperature_c column)")
    p.set_defaults(func=run)


def _cell_temperature(text: str) -> float:
    """A cell temperature in degC, within the range the recordings' temperature_c is held to
    (``core.ocv.CELL_TEMPERATURE_RANGE_C``): the table is read at it, so 500 (kelvin?) would file it far off."""
    lo, hi = CELL_TEMPERATURE_RANGE_C
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not lo <= value <= hi:  # NaN fails too
        raise argparse.ArgumentTypeError(f"{text!r} is not a cell temperature in degC ({lo:g}..{hi:g})")
    return value


#: hours a slow (pseudo-OCV) discharge takes at its own current: C/2 .. C/200 (the data set's C/20: 18.5-20.7 h)
C20_BRANCH_HOURS = (2.0, 200.0)


def _check_branch_hours(path: Path, current_a: np.ndarray, capacity_ah: float) -> None:
    """Refuse a discharge branch that lasts outside ``C20_BRANCH_HOURS`` at its median current: a time_s in hours
    or minutes, or in ms, makes every capacity of the table 3600 or 60 times too small or 1000 times too large
    (the LG 25 degC test in hours: a 0.001 Ah table, written without a word). The OCV shape is unchanged (each
    branch is read on its own throughput), but the table's capacity_ah is what --capacity-ah is checked against."""
    i = np.asarray(current_a, dtype=float)
    ref = float(np.percentile(np.abs(i), 90))
    dis = -i[i < -0.2 * ref]
    if dis.size == 0 or not capacity_ah:
        return
    hours = capacity_ah / float(np.median(dis))
    lo, hi = C20_BRANCH_HOURS
    if not lo <= hours <= hi:
        raise DataError(f"{path}: its discharge branch lasts {hours:.3g} h at its median current "
                        f"({float(np.median(dis)):.4g} A for {capacity_ah:.4g} Ah), where a slow OCV test's takes "
                        f"{lo:g}-{hi:g} h (C/20: 20 h): is time_s in seconds?")


def run(args: argparse.Namespace) -> int:
    check_outputs([("DATA", args.data), ("--hppc-steps", args.hppc_steps)], [file_output("-o/--output", args.output)])
    rec = load_recording(args.data, resample_s=None)
    temperature = args.temperature_c if args.temperature_c is not None else rec.temperature_c
    if args.hppc_steps is not None:
        steps = load_recording(args.hppc_steps, resample_s=None)
        try:
            curve = OcvCurve.from_hppc(
                (rec.time_s, rec.current_a, rec.voltage_v), (steps.time_s, steps.current_a, steps.voltage_v),
                temperature_c=temperature,
            )
        except ValueError as exc:  # the pair of files is not an HPPC test and its steps
            raise DataError(f"{args.data} with --hppc-steps {args.hppc_steps}: {exc}") from None
    else:
        try:
            curve = OcvCurve.from_c20(rec.time_s, rec.current_a, rec.voltage_v, temperature_c=temperature)
        except ValueError as exc:  # the file is not a C/20 test
            raise DataError(f"{args.data}: {exc} (an HPPC test needs --hppc-steps)") from None
        _check_branch_hours(args.data, rec.current_a, curve.capacity_discharge_ah)
    write_ocv_table(curve, args.output)
    msg = f"wrote {args.output}: {len(curve.soc)} points, OCV {curve.ocv_v[0]:.3f}..{curve.ocv_v[-1]:.3f} V"
    if curve.temperature_c is None:
        msg += ("; no temperature_c (the data logs no cell temperature): give --temperature-c to use this table "
                "with others")
    else:
        msg += f" at {curve.temperature_c:g} degC"
    cd, cc = getattr(curve, "capacity_discharge_ah", None), getattr(curve, "capacity_charge_ah", None)
    if cd is not None and cc is not None:
        msg += f"; C/20 branch capacities {cd:.3f} Ah discharge, {cc:.3f} Ah charge"
    print(msg)
    return 0
