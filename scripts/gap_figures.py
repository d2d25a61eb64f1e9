"""The README's "Across a gap" figures: the SOC estimator over a recording whose long rests are cut out. One command.

    PYTHONPATH=. python scripts/gap_figures.py [--data ../shared/data] [--out docs/gap]

The Panasonic 18650PF 25 degC HPPC file (27 h): pulse sets at SOC steps from full to empty,
five pulses 1200 s apart in each; between the sets the cell is discharged by a step and rests,
which this file does not log (13 logging gaps of 1950-3750 s; ``hppc_steps`` logs them, on
its own time axis).  The gateway of a parked car is asleep the same way.  Samples at 1 s
(``load_recording``: the logging gaps filled with zero current and the voltage interpolated).

Reference SOC: coulomb counting of every logged sample plus the charge each discharge step
removed inside its logging gap (``hppc_gap_charges``: the alignment ``ocv --hppc-steps`` uses),
spread over the gap, from full; with the C/20 table's capacity, and with the reference capacity
of ``bms_estimator/scoring.py`` (the final rest read on the C/20 discharge branch).  Counting
the file's own samples alone misses the steps' 1.46 Ah (half the cell).

Runs (the estimator's defaults, ``ekf``, OCV from the same folder's ``c20_ocv``, 2.9 Ah stated),
from full and from 20 % low:

* ``full``: every 1 s sample (the file as ``bms-estimator soc`` reads it).
* ``holes``: every rest longer than 10 min (``|i| < 0.01 A``; the logging gaps lie inside
  such rests) removed but for its last 10 s (the gateway wakes with the ignition), the samples
  fed one after the other, as the service saw them before: the gap read as one period.
* ``holes+rest``: the same, with ``SocEstimator.rest`` over each hole (``rest_soc_reading`` "ocv",
  the default, and "fused"; and with ``rest_relaxation_s`` 600 s instead of 1800 s, so that the
  1200 s rests between the pulses are read too).

* ``logging gaps`` / ``logging gaps+rest``: only the 13 logging gaps as holes (where this logger
  itself was off), without and with ``rest``.

Scored on the samples every run sees (the kept ones outside the logging gaps): RMSE over all of
them and the largest |error| from 30 min on (``soc_error_figures``), in % SOC.  Writes ``<out>/gap_results.json``, ``<out>/gap_table.md`` and
``<out>/hppc_gap.png``.

Also the LG HG2 25 degC UDDS file cut in two, the second half's first 20 min removed: a gap that was
driven, not parked, the case ``rest`` does not model (it is told zero current and the first sample
after the cut is under load, so nothing is read), scored against ``scoring.py``'s reference.

Data: P. Kollmeyer, "Panasonic 18650PF Li-ion Battery Data", Mendeley Data, v1, 2018,
doi:10.17632/wykht8y7tg.1, CC BY 4.0.  P. Kollmeyer, C. Vidal, M. Naguib, M. Skells, "LG 18650HG2
Li-ion Battery Data", Mendeley Data, v3, 2020, doi:10.17632/cp3473x7xv.3, CC BY 4.0.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bms_estimator.analysis import run_soc  # noqa: E402
from bms_estimator.core.ocv import hppc_gap_charges  # noqa: E402
from bms_estimator.core.soc import SocConfig  # noqa: E402
from bms_estimator.data import load_recording, shared_data_dir  # noqa: E402
from bms_estimator.scoring import counted_soc, soc_error_figures, soc_reference  # noqa: E402
from bms_estimator.soc_matrix import ambient_table  # noqa: E402

CELL, AMBIENT, STATED_AH = "panasonic-18650pf", "25degC", 2.9
REST_A = 0.01  # |current| below this is rest
ASLEEP_AFTER_S = 600  # a rest longer than this is cut out
AWAKE_S = 10  # of it, the last seconds are kept: the gateway wakes before the current flows


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """[start, end) of the runs of True."""
    d = np.diff(np.r_[0, mask.astype(np.int8), 0])
    return list(zip(np.flatnonzero(d == 1), np.flatnonzero(d == -1)))


def experiment(data: Path) -> dict:
    folder = data / CELL / AMBIENT
    native = load_recording(folder / "hppc.csv.gz", resample_s=None)
    steps = load_recording(folder / "hppc_steps.csv.gz", resample_s=None)
    rec = load_recording(folder / "hppc.csv.gz", resample_s=1.0)
    table = ambient_table(folder)
    curve = table.curve
    q_c20 = float(curve.capacity_discharge_ah)
    n = len(rec.current_a)
    t = np.arange(n, dtype=float)

    # where the logger was off, and the step charge it did not log there (Ah), spread over the gap's bins
    gaps, gap_q, _ = hppc_gap_charges((native.time_s, native.current_a, native.voltage_v),
                                      (steps.time_s, steps.current_a, steps.voltage_v))
    logged = np.ones(n, dtype=bool)
    i_ref = rec.current_a.copy()
    for g, q in zip(gaps, gap_q):
        a, b = int(np.ceil(native.time_s[g])), int(np.floor(native.time_s[g + 1]))
        logged[a:b] = False
        i_ref[a:b] += q * 3600.0 / (b - a)
    refs = {"c20": (counted_soc(i_ref, 1.0, q_c20, 1.0), q_c20)}
    try:
        sr = soc_reference(i_ref, rec.voltage_v, 1.0, curve)
        refs["scoring"] = (sr.soc, sr.capacity_ah)
        scoring_note = sr.why
    except ValueError as exc:
        scoring_note = f"does not apply: {exc}"

    # the rests the gateway sleeps through
    keep = np.ones(n, dtype=bool)
    holes = []
    for a, b in _runs(np.abs(rec.current_a) < REST_A):
        if b - a > ASLEEP_AFTER_S and b < n:  # (the final rest: nothing follows it to wake for)
            keep[a:b - AWAKE_S] = False
            holes.append((a, b - AWAKE_S))
    idx = np.flatnonzero(keep)
    rest_s = np.zeros(idx.size)
    jump = np.flatnonzero(np.diff(idx) > 1) + 1
    rest_s[jump] = np.diff(idx)[jump - 1] - 1.0
    scored_full = keep & logged

    out = {"file": str(folder / "hppc.csv.gz"), "samples": n, "kept": int(idx.size), "holes": len(holes),
           "hole_s": float(sum(b - a for a, b in holes)), "logging_gaps": int(gaps.size),
           "step_charge_ah": float(gap_q.sum()), "capacity_c20_ah": q_c20,
           "capacity_scoring_ah": refs["scoring"][1] if "scoring" in refs else None,
           "scoring_reference": scoring_note, "runs": {}, "traces": {}}
    # the logging gaps alone as holes (where this logger itself was off)
    idx_log = np.flatnonzero(logged)
    rest_log = np.zeros(idx_log.size)
    jump = np.flatnonzero(np.diff(idx_log) > 1) + 1
    rest_log[jump] = np.diff(idx_log)[jump - 1] - 1.0
    cases = {
        "full": (np.arange(n), None, SocConfig()),
        "logging gaps": (idx_log, None, SocConfig()),
        "logging gaps+rest": (idx_log, rest_log, SocConfig()),
        "holes": (idx, None, SocConfig()),
        "holes+rest": (idx, rest_s, SocConfig()),
        "holes+rest fused": (idx, rest_s, SocConfig(rest_soc_reading="fused")),
        "holes+rest 10 min": (idx, rest_s, SocConfig(rest_relaxation_s=600.0)),
    }
    for start_name, soc0 in (("correct start", 1.0), ("20 % low", 0.8)):
        for name, (rows, rests, cfg) in cases.items():
            run = run_soc(rec.current_a[rows], rec.voltage_v[rows], curve, STATED_AH, soc0, 1.0, cfg,
                          rest_s=rests)
            scored = scored_full[rows]  # the samples every run sees
            row = {}
            for ref_name, (ref, _) in refs.items():
                fig = soc_error_figures(run.soc[scored], ref[rows][scored], t[rows][scored], 0.0)
                row[ref_name] = {"rmse_pct": fig["rmse_all_pct"], "max_abs_pct": fig["max_abs_pct"]}
            out["runs"][f"{name} | {start_name}"] = row
            out["traces"][f"{name} | {start_name}"] = (t[rows][scored], 100.0 * (run.soc - refs["c20"][0][rows])[scored])
            print(f"{name:17s} {start_name:14s} " + "  ".join(
                f"{k}: RMSE {v['rmse_pct']:.2f} %, max {v['max_abs_pct']:.2f} %" for k, v in row.items()), flush=True)
    return out


def drive_cut(data: Path) -> dict:
    """The LG HG2 25 degC UDDS file cut in two, the second half's first 20 min removed: a gap that was
    *driven*, not parked (the gateway off while the car ran), the case ``rest`` does not model."""
    folder = data / "lg-hg2" / "25degC"
    rec = load_recording(folder / "udds.csv.gz", resample_s=1.0)
    curve = ambient_table(folder).curve
    ref = soc_reference(rec.current_a, rec.voltage_v, 1.0, curve)
    n = len(rec.current_a)
    half, cut = n // 2, 1200
    keep = np.ones(n, dtype=bool)
    keep[half:half + cut] = False
    idx = np.flatnonzero(keep)
    rest_s = np.zeros(idx.size)
    rest_s[half] = float(cut)
    t = np.arange(n, dtype=float)
    out = {"file": str(folder / "udds.csv.gz"), "samples": n, "removed_s": cut,
           "unseen_charge_ah": float(np.sum(rec.current_a[half:half + cut]) / 3600.0),
           "reference_capacity_ah": ref.capacity_ah, "reference": ref.why, "runs": {}}
    for name, rows, rests in (("every sample", np.arange(n), None), ("cut", idx, None), ("cut+rest", idx, rest_s)):
        run = run_soc(rec.current_a[rows], rec.voltage_v[rows], curve, 3.0, 1.0, 1.0, SocConfig(), rest_s=rests)
        after = t[rows] >= half + cut
        err = 100.0 * (run.soc - ref.soc[rows])[after]
        out["runs"][name] = {"rmse_pct": float(np.sqrt(np.mean(err**2))), "max_abs_pct": float(np.max(np.abs(err))),
                             "at_60s_pct": float(err[60]), "at_30min_pct": float(err[1800])}
        print(f"LG udds {name:13s} after the cut: " + ", ".join(f"{k} {v:.2f}" for k, v in out["runs"][name].items()),
              flush=True)
    return out


def table_md(res: dict) -> str:
    refs = list(next(iter(res["runs"].values())).keys())
    head = "| run | start | " + " | ".join(f"RMSE, max ({r}) %" for r in refs) + " |"
    lines = [head, "|---|---|" + "---|" * len(refs)]
    for key, row in res["runs"].items():
        name, start = key.split(" | ")
        lines.append(f"| {name} | {start} | " + " | ".join(
            f"{row[r]['rmse_pct']:.2f}, {row[r]['max_abs_pct']:.2f}" for r in refs) + " |")
    cut = res.get("drive_cut")
    if cut:
        lines += ["", f"LG HG2 25 degC UDDS, {cut['removed_s']} s of driving removed at the middle "
                      f"({cut['unseen_charge_ah']:.3f} Ah unseen), from the cut on:", "",
                  "| run | RMSE % | max % | at +60 s % | at +30 min % |", "|---|---|---|---|---|"]
        for name, r in cut["runs"].items():
            lines.append(f"| {name} | {r['rmse_pct']:.2f} | {r['max_abs_pct']:.2f} | {r['at_60s_pct']:.2f} | "
                         f"{r['at_30min_pct']:.2f} |")
    return "\n".join(lines) + "\n"


def plot(res: dict, path: Path) -> None:
    import matplotlib.pyplot as plt

    from bms_estimator.plots import save_figure

    fig, axes = plt.subplots(2, 1, figsize=(10, 6.5), sharex=True)
    for ax, start in zip(axes, ("correct start", "20 % low")):
        for name in ("full", "holes", "holes+rest"):
            tt, err = res["traces"][f"{name} | {start}"]
            ax.plot(tt / 3600.0, err, ".", ms=1.5, label=name)
        ax.axhline(0, color="k", lw=0.5)
        ax.set_ylabel("SOC error, % (C/20 ref.)")
        ax.set_title(f"Panasonic 18650PF 25 degC HPPC, {start}", fontsize=10)
        ax.legend(markerscale=6, fontsize=8)
    axes[-1].set_xlabel("time in the test, h")
    save_figure(fig, path, "Data: P. Kollmeyer, Panasonic 18650PF Li-ion Battery Data, Mendeley Data, CC BY 4.0")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", type=Path, default=None, help="the measured data set (default: ../shared/data)")
    p.add_argument("--out", type=Path, default=REPO / "docs" / "gap")
    args = p.parse_args(argv)
    data = args.data or shared_data_dir()
    if data is None:
        print("the measured data set is not there (--data, or ../shared/data)", file=sys.stderr)
        return 3
    need = [Path(data) / CELL / AMBIENT / "hppc.csv.gz", Path(data) / "lg-hg2" / "25degC" / "udds.csv.gz"]
    missing = [str(p) for p in need if not p.exists()]
    if missing:
        print(f"the figures need {', '.join(missing)} of the measured data set, not there", file=sys.stderr)
        return 3
    res = experiment(Path(data))
    res["drive_cut"] = drive_cut(Path(data))
    args.out.mkdir(parents=True, exist_ok=True)
    plot(res, args.out / "hppc_gap.png")
    (args.out / "gap_table.md").write_text(table_md(res))
    res.pop("traces")
    (args.out / "gap_results.json").write_text(json.dumps(res, indent=2) + "\n")
    print(f"wrote {args.out}/gap_results.json, gap_table.md, hppc_gap.png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
