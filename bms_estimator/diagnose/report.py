"""Report folder of a diagnosis: ``report.md`` plus PNG figures (matplotlib, Agg).

Figures:

* ``residual.png`` - the baseline's residual (measured minus simulated, in-sample
  full fit) against time, SOC, current and temperature, with the winning
  extension's residual on top: the signature of the cause.
* ``voltage.png`` - measured against simulated voltage before (baseline) and after
  (winning extension) the extension, out-of-sample, with their errors.
* ``candidates.png`` - out-of-sample RMSE of the baseline and every candidate.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .decide import Diagnosis
from .extensions import FEATURES

__all__ = ["write_report", "PHYSICS"]

#: One paragraph per cause: what it is physically and what its residual looks like.
PHYSICS = {
    "none": "No extension earns its extra parameters out of sample: what the 2-RC model misses is "
            "noise or spread over many small effects.",
    "hysteresis": "The open-circuit voltage depends on the direction of the recent charge throughput "
                  "(phase-transition and particle-population effects in the electrodes): after charging the "
                  "cell rests higher than after discharging. Signature: a residual that steps with the current's "
                  "direction and relaxes with charge throughput, not with time.",
    "temperature": "Ohmic and charge-transfer resistances fall with temperature (Arrhenius: electrolyte "
                   "conductivity, exchange current density). Signature: the residual scales with current and "
                   "follows the temperature trace (self-heating during aggressive driving).",
    "soc_dependence": "Resistances change with the state of charge (lithium concentration in the electrodes, "
                      "steeply towards empty). Signature: the current-proportional part of the residual grows "
                      "or changes sign along the SOC axis.",
    "current_nonlinearity": "The charge-transfer overpotential follows Butler-Volmer kinetics, "
                            "eta ~ asinh(i / 2 i0): linear for small currents, logarithmic for large ones, so the "
                            "apparent resistance falls as |I| grows. Signature: residual odd in current, largest at "
                            "the peaks.",
    "direction_asymmetry": "Charge and discharge see different resistances (asymmetric kinetics, lithium "
                           "plating/stripping paths). Signature: residual proportional to |I| on one direction only.",
    "slow_diffusion": "Solid-state diffusion in the active particles is slower than the two RC branches can "
                      "represent (Warburg behaviour, time constants of 10^3 s and more). Signature: a slowly "
                      "building and relaxing residual after long one-directional stretches and during rests.",
    "current_offset": "The current sensor has a constant bias, so the coulomb count drifts with time "
                      "(also at rest). Signature: a residual that grows with elapsed time, scaled by the OCV slope.",
    "capacity_error": "The cell's capacity differs from the stated one (ageing, temperature, rate), so the "
                      "coulomb-counted SOC drifts with charge throughput. Signature: a residual that grows with "
                      "the discharged charge, scaled by the OCV slope (large near empty).",
}


def _plots(d: Diagnosis, folder: Path) -> list[str]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ..plots import ATTRIBUTION, save_figure

    s = d.series
    out = []
    t_h = np.arange(len(s)) * s.dt_s / 3600.0
    r_base = (s.voltage_v - d.predictions["none"]) * 1e3
    win = d.cause if d.cause != "none" else None
    r_win = (s.voltage_v - d.predictions[win]) * 1e3 if win else None
    axes_spec = [("time [h]", t_h), ("SOC (counted, stated capacity)", s.soc), ("current [A]", s.current_a)]
    if s.temperature_c is not None:
        axes_spec.append(("temperature [degC]", s.temperature_c))
    fig, axes = plt.subplots(len(axes_spec), 1, figsize=(10, 2.6 * len(axes_spec)))
    for ax, (label, x) in zip(np.atleast_1d(axes), axes_spec):
        kind = "line" if label.startswith("time") else "scatter"
        if kind == "line":
            ax.plot(x, r_base, lw=0.6, color="tab:blue", label="baseline 2-RC")
            if r_win is not None:
                ax.plot(x, r_win, lw=0.6, color="tab:red", alpha=0.8, label=f"with {win}")
        else:
            step = max(1, len(x) // 6000)
            ax.scatter(x[::step], r_base[::step], s=1.5, color="tab:blue", label="baseline 2-RC")
            if r_win is not None:
                ax.scatter(x[::step], r_win[::step], s=1.5, color="tab:red", alpha=0.5, label=f"with {win}")
        ax.set_xlabel(label)
        ax.set_ylabel("residual [mV]")
        ax.grid(alpha=0.3)
    np.atleast_1d(axes)[0].legend(loc="best", fontsize=8)
    fig.suptitle("residual = measured - simulated (in-sample fit)")
    save_figure(fig, folder / "residual.png", ATTRIBUTION, dpi=100)
    out.append("residual.png")

    sc = d.scored
    t2 = np.arange(len(sc)) * sc.dt_s / 3600.0
    fig, axes = plt.subplots(2, 1, figsize=(10, 6), sharex=True)
    axes[0].plot(t2, sc.voltage_v, color="black", lw=0.8, label="measured")
    axes[0].plot(t2, d.oos["none"], color="tab:blue", lw=0.6, label=f"baseline ({d.baseline_rmse_mv:.1f} mV)")
    axes[1].plot(t2, (d.oos["none"] - sc.voltage_v) * 1e3, color="tab:blue", lw=0.6, label="baseline")
    if win:
        axes[0].plot(t2, d.oos[win], color="tab:red", lw=0.6, label=f"with {win} ({d.extended_rmse_mv:.1f} mV)")
        axes[1].plot(t2, (d.oos[win] - sc.voltage_v) * 1e3, color="tab:red", lw=0.6, label=f"with {win}")
    axes[0].set_ylabel("voltage [V]")
    axes[0].legend(loc="lower left", fontsize=8)
    axes[1].set_ylabel("simulated - measured [mV]")
    axes[1].set_xlabel("time [h]")
    for ax in axes:
        ax.grid(alpha=0.3)
    fig.suptitle(f"out-of-sample simulation ({d.scoring})")
    save_figure(fig, folder / "voltage.png", ATTRIBUTION, dpi=100)
    out.append("voltage.png")

    cands = [c for c in d.candidates if np.isfinite(c.rmse_mv)]
    fig, ax = plt.subplots(figsize=(8, 3.5))
    names = ["baseline"] + [c.cause for c in cands]
    vals = [d.baseline_rmse_mv] + [c.rmse_mv for c in cands]
    colors = ["0.5"] + ["tab:red" if c.cause == d.cause else ("tab:orange" if c.significant else "tab:blue")
                        for c in cands]
    ax.barh(names, vals, color=colors)
    ax.invert_yaxis()
    ax.set_xlabel("out-of-sample RMSE [mV]")
    ax.grid(alpha=0.3, axis="x")
    save_figure(fig, folder / "candidates.png", dpi=100)
    out.append("candidates.png")
    return out


#: what a fit that holds a value no cell has means (:attr:`Diagnosis.non_physical`)
NON_PHYSICAL = ("**Not physical:** the {fit} fit holds {values}: no cell has it. The fit uses it to absorb what it "
                "does not model (an SOC knot with few samples, an SOC path that misses charge, another cell's OCV "
                "table): read the gain as the size of what the 2-RC model misses, not these parameters as the cell's.")


def _fit_name(d: Diagnosis) -> str:
    return f"`{d.cause}` extension's" if d.cause != "none" else "baseline's"


#: every file :func:`write_report` may write in its folder
REPORT_FILES = ("report.md", "residual.png", "voltage.png", "candidates.png")


def write_report(d: Diagnosis, folder: str | Path, title: str = "diagnosis") -> Path:
    """Write ``folder/report.md`` and the figures; returns the markdown path."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    figs = _plots(d, folder)
    lines = [
        f"# {title}",
        "",
        f"**Cause: `{d.cause}`** - baseline {d.baseline_rmse_mv:.2f} mV, with the extension "
        f"{d.extended_rmse_mv:.2f} mV ({d.gain_pct:.1f} % lower), out of sample ({d.scoring}). "
        f"White-noise level of the residual: {d.noise_mv:.2f} mV.",
        "",
        PHYSICS.get(d.cause, ""),
        "",
    ]
    if d.non_physical:
        lines += [NON_PHYSICAL.format(fit=_fit_name(d), values="; ".join(d.non_physical)), ""]
    if d.secondary:
        lines += [f"Second effect (fitted jointly, smaller): `{d.secondary}` - {PHYSICS.get(d.secondary, '')}", ""]
    if d.ties:
        ties = ", ".join(f"`{t}`" for t in d.ties)
        lines += [f"Not beaten consistently (block by block) by the named cause, so hard to tell apart on "
                  f"these data: {ties}.",
                  ""]
    if d.joint and d.joint.get("significant"):
        j = d.joint
        comp = ", ".join(f"{k} {v:.2f} mV" for k, v in j["components_mv"].items())
        lines += [f"Pair stage: {' + '.join(j['causes'])} fitted jointly, out-of-sample {j['rmse_mv']:.2f} mV, "
                  f"{'significant' if j['significant'] else 'not significant'} against the better single; "
                  f"sizes in the joint fit: {comp}.", ""]
    lines += [
        "## Candidates",
        "",
        "| cause | extra params | RMSE [mV] | gain [%] | explained [mV] | score | t | n_eff | significant |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for c in d.ranking():
        if not np.isfinite(c.rmse_mv):
            lines.append(f"| {c.cause} | {c.extra_params} | - | - | - | - | - | - | no ({c.note}) |")
            continue
        lines.append(
            f"| {'**' + c.cause + '**' if c.cause == d.cause else c.cause} | {c.extra_params} | {c.rmse_mv:.2f} | "
            f"{c.gain_pct:.1f} | {c.explained_mv:.2f} | {c.score:.3f} | {c.t_stat:.1f} | {c.n_eff:.0f} | "
            f"{'yes' if c.significant else 'no'} |"
        )
    lines += [
        "",
        "score = ln(MSE_baseline / MSE_candidate) - 2 k / n_eff (out of sample); significant = score > 0, "
        "t >= 2 over the folds (log gain per fold) and explained >= half the noise level. The cause is the "
        "significant candidate with the largest score, or the larger effect of a significant pair fitted jointly.",
        "",
        "## Baseline (2-RC, constant parameters, output-error fit)",
        "",
        "| parameter | value |",
        "|---|---|",
    ]
    for k, v in d.baseline_params.items():
        lines.append(f"| {k} | {v:.6g} |")
    if d.lif:
        lines += ["", f"Online LIF identification (warm start): simulation RMSE with its parameter trajectory "
                      f"{d.lif.get('sim_rmse_mv', float('nan')):.2f} mV (in-sample), "
                      f"median tau1 {d.lif.get('tau1_s', float('nan')):.1f} s, "
                      f"tau2 {d.lif.get('tau2_s', float('nan')):.0f} s."]
    if d.cause != "none":
        c = d.candidate(d.cause)
        lines += ["", f"## Fitted `{d.cause}` extension ({FEATURES[d.cause].description})", "",
                  "| parameter | value |", "|---|---|"]
        for k, v in c.params.items():
            lines.append(f"| {k} | {v if isinstance(v, list) else f'{v:.6g}'} |")
    lines += ["", "## Figures", ""] + [f"![{f}]({f})" for f in figs] + [""]
    md = folder / "report.md"
    md.write_text("\n".join(lines), encoding="utf-8")
    return md
