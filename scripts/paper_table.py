#!/usr/bin/env python3
"""The README's results table: the paper's Section IV-A and Fig. 10 on the measured cells.

For each cell at 25 degC: train on one drive cycle, validate on another (every pair
listed below: each file is trained on once and validated on once), stating only the
nominal capacity; CT (LIF) and DT (ARX) simulation RMSE in the 20-90 % SOC window, the
CT figure without the known-SOC c0 prior (the paper's plain estimate), and SOC from a
20 % initial error on the validation file (the default estimator, scored against the
independent reference of :mod:`bms_estimator.scoring`; the full SOC matrix is
``scripts/soc_matrix.py``). Prints Markdown; with --readme it replaces the block between the markers in
README.md. Needs ../shared/data (or BMS_SHARED_DATA).

    python scripts/paper_table.py --readme
"""

from __future__ import annotations

import argparse
import re
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

from bms_estimator.analysis import compare_methods, run_soc
from bms_estimator.core.ocv import OcvCurve
from bms_estimator.data import load_recording, shared_data_dir
from bms_estimator.scoring import soc_error_figures, soc_reference

PAIRS = [
    ("panasonic-18650pf", 2.9, "cycle_1", "cycle_2"),
    ("panasonic-18650pf", 2.9, "la92", "us06"),
    ("panasonic-18650pf", 2.9, "hwfet_a", "nn"),
    ("panasonic-18650pf", 2.9, "us06", "cycle_3"),
    ("panasonic-18650pf", 2.9, "nn", "la92"),
    ("panasonic-18650pf", 2.9, "cycle_3", "hwfet_a"),
    ("lg-hg2", 3.0, "udds", "la92"),
    ("lg-hg2", 3.0, "mixed1", "us06"),
    ("lg-hg2", 3.0, "mixed3", "mixed4"),
    ("lg-hg2", 3.0, "us06", "mixed2"),
    ("lg-hg2", 3.0, "la92", "mixed1"),
    ("lg-hg2", 3.0, "mixed2", "udds"),
]
ROOT = Path(__file__).resolve().parents[1]
BEGIN, END = "<!-- paper-table:begin -->", "<!-- paper-table:end -->"


def one(job):
    cell, q, train, val = job
    data = shared_data_dir()
    c20 = load_recording(data / cell / "25degC" / "c20_ocv.csv.gz", resample_s=None)
    ocv = OcvCurve.from_c20(c20.time_s, c20.current_a, c20.voltage_v)
    tr = load_recording(data / cell / "25degC" / f"{train}.csv.gz")
    va = load_recording(data / cell / "25degC" / f"{val}.csv.gz")
    m = compare_methods((tr.current_a, tr.voltage_v), (va.current_a, va.voltage_v), ocv, q).metrics
    plain = compare_methods((tr.current_a, tr.voltage_v), (va.current_a, va.voltage_v), ocv, q,
                            methods=("lif",), c0_prior_weight=0.0).metrics
    m["validate"]["lif"]["sim_rmse_mv_no_c0_prior"] = plain["validate"]["lif"]["sim_rmse_mv"]
    ref = soc_reference(va.current_a, va.voltage_v, va.dt_s, ocv)
    s = run_soc(va.current_a, va.voltage_v, ocv, q, 0.8, va.dt_s, temperature_c=va.temperature_c)
    e = soc_error_figures(s.soc, ref.soc, va.time_s - va.time_s[0])
    return job, m, e, float(s.capacity_ah[-1]), ref.capacity_ah


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--readme", action="store_true", help="write the table into README.md")
    args = ap.parse_args()
    data = shared_data_dir()
    if data is None:
        print("../shared/data not found (set BMS_SHARED_DATA)", file=sys.stderr)
        return 2
    need = dict.fromkeys(data / cell / "25degC" / f"{name}.csv.gz" for cell, _, *pair in PAIRS
                         for name in ("c20_ocv", *pair))
    missing = [str(p) for p in need if not p.exists()]
    if missing:
        print(f"the table's {len(PAIRS)} pairs need {len(need)} files of the measured data; missing: "
              f"{', '.join(missing)}", file=sys.stderr)
        return 2
    with ProcessPoolExecutor(2) as pool:
        rows = list(pool.map(one, PAIRS))
    lines = [
        "| cell | train -> validate | CT sim train / val [mV] | DT sim train / val [mV] | CT val, no c0 prior [mV] | CT OSA val [mV] | DT OSA val [mV] | capacity est. [Ah] | SOC from 20 % low: RMSE all / after 1 h [%] (reference capacity) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for (cell, q, train, val), m, e, q_est, q_ref in rows:
        lif, arx = m["train"]["lif"], m["train"]["arx"]
        vl, va = m["validate"]["lif"], m["validate"]["arx"]
        lines.append(
            f"| {cell} | {train} -> {val} | {lif['sim_rmse_mv']:.1f} / **{vl['sim_rmse_mv']:.1f}** | "
            f"{arx['sim_rmse_mv']:.1f} / **{va['sim_rmse_mv']:.1f}** | {vl['sim_rmse_mv_no_c0_prior']:.1f} | {vl['osa_rmse_mv']:.1f} | {va['osa_rmse_mv']:.1f} | "
            f"{m['capacity_ah_estimated']:.3f} (stated {q}) | {e['rmse_all_pct']:.2f} / {e['rmse_1h_pct']:.2f} "
            f"({q_ref:.2f} Ah) |"
        )
    lines.append("| paper (NCA 18650, 25 degC, simulation) | | 21.6 / 17.3 | 36.3 / 53.8 | | | | | 2.3 |")
    for cell in dict.fromkeys(r[0][0] for r in rows):
        mine = [m for (c, *_), m, *_ in rows if c == cell]
        ct = [m["validate"]["lif"]["sim_rmse_mv"] for m in mine]
        wins = sum(m["validate"]["lif"]["sim_rmse_mv"] < m["validate"]["arx"]["sim_rmse_mv"] for m in mine)
        after = [e["rmse_1h_pct"] for (c, *_), _m, e, *_ in rows if c == cell]
        lines.append(f"\n{cell}: CT validation {min(ct):.1f}-{max(ct):.1f} mV (median {sorted(ct)[len(ct) // 2]:.1f}), "
                     f"CT below DT on {wins} of {len(mine)} pairs; SOC after 1 h {min(after):.2f}-{max(after):.2f} %.")
    table = "\n".join(lines)
    print(table)
    if args.readme:
        readme = ROOT / "README.md"
        text = readme.read_text()
        new = re.sub(f"{re.escape(BEGIN)}.*?{re.escape(END)}", f"{BEGIN}\n{table}\n{END}", text, flags=re.S)
        readme.write_text(new)
        print(f"updated {readme}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
