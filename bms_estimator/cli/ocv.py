"""``bms-estimator ocv``: OCV(SOC) table from a C/20 test, or from HPPC rest points."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..core.ocv import CELL_TEMPERATURE_RANGE_C, OcvCurve
from ..data import load_recording
from ..errors import DataError
from ..ocv_table import write_ocv_table
from .outputs import check_outputs, file_output


def add_parser(sub) -> None:
    p = sub.add_parser("ocv", help="build an OCV table (soc,ocv_v,hysteresis_v,temperature_c,capacity_ah) "
                                   "from a C/20 or HPPC test",
                       description="C/20 discharge + charge: both branches by coulomb counting, their mean as "
                                   "the OCV, half their gap as the hysteresis. With --hppc-steps the input is an "
                                   "HPPC test and the OCV comes from its rest points. The table records the test's "
                                   "temperature (temperature_c) and discharge capacity (capacity_ah): give several "
                                   "tables to --ocv, one per temperature.")
    p.add_argument("data", type=Path, help="c20_ocv CSV (or hppc CSV with --hppc-steps)")
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
