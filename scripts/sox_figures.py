"""The README's SOP/SOE/SOH figures on the Panasonic 18650PF data: one command.

    PYTHONPATH=. python scripts/sox_figures.py [--data ../shared/data] [--out docs/sox] [--jobs 2]

For every Panasonic file (HPPC and drive cycles at 25, 10, 0, -10 degC) it runs the
SOP back-test of ``bms-estimator sop-backtest`` (bms_estimator.sop_backtest) with the four
OCV tables (25 degC C/20 shipped sample; HPPC-rest tables at the others, made here with
``bms-estimator ocv``), 2.9 Ah stated, 10 s horizon, the files' logging gaps rested over as the
service would (the command's default, bms_estimator.sop_backtest "Logging gaps"), and writes:

    <out>/sox_results.json   every file's summary plus the SOE and SOH rows
    <out>/cache/*.json       each file's result (a re-run reuses them; delete to recompute)
    <out>/sox_tables.md      the README tables
    <out>/hppc_error.png     |10 s voltage error| of the HPPC pulses by SOC, per temperature
    <out>/soe_error.png      SOE error against the energy delivered to the cut-off, as the drive goes on

Data: P. Kollmeyer, "Panasonic 18650PF Li-ion Battery Data", Mendeley Data, v1, 2018,
doi:10.17632/wykht8y7tg.1, CC BY 4.0.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bms_estimator.cli.common import load_ocv  # noqa: E402
from bms_estimator.core.sop import SopConfig  # noqa: E402
from bms_estimator.data import load_recording, shared_data_dir  # noqa: E402
from bms_estimator.jsonsafe import to_jsonable  # noqa: E402
from bms_estimator.sop_backtest import run_backtest, summary  # noqa: E402

CELL = "panasonic-18650pf"
TEMPS = ("25degC", "10degC", "0degC", "n10degC")
CAPACITY_AH = 2.9
STRICT_V_MIN = (3.0, 3.2)


def _ocv_tables(data: Path, out: Path) -> list[Path]:
    tables = [REPO / "bms_estimator" / "samples" / f"{CELL}_25degC_ocv.csv"]
    for t in TEMPS[1:]:
        path = out / f"ocv_{t}.csv"
        if not path.exists():
            subprocess.run([sys.executable, "-m", "bms_estimator.cli", "ocv", str(data / CELL / t / "hppc.csv.gz"),
                            "--hppc-steps", str(data / CELL / t / "hppc_steps.csv.gz"), "-o", str(path)],
                           check=True, cwd=REPO)
        tables.append(path)
    return tables


def _one(args: tuple[Path, list[Path], Path]) -> dict:
    path, tables, cache_dir = args
    cache = cache_dir / f"{path.parent.name}_{path.name}.json"
    if cache.exists():
        return json.loads(cache.read_text())
    rec = load_recording(path, resample_s=1.0)
    ocv = load_ocv(tables, rec)
    res = run_backtest(rec.current_a, rec.voltage_v, rec.temperature_c, rec.dt_s, ocv, CAPACITY_AH,
                       horizon_s=10.0, initial_soc=1.0, sop_config=SopConfig(), extra_v_min=STRICT_V_MIN,
                       time_s=rec.time_s, unlogged=rec.filled)  # the logging gaps rested over, as the service
    out = summary(res, CAPACITY_AH)
    out["file"] = f"{path.parent.name}/{path.name}"
    q_out = float(-np.sum(np.minimum(rec.current_a, 0.0)) * rec.dt_s / 3600.0)
    q_in = float(np.sum(np.maximum(rec.current_a, 0.0)) * rec.dt_s / 3600.0)
    out["ah_discharged_net"] = q_out - q_in
    out["rows"] = {"start_s": res.start_s, "soc": res.soc, "current_a": res.current_a, "error_mv": res.error_mv,
                   "energy_left_wh": res.energy_left_wh, "energy_to_end_wh": res.energy_to_end_wh,
                   "i_dis_a": res.i_dis_a, "i_dis_hppc_a": res.i_dis_hppc_a, "v_meas": res.v_meas}
    out = to_jsonable(out)
    cache.write_text(json.dumps(out))  # a file's result survives an interrupted run
    return out


def _tables(results: list[dict]) -> str:
    lines = ["### HPPC: 10 s end-of-pulse voltage error (|predicted - measured|, mV)", "",
             "| ambient | pulses | median | p95 | by C-rate (median) |", "|---|---|---|---|---|"]
    for r in results:
        if r["mode"] != "hppc":
            continue
        c = np.abs(np.asarray(r["rows"]["current_a"], float)) / CAPACITY_AH  # of the stated capacity
        err = np.abs(np.asarray(r["rows"]["error_mv"], float))
        by_rate = ", ".join(f"{lo:g}-{hi:g}C {np.median(err[(c >= lo) & (c < hi)]):.0f}"
                            for lo, hi in ((0.4, 0.75), (0.75, 1.5), (1.5, 3.0), (3.0, 5.0), (5.0, 7.0))
                            if np.any((c >= lo) & (c < hi)))
        lines.append(f"| {r['file'].split('/')[0]} | {r['windows']} | {r['voltage_error_mv']['median']:.1f} | "
                     f"{r['voltage_error_mv']['p95']:.1f} | {by_rate} |")
    lines += ["", "### HPPC: median |error| by SOC band (mV)", "",
              "| ambient | " + " | ".join(f"{lo / 10:.1f}-{(lo + 1) / 10:.1f}" for lo in range(10)) + " |",
              "|---|" + "---|" * 10]
    for r in results:
        if r["mode"] != "hppc":
            continue
        cells = []
        for lo in range(10):
            key = f"{lo / 10:.1f}-{(lo + 1) / 10:.1f}"
            v = r["abs_error_mv_by_soc"].get(key)
            cells.append(f"{v['median']:.0f}" if v else "-")
        lines.append(f"| {r['file'].split('/')[0]} | " + " | ".join(cells) + " |")
    lines += ["", "### Drive cycles: every 10 s window", "",
              "| file | windows | median / p95 \\|error\\| mV | within limit | exceeded (2.5 / 4.2 V) | exceeded at v_min 3.0 V / 3.2 V "
              "(HPPC method at 2.5 V) | median limit model / HPPC A |",
              "|---|---|---|---|---|---|---|"]
    for r in results:
        if r["mode"] != "drive":
            continue
        strict = r.get("limit_exceeded_at_v_min", {})
        s = " / ".join(f"{strict[k]['limit_exceeded']} of {strict[k]['windows_within_limit']}" for k in strict)
        lines.append(f"| {r['file']} | {r['windows']} | {r['voltage_error_mv']['median']:.1f} / "
                     f"{r['voltage_error_mv']['p95']:.1f} | {r['windows_within_limit']} | {r['limit_exceeded']} | {s} "
                     f"({r['hppc_method']['limit_exceeded']}) | {r['discharge_limit_a']['model']['median']:.1f} / "
                     f"{r['discharge_limit_a']['hppc']['median']:.1f} |")
    return "\n".join(lines) + "\n"


def _soe_drives(results: list[dict]):
    """(file, energy left, energy delivered to the end) of each drive that ended at the 2.5 V
    cut-off (the 25 and 10 degC files; the colder ones stop at a depth of discharge)."""
    for r in results:
        if r["mode"] == "drive" and r["file"].startswith(("25degC", "10degC")):
            rows = r["rows"]
            yield r["file"], np.asarray(rows["energy_left_wh"], float), np.asarray(rows["energy_to_end_wh"], float)


def _soe_rows(results: list[dict]) -> list[dict]:
    """SOE error (predicted energy left - energy delivered to the end) at 10..90 % of each drive."""
    out = []
    for name, e_left, e_end in _soe_drives(results):
        total = e_end[0]
        row = {"file": name, "energy_total_wh": float(total)}
        for frac in (0.1, 0.3, 0.5, 0.7, 0.9):
            k = int(np.argmin(np.abs((total - e_end) / total - frac)))
            row[f"{int(frac * 100)}%"] = float(e_left[k] - e_end[k])
        out.append(row)
    return out


def _soh_rows(results: list[dict]) -> list[dict]:
    return [{"file": r["file"], "capacity_ah_estimated": r["capacity_ah_estimated"],
             "ah_discharged": r["ah_discharged_net"], "temperature_c": r["temperature_c_median"]}
            for r in results if r["mode"] == "drive"]


def _plots(results: list[dict], out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4))
    for r in results:
        if r["mode"] != "hppc":
            continue
        rows = r["rows"]
        ax.scatter(100 * np.asarray(rows["soc"], float), np.abs(np.asarray(rows["error_mv"], float)), s=12,
                   label=r["file"].split("/")[0])
    ax.set_yscale("log")
    ax.set_xlabel("estimated SOC at the pulse (%)")
    ax.set_ylabel("|10 s voltage error| (mV)")
    ax.axhline(10, color="k", lw=0.5)
    ax.legend()
    ax.set_title("SOP back-test, Panasonic 18650PF HPPC pulses (Kollmeyer 2018, CC BY 4.0)", fontsize=8)
    fig.tight_layout()
    fig.savefig(out / "hppc_error.png", dpi=110)
    plt.close(fig)
    fig, ax = plt.subplots(figsize=(7, 4))
    for name, e_left, e_end in _soe_drives(results):
        ax.plot(100 * (1 - e_end / e_end[0]), e_left - e_end, lw=0.8, label=name)
    ax.set_xlabel("energy delivered so far (% of the drive's total)")
    ax.set_ylabel("SOE - energy delivered to cut-off (Wh)")
    ax.axhline(0, color="k", lw=0.5)
    ax.legend(fontsize=6)
    ax.set_title("SOE back-test, Panasonic 18650PF drive cycles (Kollmeyer 2018, CC BY 4.0)", fontsize=8)
    fig.tight_layout()
    fig.savefig(out / "soe_error.png", dpi=110)
    plt.close(fig)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=shared_data_dir() or REPO.parent / "shared" / "data")
    ap.add_argument("--out", type=Path, default=REPO / "docs" / "sox")
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--only", default="", help="substring of the files to run (default: all)")
    ap.add_argument("--cached-only", action="store_true",
                    help="make the tables and plots from the files already in <out>/cache only")
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    files = sorted(p for t in TEMPS for p in (args.data / CELL / t).glob("*.csv.gz")
                   if "c20" not in p.name and "hppc_steps" not in p.name and args.only in str(p))
    # HPPC first, then one drive cycle per ambient before the rest (an interrupted run still covers them)
    first = ("us06", "la92")
    files.sort(key=lambda p: ("hppc" not in p.name, not any(p.name.startswith(f) for f in first),
                              TEMPS.index(p.parent.name), p.name))
    if not files:  # a checkout without the data set: say so, and leave the committed tables and figures alone
        print(f"no Panasonic files under {args.data / CELL} (give --data, the measured data set's folder); "
              f"nothing written", file=sys.stderr)
        return 2
    tables = _ocv_tables(args.data, args.out)
    cache_dir = args.out / "cache"
    cache_dir.mkdir(exist_ok=True)
    if args.cached_only:
        files = [p for p in files if (cache_dir / f"{p.parent.name}_{p.name}.json").exists()]
        if not files:
            print(f"--cached-only: no cached result in {cache_dir}; nothing written", file=sys.stderr)
            return 2
    with ProcessPoolExecutor(max_workers=args.jobs) as pool:
        results = list(pool.map(_one, [(p, tables, cache_dir) for p in files]))
    for r in results:
        print(f"{r['file']}: {r['mode']} {r['windows']} windows, median |err| {r['voltage_error_mv']['median']:.1f} mV, "
              f"exceeded {r['limit_exceeded']}", flush=True)
    doc = {"results": results, "soe": _soe_rows(results), "soh": _soh_rows(results)}
    (args.out / "sox_results.json").write_text(json.dumps(to_jsonable(doc)) + "\n")
    md = _tables(results)
    md += "\n### SOE error (Wh) as the drive goes on\n\n| file | total Wh | 10 % | 30 % | 50 % | 70 % | 90 % |\n|---|---|---|---|---|---|---|\n"
    for row in doc["soe"]:
        md += (f"| {row['file']} | {row['energy_total_wh']:.2f} | "
               + " | ".join(f"{row[k]:+.2f}" for k in ("10%", "30%", "50%", "70%", "90%")) + " |\n")
    md += "\n### Capacity estimate per drive cycle\n\n| file | median T degC | estimated Ah | Ah discharged (net) |\n|---|---|---|---|\n"
    for row in doc["soh"]:
        md += (f"| {row['file']} | {row['temperature_c']:.1f} | {row['capacity_ah_estimated']:.3f} | "
               f"{row['ah_discharged']:.3f} |\n")
    (args.out / "sox_tables.md").write_text(md)
    _plots(results, args.out)
    print(f"wrote {args.out}/sox_results.json, sox_tables.md, hppc_error.png, soe_error.png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
