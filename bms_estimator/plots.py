"""Figures (matplotlib, Agg: no display needed). Each function writes one PNG and returns its path."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

ATTRIBUTION = "Data: P. Kollmeyer et al., Mendeley Data (CC BY 4.0)"
COLORS = {"lif": "tab:blue", "lif-iv": "tab:green", "lif-iv-bv": "tab:purple", "lif-iv-ct": "tab:red", "arx": "tab:orange",
          "measured": "black"}
LABELS = {"lif": "CT-LS (LIF)", "lif-iv": "CT-IV (LIF, recursive IV)", "lif-iv-bv": "CT-IV-BV (CT-IV + kinetic term)",
          "lif-iv-ct": "CT-IV-CT (CT-IV, charge-transfer fast branch)",
          "arx": "DT (ARX)"}


def save_figure(fig, path: Path, note: str | None = None, *, dpi: int = 110) -> Path:
    """Write ``fig`` as a PNG at ``path`` (its folder made), ``note`` (the data's attribution, say)
    in its bottom right corner, and close it."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if note:
        fig.text(0.99, 0.005, note, ha="right", va="bottom", fontsize=7, color="0.4")
    fig.tight_layout()
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return path


#: the time axis of the figures: hours from the recording's first sample, as --start-s counts (a log stamped in Unix
#: time drew its axis at 472,222 h plus an offset)
TIME_LABEL = "time from the recording's start [h]"


def _hours_from_start(time_s) -> np.ndarray:
    t = np.asarray(time_s, dtype=float)
    return (t - t[0]) / 3600.0 if t.size else t


def plot_parameters(time_s: np.ndarray, params: dict[str, dict[str, np.ndarray]], path: Path, title: str = "") -> Path:
    """Parameter trajectories (the paper's Figs 5-7): R0, R1, R2, tau1, tau2, c0 per method."""
    t = _hours_from_start(time_s)
    fig, axes = plt.subplots(3, 2, figsize=(11, 8), sharex=True)
    spec = [("r0_ohm", "R0 [mOhm]", 1e3), ("c0_v", "c0 [mV]", 1e3), ("r1_ohm", "R1 [mOhm]", 1e3),
            ("tau1_s", "tau1 [s]", 1.0), ("r2_ohm", "R2 [mOhm]", 1e3), ("tau2_s", "tau2 [s]", 1.0)]
    for ax, (key, label, k) in zip(axes.flat, spec):
        for method, p in params.items():
            ax.plot(t, p[key] * k, color=COLORS.get(method), label=LABELS.get(method, method), lw=0.9)
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    axes[0, 0].legend()
    for ax in axes[-1]:
        ax.set_xlabel(TIME_LABEL)
    fig.suptitle(title)
    return save_figure(fig, path, ATTRIBUTION)


def plot_errors(time_s, voltage_v, predicted: dict[str, np.ndarray], path: Path, title: str, ylabel: str,
                mask: np.ndarray | None = None) -> Path:
    """Voltage error against time (the paper's Figs 8-9: OSA or simulation error), where ``mask`` is True; a
    mask without a True sample (a file that never enters the SOC window) shows the whole file, and says so
    (the panel was left empty)."""
    t = _hours_from_start(time_s)
    if mask is not None and not np.any(mask):
        mask, title = None, f"{title} (whole file: none of it in the SOC window)"
    fig, axes = plt.subplots(2, 1, figsize=(11, 6), sharex=True)
    axes[0].plot(t, voltage_v, color="black", lw=0.8, label="measured")
    for method, v in predicted.items():
        axes[0].plot(t, v, color=COLORS.get(method), lw=0.7, label=LABELS.get(method, method))
        err = (np.asarray(v) - np.asarray(voltage_v)) * 1e3
        if mask is not None:
            err = np.where(mask, err, np.nan)
        axes[1].plot(t, err, color=COLORS.get(method), lw=0.7, label=LABELS.get(method, method))
    axes[0].set_ylabel("voltage [V]")
    axes[0].legend(loc="lower left")
    axes[1].set_ylabel(ylabel)
    axes[1].set_xlabel(TIME_LABEL)
    for ax in axes:
        ax.grid(alpha=0.3)
    fig.suptitle(title)
    return save_figure(fig, path, ATTRIBUTION)


def plot_soc(time_s, soc, soc_ref, capacity_ah, path: Path, title: str = "", counted=None) -> Path:
    """Estimated vs reference SOC and the error (the paper's Fig. 10), with plain counting from the same start."""
    t = _hours_from_start(time_s)
    fig, axes = plt.subplots(3, 1, figsize=(10, 8), sharex=True)
    axes[0].plot(t, np.asarray(soc_ref) * 100, color="black", label="reference (coulomb counting from the start)")
    axes[0].plot(t, np.asarray(soc) * 100, color="tab:blue", label="estimated")
    if counted is not None:
        axes[0].plot(t, np.asarray(counted) * 100, color="0.5", ls=":", label="counting, stated capacity")
    axes[0].set_ylabel("SOC [%]")
    axes[0].legend()
    if counted is not None:
        axes[1].plot(t, (np.asarray(counted) - np.asarray(soc_ref)) * 100, color="0.5", ls=":",
                     label="counting, stated capacity")
    axes[1].plot(t, (np.asarray(soc) - np.asarray(soc_ref)) * 100, color="tab:red", label="estimated")
    if counted is not None:
        axes[1].legend()
    axes[1].axhline(2, color="0.5", ls="--", lw=0.8)
    axes[1].axhline(-2, color="0.5", ls="--", lw=0.8)
    axes[1].set_ylabel("SOC error [%]")
    axes[2].plot(t, capacity_ah, color="tab:green")
    axes[2].set_ylabel("capacity [Ah]")
    axes[2].set_xlabel(TIME_LABEL)
    for ax in axes:
        ax.grid(alpha=0.3)
    fig.suptitle(title)
    return save_figure(fig, path, ATTRIBUTION)
