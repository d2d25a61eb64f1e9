"""The SOC matrix: every drive cycle of a cell, four starts, scored against the independent reference.

Starts (the estimator is told the start SOC; the reference is always counted from
the file's full start, :mod:`bms_estimator.scoring`):

* ``full``      at t = 0 with SOC 1.0 (right)
* ``full-20``   at t = 0 with SOC 0.8 (20 % low)
* ``mid+10``    at 25 % of the file with the reference + 10 %
* ``mid-10``    at 25 % of the file with the reference - 10 %

and, asked for by name (``--starts``), ``atP+E`` / ``atP-E``: at P % of the file
with the reference + or - E % (``at75-5``: three quarters through, 5 % low), the
starts a hidden recording may bring that the four above do not; and ``ocv``: at
t = 0 with the SOC read from the first sample's voltage (the files start at rest),
as the service starts after a rest and ``soc --start-soc ocv`` does; ``atPocv``: at P % of
the file with the SOC read from the voltage there, under load (a gateway started mid-drive
without a state, ``soc --start-s T --start-soc ocv``).

OCV: every table the cell has (C/20 tests, and HPPC rests where an ambient has no
C/20 test), interpolated by the cell temperature.  Where the file's own ambient
has a table, the run is repeated with that table left out (``own table out``), as
hidden recordings at other ambients will be run.  Beside each run: plain coulomb
counting with the stated capacity from the same start.

All files x starts of one cell run as the cells of one vectorised estimator
(shorter files are padded with invalid samples).  A file's logging gaps (no sample
for longer than the service's sampler bridges) are rested over as the service rests
over a time jump (:func:`bms_estimator.gaps.rest_plan`; ``rest_over_gaps=False``:
fed as ``load_recording`` fills them): its starts then run as an estimator of their
own, not fed inside a gap (the estimate held there, and scored over every sample of
the file as before) and rested before the sample after it; a start inside a gap
begins at the next logged sample.  ``scripts/soc_matrix.py``
writes the README table from it; ``tests/core/test_measured_soc.py`` checks it.
"""

from __future__ import annotations

import fnmatch
import re
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import NamedTuple

import numpy as np

from .core.ocv import OcvCurve
from .core.ocv_surface import OcvSurface
from .core.soc import SocConfig, SocEstimator
from .data import load_recording
from .gaps import RestPlan, recording_rest_plan
from .scoring import SocReference, counted_soc, soc_error_figures, soc_reference

__all__ = ["CELLS", "STARTS", "ambient_c", "ambient_ocv", "ambient_table", "build_tables", "check_start", "file_reference", "run_cell", "start_point", "summary_lines", "summary_table",
           "markdown"]

CELLS = {"lg-hg2": 3.0, "panasonic-18650pf": 2.9}  # stated (nominal) capacity, Ah
STARTS = ("full", "full-20", "mid+10", "mid-10")
DRIVE_SKIP = ("c20_ocv", "hppc", "hppc_steps")


def ambient_c(folder: str) -> float:
    return -float(folder[1:-4]) if folder.startswith("n") else float(folder[:-4])


@dataclass
class Table:
    ambient: str
    kind: str  # "c20" or "hppc"
    curve: OcvCurve
    temperature_c: float


def ambient_table(amb_dir: Path) -> Table | None:
    """An ambient folder's OCV table: its C/20 test, else its HPPC rests (None: it has neither)."""
    c20, hppc, steps = amb_dir / "c20_ocv.csv.gz", amb_dir / "hppc.csv.gz", amb_dir / "hppc_steps.csv.gz"
    if c20.exists():
        r = load_recording(c20, resample_s=None)
        curve = OcvCurve.from_c20(r.time_s, r.current_a, r.voltage_v)
        kind = "c20"
    elif hppc.exists() and steps.exists():
        r = load_recording(hppc, resample_s=None)
        s = load_recording(steps, resample_s=None)
        curve = OcvCurve.from_hppc((r.time_s, r.current_a, r.voltage_v), (s.time_s, s.current_a, s.voltage_v))
        kind = "hppc"
    else:
        return None
    t = float(np.median(r.temperature_c)) if r.temperature_c is not None else ambient_c(amb_dir.name)
    return Table(amb_dir.name, kind, curve, t)


def ambient_ocv(cell_dir: Path, ambient: str) -> tuple[OcvCurve, str]:
    """An ambient's OCV table and where it came from: its own C/20 test, else its HPPC rests, else
    the C/20 test of the nearest ambient that has one (a recording at a temperature the cell was
    not characterised at).  Raises FileNotFoundError when the cell has no C/20 test at all."""
    table = ambient_table(cell_dir / ambient)
    if table is not None:
        return table.curve, "C/20" if table.kind == "c20" else "HPPC"
    others = [d.name for d in cell_dir.iterdir() if (d / "c20_ocv.csv.gz").exists()]
    if not others:
        raise FileNotFoundError(f"{cell_dir / ambient}: no OCV test here, and {cell_dir} has no C/20 test at any ambient")
    near = min(others, key=lambda a: abs(ambient_c(a) - ambient_c(ambient)))
    return ambient_table(cell_dir / near).curve, f"C/20 at {near}"


def build_tables(data: Path, cell: str) -> list[Table]:
    """Every OCV table of a cell: its C/20 tests, and HPPC rests where an ambient has no C/20 test."""
    tables = (ambient_table(amb_dir) for amb_dir in sorted((data / cell).iterdir()))
    return [t for t in tables if t is not None]


def make_ocv(tables: list[Table]) -> OcvSurface:
    """The estimator's OCV from several tables: OCV(soc, T)."""
    return OcvSurface([t.curve for t in tables], [t.temperature_c for t in tables])


def jittered(table: Table, sigma_v: float, seed: int) -> Table:
    """``table`` with every OCV knot moved by an independent normal error of ``sigma_v`` (the seed and the
    table's ambient pick the draw), kept strictly increasing (a knot that would fall to or below the one
    before it is set a microvolt above it); the hysteresis and capacities as they are."""
    c = table.curve
    rng = np.random.default_rng([seed, int(round(100 * abs(table.temperature_c))), len(c.ocv_v)])
    v = c.ocv_v + sigma_v * rng.standard_normal(c.ocv_v.size)
    for k in range(1, v.size):
        v[k] = max(v[k], v[k - 1] + 1e-6)
    curve = OcvCurve(c.soc, v, c.hysteresis_v, capacity_discharge_ah=c.capacity_discharge_ah,
                     capacity_charge_ah=c.capacity_charge_ah, temperature_c=c.temperature_c)
    return replace(table, curve=curve)


def estimator_config(method: str, overrides: dict | None = None) -> SocConfig:
    """The default SocConfig with ``soc_method`` and settings to try (``"ekf.voltage_sigma_v": 0.01``)."""
    cfg = SocConfig(soc_method=method)
    for key, value in (overrides or {}).items():
        if "." in key:
            part, name = key.split(".", 1)
            cfg = cfg.with_(**{part: replace(getattr(cfg, part), **{name: value})})
        else:
            cfg = cfg.with_(**{key: value})
    return cfg


class GroupRun(NamedTuple):
    """What :func:`run_group` returns: per sample and cell (n_max, n_cells), NaN before a start."""

    soc: np.ndarray
    soc_sigma: np.ndarray  # the estimator's 1-sigma SOC uncertainty (NaN where the method reports none)
    capacity_ah: np.ndarray  # (n_cells,) the capacity the count uses at the end


def run_group(recs: list, starts: list[tuple[int, float]], ocv, stated_ah: float, config: SocConfig,
              rest_over_gaps: bool = True, plans: list[RestPlan] | None = None) -> GroupRun:
    """One estimator, one cell per (recording, start), run over the samples of all of them.

    With ``rest_over_gaps`` a recording's logging gaps are rested over as the service rests over a
    time jump (:func:`bms_estimator.gaps.rest_plan`): their samples are not fed (the estimate held,
    as ``soc`` traces it) and before the first sample after one, every cell of that recording that
    has begun rests over it (``SocEstimator.rest``).  A cell not fed must not be updated at all, so
    the starts of a recording with gaps run as the cells of an estimator of their own; the others
    share one.  A start must be on a fed sample (:func:`start_point` moves one in a gap to the next).
    ``plans``: each recording's :func:`~bms_estimator.gaps.recording_rest_plan`, where the caller has them.
    """
    if plans is None:
        plans = [recording_rest_plan(r, rest_over_gaps) for r in recs]
    parts: dict[int | None, list[int]] = {}
    for c, (r, plan) in enumerate(zip(recs, plans)):
        parts.setdefault(id(r) if plan.gaps or plan.not_fed else None, []).append(c)
    n_max = max(len(r) for r in recs)
    out = np.full((n_max, len(recs)), np.nan)
    sigma = np.full((n_max, len(recs)), np.nan)
    capacity = np.full(len(recs), np.nan)
    for key, cells in parts.items():
        plan = None if key is None else plans[cells[0]]
        run = _run_cells([recs[c] for c in cells], [starts[c] for c in cells], ocv, stated_ah, config, plan, n_max)
        out[:, cells] = run.soc
        sigma[:, cells] = run.soc_sigma
        capacity[cells] = run.capacity_ah
    return GroupRun(out, sigma, capacity)


def _run_cells(recs: list, starts: list[tuple[int, float]], ocv, stated_ah: float, config: SocConfig,
               plan: RestPlan | None, n_max: int) -> GroupRun:
    """:func:`run_group`'s cells of one estimator over ``n_max`` samples: every sample fed (``plan`` None), or
    the samples of one recording by its ``plan``; past a recording's end, invalid samples.  (Every estimator
    runs to the group's longest recording, as the one estimator did before the gaps were rested over: the c0
    method's capacity keeps taking anchors from a stable c0 window after a file's end, so its end capacity
    depends on how long the group runs on.)"""
    n_cells = len(recs)
    cur = np.full((n_max, n_cells), np.nan)
    vol = np.full((n_max, n_cells), np.nan)
    tmp = np.full((n_max, n_cells), np.nan)
    for j, r in enumerate(recs):
        cur[: len(r), j] = r.current_a
        vol[: len(r), j] = r.voltage_v
        if r.temperature_c is not None:
            tmp[: len(r), j] = r.temperature_c
    k_start = np.array([k for k, _ in starts])
    soc_start = np.array([s for _, s in starts])
    if plan is not None and not plan.fed[k_start].all():
        k = int(k_start[~plan.fed[k_start]][0])
        raise ValueError(f"start sample {k} of {recs[0].source} lies in a logging gap: start at the next logged "
                         f"sample, {plan.first_fed(k)}")
    est = SocEstimator(n_cells, ocv, stated_ah, 1.0, initial_soc=np.where(k_start == 0, soc_start, np.nan),
                       config=config)
    out = np.full((n_max, n_cells), np.nan)
    sigma = np.full((n_max, n_cells), np.nan)
    for k in range(n_max):
        if plan is not None and k < plan.fed.size:
            if not plan.fed[k]:  # in a logging gap: not fed, the estimate held (k > 0: sample 0 is logged)
                out[k], sigma[k] = out[k - 1], sigma[k - 1]
                continue
            if plan.rest_before_s[k] > 0:  # the first sample after one: the cells begun rest over it
                est.rest(float(plan.rest_before_s[k]), k_start < k)
        before = k < k_start
        starting = k == k_start
        if starting.any() and k > 0:
            est.set_soc(soc_start, starting)
        i = np.where(before, np.nan, cur[k])
        v = np.where(before, np.nan, vol[k])
        est.update(i, v, temperature_c=tmp[k])
        out[k] = np.where(before, np.nan, est.soc)
        sigma[k] = np.where(before, np.nan, est.soc_sigma)
    return GroupRun(out, sigma, est.counting_capacity_ah.copy())


_AT = re.compile(r"at(\d+(?:\.\d+)?)(?:([+-]\d+(?:\.\d+)?)|ocv)")


def check_start(name: str) -> str:
    """``name`` if it is a start this module knows (module docstring), else ValueError naming it."""
    m = _AT.fullmatch(name)
    if name in STARTS or name == "ocv" or (m and 0.0 <= float(m.group(1)) < 100.0):
        return name
    raise ValueError(f"unknown start {name!r}: use {', '.join(STARTS)}, ocv, atP+E / atP-E "
                     f"(P % of the file, E % off) or atPocv (P % of the file, read from the voltage there)")


def start_point(name: str, base_soc: np.ndarray, fed: np.ndarray | None = None) -> tuple[int, float]:
    """(sample, SOC told to the estimator) of a start in a file whose reference SOC is ``base_soc``.

    NaN for ``ocv`` and ``atPocv``: the estimator reads it from that sample's voltage.  ``fed`` (per sample,
    :class:`~bms_estimator.gaps.RestPlan`): a start in a logging gap begins at the next fed sample,
    told the reference there (as ``soc --start-s``).
    """
    n = len(base_soc)
    if name == "ocv":
        return 0, float("nan")
    if name == "full":
        return 0, 1.0
    if name == "full-20":
        return 0, 0.8
    if name in ("mid+10", "mid-10"):
        k, err = n // 4, (0.1 if name == "mid+10" else -0.1)
    else:
        m = _AT.fullmatch(check_start(name))
        k, err = int(n * float(m.group(1)) / 100.0), (float("nan") if m.group(2) is None else float(m.group(2)) / 100.0)
    if fed is not None and not fed[k]:
        k += int(np.argmax(fed[k:]))
    return k, float(np.clip(base_soc[k] + err, 0.0, 1.0))  # (NaN for atPocv: read from the voltage there)


def file_reference(tables: list[Table], ambient: str, rec) -> SocReference | str:
    """A drive file's SOC reference (:func:`~bms_estimator.scoring.soc_reference`), or why it has none.

    Read on its own ambient's C/20 test, the one reference that counts for pass/fail.  An ambient
    with HPPC rests only gives the mean curve (no discharge branch); an ambient with neither (a
    recording at a temperature the cell was never characterised at) gives the C/20 tests of the
    other ambients read at the file's median cell temperature (interpolated between them, held
    beyond them).  Both are approximate: reported, kept out of pass/fail."""
    own = next((t for t in tables if t.ambient == ambient), None)
    c20 = [t for t in tables if t.kind == "c20"]
    try:
        if own is not None:
            ref = soc_reference(rec.current_a, rec.voltage_v, rec.dt_s, own.curve)
            if own.kind == "c20":
                return ref
            return replace(ref, relaxed=False, why_override="no C/20 test at this ambient: approximate reference "
                                                           "from the HPPC rest table (no discharge branch), reported only")
        if not c20:
            return "no C/20 test at this ambient nor any other: no reference"
        temps = rec.temperature_c[np.isfinite(rec.temperature_c)] if rec.temperature_c is not None else ()
        t_c = float(np.median(temps)) if len(temps) else ambient_c(ambient)
        ref = soc_reference(rec.current_a, rec.voltage_v, rec.dt_s, make_ocv(c20), temperature_c=t_c)
        at = ", ".join(f"{t.temperature_c:.1f}" for t in sorted(c20, key=lambda t: t.temperature_c))
        return replace(ref, relaxed=False, why_override=f"no C/20 test at this ambient: approximate reference from "
                                                       f"the C/20 tests at {at} degC read at the file's {t_c:.1f} "
                                                       f"degC, reported only")
    except ValueError as exc:  # no final rest, no net discharge, ends full
        return f"no reference: {exc}"


def run_cell(data: Path, cell: str, methods: list[str], pattern: str = "*", leave_out: bool = True,
             overrides: dict | None = None, start_names: tuple[str, ...] = STARTS,
             rest_over_gaps: bool = True, current_gain: float = 1.0, current_offset_a: float = 0.0,
             ocv_jitter_v: float = 0.0, seed: int = 0) -> list[dict]:
    """Every drive cycle of ``cell`` under ``data`` matching ``pattern`` (cell/ambient/file), each of
    ``start_names``, per SOC method: one row of figures per run.  ``rest_over_gaps``: the files' logging
    gaps rested over (:func:`run_group`), else fed as ``load_recording`` fills them.

    ``current_gain`` multiplies every file's current before the estimator and the reference see it:
    a cell whose capacity is that many times its files' against unchanged OCV tables (the reference's
    Q_ref scales with it, the tables' C/20 capacities do not), or a current sensor's gain error.  A
    stress test of how the figures carry to a cell that is not the one the tables were measured on.

    ``current_offset_a`` is added to the current the estimator and plain counting see, not to the
    reference's: a current sensor's zero offset (the reference is the true charge; charge positive).

    ``ocv_jitter_v`` moves every knot of the estimator's OCV tables by an independent normal error of
    that sigma (``seed``; :func:`jittered`), not the reference's: the same C/20 test measured again.  How
    far a figure hangs on the tables' last tenth of a millivolt."""
    if not (np.isfinite(current_gain) and current_gain > 0):
        raise ValueError(f"current_gain must be a positive number, got {current_gain!r}")
    if not np.isfinite(current_offset_a):
        raise ValueError(f"current_offset_a must be a finite number, got {current_offset_a!r}")
    stated = CELLS[cell]
    tables = build_tables(data, cell)
    rows = []
    files = []
    for amb_dir in sorted((data / cell).iterdir()):
        for p in sorted(amb_dir.glob("*.csv.gz")):
            name = p.name.removesuffix(".csv.gz")
            if name in DRIVE_SKIP or not fnmatch.fnmatch(f"{cell}/{amb_dir.name}/{name}", pattern):
                continue
            rec = load_recording(p, resample_s=1.0)
            if current_gain != 1.0:
                rec = replace(rec, current_a=rec.current_a * current_gain)
            files.append((amb_dir.name, name, rec))
    if not files:
        return rows
    # what the estimator and counting read: the current through a sensor with a zero offset
    sensed = [replace(rec, current_a=rec.current_a + current_offset_a) if current_offset_a else rec
              for _, _, rec in files]
    plans = [recording_rest_plan(rec, rest_over_gaps) for rec in sensed]
    refs = [file_reference(tables, amb, rec) for amb, _, rec in files]
    variants = [("all tables", None)]
    if leave_out:
        variants.append(("own table out", "own"))
    for method in methods:
        for variant, drop in variants:
            # one estimator per left-out ambient (the tables differ), one for all tables
            groups: dict[str | None, list[int]] = {}
            for j, (amb, _, _) in enumerate(files):
                key = amb if drop == "own" else None
                if drop == "own" and not any(t.ambient == amb for t in tables):
                    continue  # nothing to leave out: the 'all tables' run is already this
                groups.setdefault(key, []).append(j)
            for key, idx in groups.items():
                tabs = [t for t in tables if t.ambient != key]
                ocv = make_ocv([jittered(t, ocv_jitter_v, seed) for t in tabs] if ocv_jitter_v else tabs)
                recs, starts, meta, rec_plans = [], [], [], []
                for j in idx:
                    amb, name, rec = files[j]
                    ref = refs[j]
                    # no reference: a mid-file start is told the stated-capacity count
                    base = ref.soc if isinstance(ref, SocReference) else counted_soc(rec.current_a, rec.dt_s, stated)
                    for start in start_names:
                        st = start_point(start, base, plans[j].fed)
                        recs.append(sensed[j])
                        rec_plans.append(plans[j])
                        starts.append(st)
                        meta.append((j, start))
                t0 = time.time()
                run = run_group(recs, starts, ocv, stated, estimator_config(method, overrides), rest_over_gaps,
                                rec_plans)
                elapsed = time.time() - t0
                for c, (j, start) in enumerate(meta):
                    amb, name, rec = files[j]
                    ref = refs[j]
                    k0, s0 = starts[c]
                    n = len(rec)
                    if not np.isfinite(s0):  # read from the OCV: what the estimator began with
                        s0 = float(run.soc[k0, c])
                    row = {
                        "cell": cell, "ambient": amb, "file": name, "method": method, "ocv": variant,
                        "start": start, "start_s": float(k0 * rec.dt_s), "start_soc": s0,
                        "tables": [f"{t.ambient}:{t.kind}" for t in tabs],
                        "capacity_ah_estimated": float(run.capacity_ah[c]),
                        "elapsed_s_group": elapsed,
                        "logging_gaps_rested": plans[j].gaps, "rested_s": plans[j].rested_s,
                    }
                    if isinstance(ref, SocReference):
                        t = rec.time_s - rec.time_s[0]
                        figs = soc_error_figures(run.soc[:n, c], ref.soc, t, k0 * rec.dt_s)
                        # plain counting with the stated capacity from the same start
                        cnt = np.full(n, np.nan)
                        cnt[k0:] = counted_soc(sensed[j].current_a[k0:], rec.dt_s, stated, s0)
                        base = soc_error_figures(cnt, ref.soc, t, k0 * rec.dt_s)
                        row.update({k: v for k, v in figs.items()})
                        row["within_sigma_pct"], row["within_2sigma_pct"] = _sigma_coverage(
                            run.soc[:n, c], run.soc_sigma[:n, c], ref.soc, k0 + int(round(1800.0 / rec.dt_s)))
                        row["counting_rmse_30min_pct"] = base["rmse_30min_pct"]
                        row["counting_rmse_1h_pct"] = base["rmse_1h_pct"]
                        row.update(capacity_ah_reference=ref.capacity_ah, reference_relaxed=ref.relaxed,
                                   reference=ref.why)
                    else:
                        row.update(reference_relaxed=False, reference=ref)
                    rows.append(row)
    return rows


def _sigma_coverage(soc: np.ndarray, sigma: np.ndarray, ref: np.ndarray, k_from: int) -> tuple[float, float]:
    """Percent of the samples from ``k_from`` on whose |SOC error| is within 1 and 2 reported sigma (NaN: none)."""
    e = np.abs(soc[k_from:] - ref[k_from:])
    s = sigma[k_from:]
    ok = np.isfinite(e) & np.isfinite(s)
    if not ok.any():
        return float("nan"), float("nan")
    return float(100.0 * np.mean(e[ok] <= s[ok])), float(100.0 * np.mean(e[ok] <= 2.0 * s[ok]))


def summary_lines(rows: list[dict]) -> list[str]:
    lines = []
    scored = [r for r in rows if r.get("reference_relaxed")]
    for method in sorted({r["method"] for r in rows}):
        for variant in ("all tables", "own table out"):
            sel = [r for r in scored if r["method"] == method and r["ocv"] == variant]
            if not sel:
                continue
            e30 = np.array([r["rmse_30min_pct"] for r in sel], dtype=float)
            e1h = np.array([r["rmse_1h_pct"] for r in sel], dtype=float)
            short = int(np.sum(~np.isfinite(e30)))  # a late start with under 30 min of file left
            e30 = e30[np.isfinite(e30)]
            if not e30.size:
                continue
            ok = int(np.sum(e30 <= 2.0))
            line = (f"{method}, {variant}: {ok}/{e30.size} runs within 2 % from 30 min after the start "
                    f"(median {np.median(e30):.2f} %, worst {np.max(e30):.2f} %)")
            if np.isfinite(e1h).any():
                line += f"; after 1 h median {np.nanmedian(e1h):.2f} %, worst {np.nanmax(e1h):.2f} %"
            if short:
                line += f"; {short} more started under 30 min before the end: not scored"
            cover = np.array([[r.get("within_sigma_pct", np.nan), r.get("within_2sigma_pct", np.nan)] for r in sel])
            if np.isfinite(cover).any():
                line += (f"; the error within the reported 1 / 2 sigma {np.nanmean(cover[:, 0]):.0f} / "
                         f"{np.nanmean(cover[:, 1]):.0f} % of the time (mean over runs)")
            lines.append(line)
    return lines


def markdown(rows: list[dict]) -> str:
    """Every run, one line each (docs/soc_matrix.md)."""
    head = ("| cell | ambient | file | method | OCV | start | RMSE 30 min+ [%] | RMSE 1 h+ [%] | max [%] | "
            "counting, stated Q, 30 min+ [%] | capacity est. / ref [Ah] |\n|---|---|---|---|---|---|---|---|---|---|---|")
    out = [head]
    for r in rows:
        if "rmse_30min_pct" in r:
            figs = (f"{r['rmse_30min_pct']:.2f} | {r['rmse_1h_pct']:.2f} | {r['max_abs_pct']:.2f} | "
                    f"{r['counting_rmse_30min_pct']:.2f} | {r['capacity_ah_estimated']:.3f} / {r['capacity_ah_reference']:.3f}")
            if not r["reference_relaxed"]:
                figs += " (not scored)"
        else:
            figs = f"- | - | - | - | {r['capacity_ah_estimated']:.3f} / -"
        out.append(f"| {r['cell']} | {r['ambient']} | {r['file']} | {r['method']} | {r['ocv']} | {r['start']} | {figs} |")
    return "\n".join(out)


def summary_table(rows: list[dict]) -> str:
    """Per cell, ambient, method and OCV variant: the runs within 2 %, median and worst (README)."""
    head = ("| cell | ambient | reference | method | OCV | runs within 2 % (30 min+) | median / worst RMSE 30 min+ [%] "
            "| median RMSE 1 h+ [%] | correct start: estimator / counting with the stated Q, 1 h+ [%] |\n"
            "|---|---|---|---|---|---|---|---|---|")
    out = [head]
    keys = []
    for r in rows:
        k = (r["cell"], r["ambient"], r["method"], r["ocv"])
        if k not in keys:
            keys.append(k)
    for cell, amb, method, variant in keys:
        sel = [r for r in rows if (r["cell"], r["ambient"], r["method"], r["ocv"]) == (cell, amb, method, variant)]
        if "rmse_30min_pct" not in sel[0]:
            out.append(f"| {cell} | {amb} | {sel[0]['reference']} | {method} | {variant} | - | - | - | - |")
            continue
        e30 = np.array([r["rmse_30min_pct"] for r in sel])
        e1h = np.array([r["rmse_1h_pct"] for r in sel])
        full = [r for r in sel if r["start"] == "full" and np.isfinite(r["rmse_1h_pct"])]
        est = np.median([r["rmse_1h_pct"] for r in full]) if full else float("nan")
        cnt = np.median([r["counting_rmse_1h_pct"] for r in full]) if full else float("nan")
        ref = ("scored" if sel[0]["reference_relaxed"] else
               "HPPC table, approximate: reported only" if "HPPC" in sel[0]["reference"] else
               "other ambients' C/20 tests, approximate: reported only" if "C/20 tests at" in sel[0]["reference"] else
               "end rest not relaxed: reported only")
        out.append(f"| {cell} | {amb} | {ref} | {method} | {variant} | {int(np.sum(e30 <= 2.0))} of {e30.size} | "
                   f"{np.median(e30):.2f} / {np.max(e30):.2f} | {np.nanmedian(e1h):.2f} | {est:.2f} / {cnt:.2f} |")
    return "\n".join(out)
