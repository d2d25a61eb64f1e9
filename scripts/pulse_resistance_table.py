#!/usr/bin/env python3
"""The README's pulse-resistance table: does the measured cell's resistance depend on the current?

Every HPPC pulse from rest in ../shared/data (Panasonic 18650PF: 10 s discharge pulses of
0.5, 1, 2, 4, 6 C at SOC steps, every ambient; the LG files have no HPPC test), its
resistance R(t) = (v(t0 + t) - v_rest) / I at t = 0.2, 1 and 9.5 s
(:func:`bms_estimator.core.pulse_resistance.pulse_resistance`), binned by pulse current and
by the SOC read from the OCV at the rest voltage before the pulse (that ambient's OCV, as in
``scripts/compare_table.py``). A linear 2-RC cell has one R(t) for every current.

    python scripts/pulse_resistance_table.py [--readme]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from compare_table import ambient_c, ocv_for, write_readme_section  # noqa: E402

from bms_estimator.core.pulse_resistance import pulse_resistance  # noqa: E402
from bms_estimator.data import load_recording, shared_data_dir  # noqa: E402

CELL, STATED_AH = "panasonic-18650pf", 2.9
AT_S = (0.2, 1.0, 9.5)
C_RATES = (0.5, 1.0, 2.0, 4.0, 6.0)
SOC_BINS = ((0.2, 0.5), (0.5, 0.9))
BEGIN, END = "<!-- pulse-resistance:begin -->", "<!-- pulse-resistance:end -->"


def measure(data: Path) -> list[dict]:
    rows = []
    for amb in sorted((d.name for d in (data / CELL).iterdir() if (d / "hppc.csv.gz").exists()), key=ambient_c,
                      reverse=True):
        rec = load_recording(data / CELL / amb / "hppc.csv.gz", resample_s=None)
        ocv, _ = ocv_for(data / CELL, amb)
        p = pulse_resistance(rec.time_s, rec.current_a, rec.voltage_v, threshold_a=0.05 * STATED_AH, at_s=AT_S)
        soc = np.asarray(ocv.soc_from_ocv(p.rest_voltage_v))
        c_rate = np.abs(p.current_a) / STATED_AH
        for c in C_RATES:
            near = np.abs(c_rate - c) < 0.25 * c
            for lo, hi in SOC_BINS:
                sel = near & (soc >= lo) & (soc < hi)
                r = p.resistance_ohm[sel]
                ok = np.isfinite(r)
                rows.append({"ambient": amb, "c_rate": c, "soc": (lo, hi), "pulses": int(sel.sum()),
                             "r_mohm": [float(1e3 * np.median(r[ok[:, k], k])) if ok[:, k].any() else float("nan")
                                        for k in range(len(AT_S))]})
    return rows


def table(rows: list[dict]) -> str:
    ambients = list(dict.fromkeys(r["ambient"] for r in rows))
    head = " | ".join(f"{a} SOC {int(100 * lo)}-{int(100 * hi)} %" for a in ambients for lo, hi in SOC_BINS)
    lines = [f"| pulse | {head} |", "|---|" + "---|" * (len(ambients) * len(SOC_BINS))]

    def cell(r: dict) -> str:
        if not r["pulses"] or not np.isfinite(r["r_mohm"][2]):
            return "-"
        return f"{r['r_mohm'][0]:.0f} / {r['r_mohm'][1]:.0f} / {r['r_mohm'][2]:.0f}"

    by = {(r["ambient"], r["c_rate"], r["soc"]): r for r in rows}
    for c in C_RATES:
        lines.append(f"| {c:g} C | " + " | ".join(cell(by[(a, c, s)]) for a in ambients for s in SOC_BINS) + " |")
    # the change of R(9.5 s) from the smallest to the largest pulse that has a figure
    change = []
    for a in ambients:
        for s in SOC_BINS:
            fig = [(c, by[(a, c, s)]["r_mohm"][2]) for c in C_RATES if by[(a, c, s)]["pulses"]]
            fig = [(c, f) for c, f in fig if np.isfinite(f)]
            change.append(f"{100 * (fig[-1][1] / fig[0][1] - 1):+.0f} % ({fig[-1][0]:g} C)" if len(fig) > 1 else "-")
    lines.append("| R(9.5 s), largest vs 0.5 C pulse | " + " | ".join(change) + " |")
    return "\n".join(lines)


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--readme", action="store_true", help="write the table into README.md")
    args = ap.parse_args()
    data = shared_data_dir()
    if data is None:
        print("../shared/data not found (set BMS_SHARED_DATA)", file=sys.stderr)
        return 2
    if not (data / CELL).is_dir():
        print(f"{data / CELL}: absent; the table is the {CELL} HPPC tests'", file=sys.stderr)
        return 2
    text = table(measure(data))
    print(text)
    if args.readme:
        write_readme_section(text, BEGIN, END)
    return 0


if __name__ == "__main__":
    sys.exit(main())
