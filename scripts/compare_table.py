#!/usr/bin/env python3
"""The README's CT/DT table at every ambient: CT-LS (lif), CT-IV (lif-iv), CT-IV-BV (lif-iv-bv) and DT (arx).

Every ordered pair of drive cycles of the same cell at the same ambient in ../shared/data:
train on one, validate on the other (the paper's Section IV-A, as `bms-estimator compare`:
SOC by coulomb counting from full with the training file's output-error capacity, the
known-SOC c0 prior, training parameters looked up by SOC on the validation file and brought
to its cell temperature by Arrhenius, ``core.arrhenius.RESISTANCE_ACTIVATION_K``). Each
training file is identified once per method and validated on every other file of its
ambient. Validation simulation RMSE over the 20-90 % SOC window.

OCV: that ambient's own C/20 test; else its HPPC rests (``OcvCurve.from_hppc``, as
``bms-estimator ocv --hppc-steps``); else the nearest ambient's C/20. ``--ocv-from AMBIENT`` takes
every file's table from that ambient's C/20 test instead (what a recording at an ambient without a test
of its own gets), ``--files cell/ambient`` (a glob) picks the groups.

    python scripts/compare_table.py --readme [--json figures.json] [--jobs 2]
    python scripts/compare_table.py --files 'lg-hg2/0degC' --ocv-from 25degC
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from fnmatch import fnmatch
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from statistics import median

import numpy as np

from bms_estimator.analysis import DEFAULT_METHODS, IDENTIFICATION_METHOD, rmse_mv, train_methods, validate_methods
from bms_estimator.core.ocv import OcvCurve
from bms_estimator.data import load_recording, shared_data_dir
from bms_estimator.soc_matrix import ambient_c, ambient_ocv, ambient_table

STATED_AH = {"panasonic-18650pf": 2.9, "lg-hg2": 3.0}
NOT_DRIVE = ("c20_ocv", "hppc", "hppc_steps")
ROOT = Path(__file__).resolve().parents[1]
BEGIN, END = "<!-- compare-table:begin -->", "<!-- compare-table:end -->"
LABEL = {"lif": "CT-LS", "lif-iv": "CT-IV", "lif-iv-bv": "CT-IV-BV", "lif-iv-ct": "CT-IV-CT", "arx": "DT"}
# compare's methods and the kinetic-term extension (core/lif_bv.py); the first one's model gives the capacity
TABLE_METHODS = tuple(dict.fromkeys((*DEFAULT_METHODS[:1], "lif-iv-bv", *DEFAULT_METHODS[1:])))


def ocv_for(cell_dir: Path, ambient: str, ocv_from: str | None = None) -> tuple[OcvCurve, str]:
    """The ambient's own C/20, else its HPPC, else the nearest ambient's C/20; ``ocv_from``: that ambient's C/20."""
    if ocv_from is not None:
        if not (cell_dir / ocv_from / "c20_ocv.csv.gz").exists():
            raise FileNotFoundError(f"{cell_dir / ocv_from}: no C/20 test")
        return ambient_table(cell_dir / ocv_from).curve, f"C/20 at {ocv_from}"
    return ambient_ocv(cell_dir, ambient)


def drive_cycles(folder: Path) -> list[str]:
    names = sorted(p.name.removesuffix(".csv.gz") for p in folder.glob("*.csv.gz"))
    return [n for n in names if n not in NOT_DRIVE]


def jobs(data: Path, files: str = "*/*", ocv_from: str | None = None) -> list[tuple]:
    out = []
    for cell in sorted(STATED_AH):
        if not (data / cell).is_dir():
            print(f"{data / cell}: absent, {cell} not run", file=sys.stderr)
            continue
        for amb in sorted((d.name for d in (data / cell).iterdir() if d.is_dir()), key=ambient_c, reverse=True):
            if not fnmatch(f"{cell}/{amb}", files) or amb == ocv_from:
                continue
            names = drive_cycles(data / cell / amb)
            out += [(cell, amb, tr, [v for v in names if v != tr], ocv_from) for tr in names if len(names) > 1]
    return out


def one(job, methods=TABLE_METHODS) -> list[dict]:
    cell, amb, train, vals, ocv_from = job
    data = shared_data_dir()
    ocv, ocv_source = ocv_for(data / cell, amb, ocv_from)
    tr = load_recording(data / cell / amb / f"{train}.csv.gz")
    training = train_methods((tr.current_a, tr.voltage_v), ocv, STATED_AH[cell], dt_s=tr.dt_s, methods=methods,
                             name=train, temperature_c=tr.temperature_c)
    mid = (training.result.soc >= 0.2) & (training.result.soc <= 0.9)
    r_total = {}
    for m, run in training.runs.items():
        sel = mid & run.identified
        r = run.params["r0_ohm"] + run.params["r1_ohm"] + run.params["r2_ohm"]
        r_total[m] = float(1e3 * np.median(r[sel])) if sel.any() else float("nan")
    rows = []
    for val in vals:
        va = load_recording(data / cell / amb / f"{val}.csv.gz")
        res = validate_methods(training, (va.current_a, va.voltage_v), ocv, dt_s=va.dt_s, name=val,
                               temperature_c=va.temperature_c)
        inside = (res.soc >= 0.2) & (res.soc <= 0.9)
        rows.append({
            "cell": cell, "ambient": amb, "train": train, "validate": val, "ocv": ocv_source,
            "capacity_ah": training.capacity_ah,
            "val_mv": {m: rmse_mv(res.simulated_v[m], res.voltage_v, inside) for m in methods},
            # what explains a pair: the validation error's mean, the training model's R0+R1+R2 (20-90 %
            # SOC median), the RMS currents of both files
            "val_bias_mv": {m: float(1e3 * np.nanmean((res.simulated_v[m] - res.voltage_v)[inside]))
                            for m in methods},
            "train_r_total_mohm": r_total,
            "rms_current_a": [float(np.sqrt(np.mean(tr.current_a**2))), float(np.sqrt(np.mean(va.current_a**2)))],
        })
    return rows


def table(rows: list[dict], default_ct: str) -> str:
    methods = list(rows[0]["val_mv"])
    cts = [m for m in methods if m != "arx"]
    head = " | ".join(f"{LABEL[m]} [mV]" for m in methods)
    # the kinetic extension against the model it extends
    ext = [("lif-iv-bv", "lif-iv")] if {"lif-iv-bv", "lif-iv"} <= set(methods) else []
    lines = [
        "| cell | ambient | OCV | pairs | " + " | ".join(f"{LABEL[m]} median / worst [mV]" for m in methods)
        + " | " + " | ".join(f"{LABEL[m]} < DT" for m in cts)
        + "".join(f" | {LABEL[a]} < {LABEL[b]}" for a, b in ext) + f" | {LABEL[default_ct]} <= 15 mV |",
        "|---|---|---|---|" + "---|" * (len(methods) + len(cts) + len(ext) + 1),
    ]
    groups: dict[tuple[str, str], list[dict]] = {}
    for r in rows:
        groups.setdefault((r["cell"], r["ambient"]), []).append(r)
    for (cell, amb), rs in groups.items():
        figs = {m: [r["val_mv"][m] for r in rs] for m in methods}
        wins = {m: sum(r["val_mv"][m] < r["val_mv"]["arx"] for r in rs) for m in cts}
        lines.append(f"| {cell} | {amb} | {rs[0]['ocv']} | {len(rs)} | "
                     + " | ".join(f"{median(figs[m]):.1f} / {max(figs[m]):.1f}" for m in methods) + " | "
                     + " | ".join(f"{wins[m]} of {len(rs)}" for m in cts)
                     + "".join(f" | {sum(x < y for x, y in zip(figs[a], figs[b]))} of {len(rs)}" for a, b in ext)
                     + f" | {sum(f <= 15.0 for f in figs[default_ct])} of {len(rs)} |")
    total = {m: sum(r["val_mv"][m] < r["val_mv"]["arx"] for r in rows) for m in cts}
    lines.append("")
    others = [m for m in cts if m != default_ct]
    lines.append("All pairs: " + ", ".join(f"{LABEL[m]} below DT on {total[m]} of {len(rows)}" for m in cts)
                 + "; " + ", ".join(f"{LABEL[default_ct]} below {LABEL[m]} on "
                                    f"{sum(r['val_mv'][default_ct] < r['val_mv'][m] for r in rows)}" for m in others)
                 + f"; default CT method: {LABEL[default_ct]}.")
    lines += ["", "<details><summary>Every pair (validation simulation RMSE, 20-90 % SOC)</summary>", "",
              f"| cell | ambient | train -> validate | capacity [Ah] | {head} | best | RMS current train -> "
              f"val [A] | mean error {LABEL[default_ct]} / DT [mV] |",
              "|---|---|---|---|" + "---|" * len(methods) + "---|---|---|"]
    for r in rows:
        v = r["val_mv"]
        best = min(methods, key=lambda m: v[m])
        lines.append(f"| {r['cell']} | {r['ambient']} | {r['train']} -> {r['validate']} | {r['capacity_ah']:.3f} | "
                     + " | ".join(f"**{v[m]:.1f}**" if m == default_ct else f"{v[m]:.1f}" for m in methods)
                     + f" | {LABEL[best]} | {r['rms_current_a'][0]:.2f} -> {r['rms_current_a'][1]:.2f} | "
                     f"{r['val_bias_mv'][default_ct]:+.1f} / {r['val_bias_mv']['arx']:+.1f} |")
    lines += ["", "</details>"]
    return "\n".join(lines)


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--readme", action="store_true", help="write the table into README.md")
    ap.add_argument("--json", type=Path, default=None, help="also write every figure as JSON")
    ap.add_argument("--from-json", type=Path, default=None, help="make the table from such a JSON (no runs)")
    ap.add_argument("--jobs", type=int, default=2, help="worker processes (default 2)")
    ap.add_argument("--files", default="*/*", help="glob over cell/ambient, e.g. 'lg-hg2/0degC' (default: all)")
    ap.add_argument("--ocv-from", default=None, metavar="AMBIENT",
                    help="every file's OCV from this ambient's C/20 test (the ambient's own files are left out)")
    args = ap.parse_args()
    if args.readme and (args.files != "*/*" or args.ocv_from is not None):
        ap.error("--readme writes the README's table: every group, each with its own table")
    if args.from_json is not None:
        rows = json.loads(args.from_json.read_text())
    else:
        data = shared_data_dir()
        if data is None:
            print("../shared/data not found (set BMS_SHARED_DATA)", file=sys.stderr)
            return 2
        with ProcessPoolExecutor(args.jobs) as pool:
            rows = [r for rs in pool.map(one, jobs(data, args.files, args.ocv_from)) for r in rs]
        if not rows:
            print(f"no drive cycle pairs match --files {args.files!r}", file=sys.stderr)
            return 2
    if args.json is not None:
        args.json.write_text(json.dumps(rows, indent=1) + "\n")
    text = table(rows, IDENTIFICATION_METHOD)
    print(text)
    if args.readme:
        write_readme_section(text, BEGIN, END)
    return 0


def write_readme_section(text: str, begin: str, end: str) -> None:
    """Replace what README.md holds between the markers ``begin`` and ``end`` by ``text``."""
    readme = ROOT / "README.md"
    new = re.sub(f"{re.escape(begin)}.*?{re.escape(end)}", f"{begin}\n{text}\n{end}", readme.read_text(), flags=re.S)
    readme.write_text(new)
    print(f"updated {readme}")


if __name__ == "__main__":
    sys.exit(main())
