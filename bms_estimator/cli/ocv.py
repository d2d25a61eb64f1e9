"""``bms-estimator ocv``: OCV(SOC) table from a C/20 test, or from HPPC rest points."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..core.ocv import OcvCurve
from ..data import load_recording


def add_parser(sub) -> None:
    p = sub.add_parser("ocv", help="build an OCV table (soc,ocv_v,hysteresis_v) from a C/20 or HPPC test",
                       description="C/20 discharge + charge: both branches by coulomb counting, their mean as "
                                   "the OCV, half their gap as the hysteresis. With --hppc-steps the input is an "
                                   "HPPC test and the OCV comes from its rest points.")
    p.add_argument("data", type=Path, help="c20_ocv CSV (or hppc CSV with --hppc-steps)")
    p.add_argument("-o", "--output", type=Path, required=True, help="OCV CSV to write")
    p.add_argument("--hppc-steps", type=Path, default=None, help="the hppc_steps CSV that goes with an hppc file")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    rec = load_recording(args.data, resample_s=None)
    if args.hppc_steps is not None:
        steps = load_recording(args.hppc_steps, resample_s=None)
        curve = OcvCurve.from_hppc(
            (rec.time_s, rec.current_a, rec.voltage_v), (steps.time_s, steps.current_a, steps.voltage_v)
        )
    else:
        curve = OcvCurve.from_c20(rec.time_s, rec.current_a, rec.voltage_v)
    curve.to_csv(args.output)
    msg = f"wrote {args.output}: {len(curve.soc)} points, OCV {curve.ocv_v[0]:.3f}..{curve.ocv_v[-1]:.3f} V"
    cd, cc = getattr(curve, "capacity_discharge_ah", None), getattr(curve, "capacity_charge_ah", None)
    if cd is not None and cc is not None:
        msg += f"; C/20 branch capacities {cd:.3f} Ah discharge, {cc:.3f} Ah charge"
    print(msg)
    return 0
