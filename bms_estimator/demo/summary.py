"""The demo's figures of merit, its text summary and its figure.

Definitions (``analyse``):

* **Reference SOC** per cell: coulomb counting from the cell's known start with its reference
  capacity, as ``bms-estimator soc`` defines it (:func:`~bms_estimator.analysis.reference_soc`):
  cell 0 (the measured cell) from full with the file's reference capacity (measured from the
  end-of-test rest when the file ends relaxed, else the stated one); every simulated cell from
  its injected start SOC with its injected capacity (truth JSON). Sample ``k`` of the service
  (``t_s = k + 1`` s, the end of its period) is compared with row ``k`` of the reference.
* **SOC error**: estimate minus reference, in % SOC: RMSE over the run, RMSE and max |error|
  after the first hour (:func:`~bms_estimator.analysis.soc_errors`), and at the end.
* **Voltage RMSE** (one-step-ahead, mV): at each sample ``k`` the model the service had
  identified at ``k-1`` (R0, R1, tau1, R2, tau2, c0, ZOH-discretised) predicts the
  overpotential ``v_o[k] = v[k] - OCV(soc)`` from the measured current and the measured
  overpotentials of ``k-1`` and ``k-2``; the RMSE of prediction minus measurement over the
  samples after the first 600 s (the block-LS start and the first compensations), leaving out
  the two samples after each SOC correction or re-anchoring (there the OCV bias moves from the
  model into the SOC, and the stored overpotentials of the two bases do not compare).
* **Identified parameters**: the values the service holds (and has published) at the end.
* **R0 ranking**: Spearman's rank correlation over the cells between the identified R0 (median
  over the samples after the initialisation) and the injected R0 (the cell model's R0 at the
  cell's own true SOC times its factor, median over the same samples). The ranking of the final
  R0 values against the injected factors is reported too.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from ..analysis import lookup_params, reference_soc, soc_errors
from ..core.params import dt_theta_from_physical

__all__ = ["analyse", "format_summary", "plot_run"]

def _spearman(a: np.ndarray, b: np.ndarray) -> float:
    from scipy.stats import spearmanr

    a, b = np.asarray(a, float), np.asarray(b, float)
    ok = np.isfinite(a) & np.isfinite(b)
    if ok.sum() < 3 or np.ptp(a[ok]) == 0 or np.ptp(b[ok]) == 0:
        return math.nan
    return float(spearmanr(a[ok], b[ok]).statistic)


def osa_errors(current_a: np.ndarray, v_o: np.ndarray, params: dict[str, np.ndarray], dt_s: float) -> np.ndarray:
    """One-step-ahead overpotential error ``(n, cells)`` in V (NaN for k < 2), see the module docstring."""
    i = np.asarray(current_a, float)[:, None]
    th = dt_theta_from_physical(params["r0_ohm"], params["r1_ohm"], params["tau1_s"], params["r2_ohm"],
                                params["tau2_s"], params["c0_v"], dt_s=dt_s)  # (n, cells, 6)
    err = np.full(v_o.shape, np.nan)
    t = th[1:-1]  # model of sample k-1 predicts sample k, k = 2..n-1
    pred = (t[..., 0] * v_o[1:-1] + t[..., 1] * v_o[:-2] + t[..., 2] * i[2:] + t[..., 3] * i[1:-1]
            + t[..., 4] * i[:-2] + t[..., 5])
    err[2:] = pred - v_o[2:]
    return err


def analyse(setup: Any, result: Any) -> dict[str, Any]:
    """Everything the summary prints, as plain numbers (JSON-able after ``to_jsonable``)."""
    rec = result.record
    truth = setup.truth
    cells = truth["cells"]
    n_cells = setup.n_cells
    dt = setup.trace.dt_s
    n = rec.rows
    if n < 3:
        raise RuntimeError(f"the service estimated only {n} samples")
    k_idx = np.rint(rec.t_s / dt).astype(int) - 1  # row of the recording
    if k_idx[0] != 0 or np.any(np.diff(k_idx) != 1):
        raise RuntimeError("the service's samples are not the recording's rows 0, 1, 2, ... in order")
    i = setup.trace.current_a[k_idx]
    t = rec.t_s - dt  # start of each sample, as the offline tools' time axis

    q_ref = float(truth["reference"]["capacity_ah"])
    q_true = np.array([q_ref if c["measured"] else c["capacity_ah"] for c in cells], float)
    soc0 = np.array([1.0 if c["measured"] else c["soc0"] for c in cells], float)
    ii = np.ascontiguousarray(np.broadcast_to(setup.trace.current_a[:, None], (setup.n_samples, n_cells)))
    soc_ref_all = reference_soc(ii, dt, q_true, soc0)
    soc_ref = soc_ref_all[k_idx]

    init_s = 600.0
    late = t >= init_s
    # injected R0 along every cell's true SOC path (the cell model's table times the factor)
    table = {k: np.asarray(v, float) for k, v in truth["soc_table"].items()}
    r0_true_path = lookup_params(table, soc_ref)["r0_ohm"] * np.array([c["r0_factor"] for c in cells])[None, :]

    # one-step-ahead voltage error
    err = osa_errors(i, rec.v_o, rec.params, dt)
    cc = rec.soc[1:] - rec.soc[:-1] - i[:-1, None] * dt / 3600.0 / rec.capacity_ah[:-1]
    jumped = np.zeros_like(err, dtype=bool)
    jumped[1:] = np.abs(cc) > 1e-3  # an SOC jump that coulomb counting does not explain (not the EKF's small steps)
    skip = jumped.copy()
    skip[1:] |= jumped[:-1]
    skip[2:] |= jumped[:-2]
    use = late[:, None] & ~skip & np.isfinite(err)

    soc_counted = _counted_from_start(rec.soc[0], i, dt, setup.capacity_stated_ah)
    per_cell = []
    for j, c in enumerate(cells):
        s = soc_errors(rec.soc[:, j], soc_ref[:, j], t)
        s_count = soc_errors(soc_counted[:, j], soc_ref[:, j], t)
        u = use[:, j]
        osa = float(1e3 * np.sqrt(np.mean(err[u, j] ** 2))) if u.any() else math.nan
        p = {k: float(v[-1, j]) for k, v in rec.params.items()}
        per_cell.append({
            "cell": j,
            "measured": bool(c["measured"]),
            "capacity_ah_true": float(q_true[j]),
            "capacity_ah_estimated": float(rec.capacity_ah[-1, j]),
            "soc0_true": float(soc0[j]),
            "soc_end_estimated": float(rec.soc[-1, j]),
            "soc_end_reference": float(soc_ref[-1, j]),
            "soc_error_end_pct": float(100 * (rec.soc[-1, j] - soc_ref[-1, j])),
            **s,
            "counting_soc_rmse_pct_after_3600s": s_count["soc_rmse_pct_after_3600s"],
            "voltage_osa_rmse_mv": osa,
            "voltage_osa_samples": int(u.sum()),
            "r0_ohm_final": p["r0_ohm"],
            "r1_ohm_final": p["r1_ohm"],
            "tau1_s_final": p["tau1_s"],
            "r2_ohm_final": p["r2_ohm"],
            "tau2_s_final": p["tau2_s"],
            "c0_v_final": p["c0_v"],
            "r0_ohm_median": float(np.median(rec.params["r0_ohm"][late, j])) if late.any() else math.nan,
            "r0_ohm_true_median": float(np.median(r0_true_path[late, j])) if late.any() else math.nan,
            "r0_factor_true": float(c["r0_factor"]),
        })
    r0_med = np.array([c["r0_ohm_median"] for c in per_cell])
    r0_true = np.array([c["r0_ohm_true_median"] for c in per_cell])
    r0_fin = np.array([c["r0_ohm_final"] for c in per_cell])
    fac = np.array([c["r0_factor_true"] for c in per_cell])
    mqtt_match = None
    received = [p for p in result.mqtt_final if p is not None]
    if received:
        mqtt_match = all(
            p is not None and p.get("t_s") == float(rec.t_s[-1])
            and _close(p.get("soc"), rec.soc[-1, j]) and _close(p.get("r0_ohm"), rec.params["r0_ohm"][-1, j])
            for j, p in enumerate(result.mqtt_final)
        )
    return {
        "cell": setup.cell,
        "cycle": setup.cycle,
        "n_cells": n_cells,
        "seed": setup.seed,
        "samples": n,
        "duration_s": float(setup.duration_s),
        "capacity_ah_stated": setup.capacity_stated_ah,
        "capacity_ah_reference": q_ref,
        "reference_capacity_source": truth["reference"]["capacity_source"],
        "spread_sigma": truth["spread_sigma"],
        "frames": result.frames_sent,
        "frames_decoded": result.frames_decoded,
        "decode_errors": result.decode_errors,
        "replay_wall_s": result.wall_s,
        "replay_speed": "max" if math.isinf(result.speed) else result.speed,
        "times_real_time": float(setup.duration_s / result.wall_s) if result.wall_s > 0 else math.inf,
        "mqtt_published": result.mqtt_published,
        "mqtt_received": result.mqtt_messages,
        "mqtt_final_states_received": len(received),
        "mqtt_final_states_match_service": mqtt_match,
        "osa_from_s": init_s,
        "spearman_r0_median_vs_injected": _spearman(r0_med, r0_true),
        "spearman_r0_final_vs_factor": _spearman(r0_fin, fac),
        "soc_rmse_pct_mean": _finite_mean([c["soc_rmse_pct"] for c in per_cell]),
        "soc_rmse_after_3600s_pct_mean": _finite_mean([c["soc_rmse_pct_after_3600s"] for c in per_cell]),
        "counting_soc_rmse_after_3600s_pct_mean": _finite_mean([c["counting_soc_rmse_pct_after_3600s"]
                                                                 for c in per_cell]),
        "voltage_osa_rmse_mv_mean": _finite_mean([c["voltage_osa_rmse_mv"] for c in per_cell]),
        "cells": per_cell,
        "pack_sox_end": dict(getattr(rec, "pack_sox", {})),
        "notes": list(result.notes),
    }


def _counted_from_start(soc_start: np.ndarray, current_a: np.ndarray, dt_s: float, capacity_ah: float) -> np.ndarray:
    """Plain coulomb counting with the stated capacity from the service's own first SOC, per cell."""
    q = np.concatenate(([0.0], np.cumsum(current_a[:-1]))) * dt_s / 3600.0
    return soc_start[None, :] + q[:, None] / capacity_ah


def _finite_mean(values: list[float]) -> float:
    a = np.asarray(values, float)
    a = a[np.isfinite(a)]
    return float(a.mean()) if a.size else math.nan


def _close(x: Any, y: float) -> bool:
    return isinstance(x, (int, float)) and abs(float(x) - float(y)) <= 1e-9 * max(1.0, abs(float(y)))


def _f(x: float, scale: float = 1.0, digits: int = 2, width: int = 6) -> str:
    if x is None or not math.isfinite(x):
        return "-".rjust(width)
    return f"{x * scale:{width}.{digits}f}"


def format_summary(a: dict[str, Any], figure: Path | None = None) -> str:
    """The summary as text (fixed width; the same on a terminal and in a log)."""
    cells = a["cells"]
    sig = a["spread_sigma"]
    lines = [
        "",
        f"Summary: {a['n_cells']}-cell pack from {a['cell']} {a['cycle']} ({a['duration_s']:.0f} s at 1 s), seed {a['seed']}; "
        f"cell 0 = the measured cell, cells 1-{a['n_cells'] - 1} simulated with a 1-sigma spread of capacity "
        f"{100 * sig['capacity']:.0f} %, R0 {100 * sig['r0']:.0f} %, R1/R2 {100 * sig['r1']:.0f} %, "
        f"tau1/tau2 {100 * sig['tau1']:.0f} %",
        f"  reference SOC: coulomb counting from full; cell 0 with {a['capacity_ah_reference']:.3f} Ah "
        f"({a['reference_capacity_source']}), the other cells with their injected capacity; stated "
        f"{a['capacity_ah_stated']:g} Ah",
        f"  voltage RMSE: one-step-ahead (the model of the previous second predicts v - OCV(soc) from the measured "
        f"past), after the {a['osa_from_s']:.0f} s initialisation",
        "",
        " cell  Q true  Q est |   SOC end est / ref   err | SOC RMSE all  >1h   max>1h | V OSA | "
        " R0 mOhm  R1 mOhm  tau1 s  R2 mOhm  tau2 s  c0 mV | R0 median est / injected",
    ]
    for c in cells:
        lines.append(
            f" {c['cell']:>3d}{'*' if c['measured'] else ' '} {c['capacity_ah_true']:6.3f} {c['capacity_ah_estimated']:6.3f} |"
            f" {_f(c['soc_end_estimated'], 100, 2, 7)} / {_f(c['soc_end_reference'], 100, 2, 6)}"
            f" {_f(c['soc_error_end_pct'], 1, 2, 6)} |"
            f" {_f(c['soc_rmse_pct'], 1, 2, 8)} {_f(c['soc_rmse_pct_after_3600s'], 1, 2, 5)} "
            f"{_f(c['soc_max_abs_error_pct_after_3600s'], 1, 2, 7)} |"
            f" {_f(c['voltage_osa_rmse_mv'], 1, 2, 5)} |"
            f" {_f(c['r0_ohm_final'], 1e3, 2, 8)} {_f(c['r1_ohm_final'], 1e3, 2, 8)} {_f(c['tau1_s_final'], 1, 1, 7)}"
            f" {_f(c['r2_ohm_final'], 1e3, 2, 8)} {_f(c['tau2_s_final'], 1, 0, 7)} {_f(c['c0_v_final'], 1e3, 2, 6)} |"
            f" {_f(c['r0_ohm_median'], 1e3, 2, 7)} / {_f(c['r0_ohm_true_median'], 1e3, 2, 6)}"
        )
    lines.append("   (* measured cell; SOC and errors in %, V OSA in mV; parameters: the service's values at the end)")
    lines.append("")
    late = a["soc_rmse_after_3600s_pct_mean"]
    lines.append(
        f"SOC RMSE, mean over cells: {a['soc_rmse_pct_mean']:.2f} % over the run"
        + (f", {late:.2f} % after the first hour (counting with the stated {a['capacity_ah_stated']:g} Ah from the "
           f"same start: {a['counting_soc_rmse_after_3600s_pct_mean']:.2f} %)" if math.isfinite(late)
           else " (the run is shorter than 1 h)")
        + "; voltage OSA RMSE, mean over cells: "
        + (f"{osa:.2f} mV" if math.isfinite(osa := a["voltage_osa_rmse_mv_mean"])
           else f"n/a (the run is not longer than the {a['osa_from_s']:.0f} s initialisation)")
    )
    rho = a["spearman_r0_median_vs_injected"]
    if math.isfinite(rho):
        lines.append(
            f"R0 ranking vs the injected spread: Spearman {rho:.3f} (median R0 after the initialisation vs "
            f"injected; final R0 vs injected factor: {a['spearman_r0_final_vs_factor']:.3f})"
        )
    else:
        lines.append(f"R0 ranking vs the injected spread: n/a (needs a run longer than the {a['osa_from_s']:.0f} s "
                     "initialisation and three cells or more)")
    sox = a.get("pack_sox_end") or {}
    if sox:
        lines.append(
            f"Power, energy, health at the end (pack): 10 s limits discharge {_f(sox.get('p_discharge_max_10s_w'), 1, 0, 1)} W"
            f" ({_f(sox.get('i_discharge_max_10s_a'), 1, 2, 1)} A), charge {_f(sox.get('p_charge_max_10s_w'), 1, 0, 1)} W"
            f" ({_f(sox.get('i_charge_max_10s_a'), 1, 2, 1)} A); energy left {_f(sox.get('energy_left_wh'), 1, 1, 1)} Wh,"
            f" discharged {_f(sox.get('energy_discharged_wh'), 1, 1, 1)} Wh, time to empty"
            f" {_f(sox.get('time_to_empty_s'), 1 / 60, 0, 1)} min; SOH capacity {_f(sox.get('soh_capacity_min'), 100, 1, 1)} %,"
            f" resistance {_f(sox.get('soh_resistance_max'), 100, 1, 1)} % (weakest cell; '-' = not yet justified)")
    mq = a["mqtt_final_states_match_service"]
    lines.append(
        f"Service: {a['frames']:,} frames, {a['samples']:,} samples in {a['replay_wall_s']:.1f} s "
        f"({a['times_real_time']:.0f}x real time, speed "
        f"{a['replay_speed'] if isinstance(a['replay_speed'], str) else format(a['replay_speed'], 'g') + 'x'}), "
        f"decode errors {a['decode_errors']}; "
        f"MQTT: {a['mqtt_published']:,} published, {a['mqtt_received']:,} received"
        + ("" if mq is None else f", final states over MQTT = the service's: {'yes' if mq else 'NO'}")
    )
    for note in a["notes"]:
        lines.append(f"note: {note}")
    if figure is not None:
        lines.append(f"Figure: {figure}")
    return "\n".join(lines)


def plot_run(setup: Any, result: Any, a: dict[str, Any], path: Path) -> Path:
    """SOC per cell vs reference, SOC error, R0 per cell vs truth, R0 over time, capacity, voltage RMSE."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ..plots import ATTRIBUTION, save_figure

    rec = result.record
    dt = setup.trace.dt_s
    t_h = (rec.t_s - dt) / 3600.0
    k_idx = np.rint(rec.t_s / dt).astype(int) - 1
    cells = a["cells"]
    n_cells = len(cells)
    q_true = np.array([c["capacity_ah_true"] for c in cells])
    soc0 = np.array([c["soc0_true"] for c in cells])
    ii = np.ascontiguousarray(np.broadcast_to(setup.trace.current_a[:, None], (setup.n_samples, n_cells)))
    soc_ref = reference_soc(ii, dt, q_true, soc0)[k_idx]
    colors = plt.cm.viridis(np.linspace(0, 0.95, n_cells))

    fig, axes = plt.subplots(3, 2, figsize=(13, 11))
    ax = axes[0, 0]
    for j in range(n_cells):
        ax.plot(t_h, 100 * soc_ref[:, j], color="0.55", lw=0.8, ls="--")
        ax.plot(t_h, 100 * rec.soc[:, j], color=colors[j], lw=0.8)
    ax.plot([], [], color="0.55", ls="--", label="reference (coulomb counting from full)")
    ax.plot([], [], color=colors[0], label="estimated by the service (one line per cell)")
    ax.set_ylabel("SOC [%]")
    ax.set_title("SOC per cell")
    ax.legend(fontsize=8, loc="lower left")

    ax = axes[0, 1]
    counted = _counted_from_start(rec.soc[0], setup.trace.current_a[k_idx], dt, setup.capacity_stated_ah)
    for j in range(n_cells):
        ax.plot(t_h, 100 * (counted[:, j] - soc_ref[:, j]), color="0.6", lw=0.6, ls=":")
        ax.plot(t_h, 100 * (rec.soc[:, j] - soc_ref[:, j]), color=colors[j], lw=0.7)
    ax.plot([], [], color="0.6", ls=":", label=f"counting with the stated {setup.capacity_stated_ah:g} Ah, same start")
    ax.plot([], [], color=colors[0], label="estimated by the service")
    ax.legend(fontsize=8, loc="lower left")
    for y in (-2, 2):
        ax.axhline(y, color="0.4", ls="--", lw=0.8)
    ax.set_ylabel("SOC error [%]")
    late = a["soc_rmse_after_3600s_pct_mean"]
    ax.set_title(f"SOC error; RMSE after 1 h, mean over cells {late:.2f} %" if math.isfinite(late)
                 else f"SOC error; RMSE, mean over cells {a['soc_rmse_pct_mean']:.2f} %")

    ax = axes[1, 0]
    est = np.array([c["r0_ohm_median"] for c in cells]) * 1e3
    tru = np.array([c["r0_ohm_true_median"] for c in cells]) * 1e3
    ax.scatter(tru, est, c=colors, zorder=3)
    for j in range(n_cells):
        ax.annotate(str(j), (tru[j], est[j]), textcoords="offset points", xytext=(4, 3), fontsize=7)
    both = np.concatenate([tru, est])
    both = both[np.isfinite(both)]
    if both.size:
        lo, hi = float(both.min()), float(both.max())
        pad = 0.05 * (hi - lo or 1.0)
        ax.plot([lo - pad, hi + pad], [lo - pad, hi + pad], color="0.5", lw=0.8, ls="--",
                label="estimated = injected")
        ax.legend(fontsize=8)
    ax.set_xlabel("injected R0 [mOhm] (median after 600 s)")
    ax.set_ylabel("identified R0 [mOhm] (median after 600 s)")
    ax.set_title(f"R0 per cell: Spearman {a['spearman_r0_median_vs_injected']:.3f}")

    ax = axes[1, 1]
    for j in range(n_cells):
        ax.plot(t_h, 1e3 * rec.params["r0_ohm"][:, j], color=colors[j], lw=0.7)
    ax.set_ylabel("R0 [mOhm]")
    ax.set_title("identified R0 per cell over time")
    r0_late = 1e3 * rec.params["r0_ohm"][t_h >= 600 / 3600.0]
    r0_late = r0_late[np.isfinite(r0_late)]
    if r0_late.size:
        ylo, yhi = np.percentile(r0_late, [0.5, 99.5])
        if yhi > ylo:
            ax.set_ylim(ylo - 0.1 * (yhi - ylo), yhi + 0.1 * (yhi - ylo))

    ax = axes[2, 0]
    for j in range(n_cells):
        ax.plot(t_h, rec.capacity_ah[:, j], color=colors[j], lw=0.8)
        ax.plot(t_h[[0, -1]], [q_true[j]] * 2, color=colors[j], lw=0.6, ls=":")
    ax.axhline(setup.capacity_stated_ah, color="black", lw=0.8, ls="--", label="stated")
    ax.set_ylabel("capacity [Ah]")
    ax.set_xlabel("time [h]")
    ax.set_title("capacity per cell: estimated (solid) vs injected (dotted)")
    ax.legend(fontsize=8)

    ax = axes[2, 1]
    osa = [c["voltage_osa_rmse_mv"] for c in cells]
    ax.bar(np.arange(n_cells), osa, color=colors)
    ax.set_xlabel("cell")
    ax.set_ylabel("one-step-ahead voltage RMSE [mV]")
    ax.set_title("voltage: model of the previous second vs measured")
    ax.set_xticks(np.arange(n_cells))

    for ax in axes.flat:
        ax.grid(alpha=0.3)
    for ax in axes[:2, 0].tolist() + [axes[0, 1], axes[1, 1]]:
        if ax is not axes[1, 0]:
            ax.set_xlabel("time [h]")
    fig.suptitle(f"bms-estimator demo: {a['n_cells']}-cell pack from {a['cell']} {a['cycle']} through the service "
                 f"(CAN -> estimator -> MQTT)")
    return save_figure(fig, path, ATTRIBUTION, dpi=100)
