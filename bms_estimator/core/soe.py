"""State of energy: the energy left down to v_min at a stated rate, and the time to empty or full.

Discharging at a constant current ``I_r`` (magnitude, A) from the SOC ``s``, the cell's
terminal voltage once the RC pairs have settled is ``v(z) = OCV(z) - R_ss I_r`` with
``R_ss = R0 + sum_j R_j`` (the identified steady-state resistance), and the charge it
delivers per unit SOC is ``3600 Q`` As.  The discharge ends at the cut-off SOC
``z_cut``, where ``v(z_cut) = v_min`` (or ``soc_min``).  The energy left is::

    E = Q * integral_{z_cut}^{s} (OCV(z) - R_ss I_r) dz            (Wh, Q in Ah)

evaluated by the trapezoid rule on ``n_points`` SOC points between ``soc_min`` and
``s`` (the integrand is clipped at v_min, which places the cut-off to within one grid
step).  The rate is stated as a C-rate (``I_r = rate Q``): 0 gives the OCV energy.

Time to empty at the recent mean discharge current ``I_m`` is
``3600 Q (s - z_cut(I_m)) / I_m``; time to full at a mean charge current is
``3600 Q (soc_max - s) / I_m``; both are infinite when ``|I_m|`` is below
``idle_current_c * Q``.

Everything is vectorised over cells; no I/O.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated, Callable

import numpy as np
from annotated_types import Ge, Gt

__all__ = ["SoeConfig", "energy_left_wh", "time_to_empty_s", "time_to_full_s"]

OcvFn = Callable[[np.ndarray], np.ndarray]


@dataclass(frozen=True)
class SoeConfig:
    rate_c: Annotated[float, Ge(0)] = 0.5  # the stated discharge rate of the energy left, C
    n_points: Annotated[int, Ge(3)] = 21  # SOC grid of the integral
    idle_current_c: Annotated[float, Gt(0)] = 0.01  # below this mean current (C), no time to empty/full
    mean_current_tau_s: Annotated[float, Gt(0)] = 300.0  # the "recent" mean current's time constant


def _grid(soc: np.ndarray, soc_min: float, n: int) -> np.ndarray:
    """(N, n) SOC points from soc_min to each cell's SOC."""
    f = np.linspace(0.0, 1.0, n)
    lo = np.full_like(soc, soc_min)
    hi = np.maximum(soc, lo)
    return lo[:, None] + (hi - lo)[:, None] * f[None, :]


def _cut_soc(z: np.ndarray, v: np.ndarray, v_min: float) -> np.ndarray:
    """The SOC where v falls to v_min below the top, interpolated between grid points (per row);
    the lowest grid SOC when it never does, the top when the top is already below."""
    below = v < v_min
    rev = below[:, ::-1]
    any_below = rev.any(axis=1)
    # the highest grid index below v_min; the crossing lies between it and the next
    k = np.where(any_below, z.shape[1] - 1 - np.argmax(rev, axis=1), 0)
    k1 = np.minimum(k + 1, z.shape[1] - 1)
    za, zb = np.take_along_axis(z, k[:, None], 1)[:, 0], np.take_along_axis(z, k1[:, None], 1)[:, 0]
    va, vb = np.take_along_axis(v, k[:, None], 1)[:, 0], np.take_along_axis(v, k1[:, None], 1)[:, 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        f = np.clip((v_min - va) / (vb - va), 0.0, 1.0)
    cut = np.where(k1 > k, za + f * (zb - za), zb)
    return np.where(any_below, cut, z[:, 0])


def energy_left_wh(soc, capacity_ah, r_ss_ohm, ocv: OcvFn, *, v_min: float, soc_min: float = 0.0,
                   config: SoeConfig = SoeConfig()) -> tuple[np.ndarray, np.ndarray]:
    """(energy left in Wh, cut-off SOC) per cell at ``config.rate_c`` (module docstring).

    ``ocv`` maps a ``(K, N)`` SOC array to volts (each column at its cell's temperature).
    Non-finite inputs give NaN for that cell.
    """
    s = np.asarray(soc, dtype=float)
    q = np.broadcast_to(np.asarray(capacity_ah, float), s.shape)
    r = np.broadcast_to(np.asarray(r_ss_ohm, float), s.shape)
    ok = np.isfinite(s) & np.isfinite(q) & (q > 0) & np.isfinite(r)
    s_u = np.where(ok, s, soc_min)
    z = _grid(s_u, soc_min, int(config.n_points))
    v = np.asarray(ocv(z.T), dtype=float).T - np.where(ok, r, 0.0)[:, None] * (config.rate_c * np.where(ok, q, 0.0))[:, None]
    z_cut = _cut_soc(z, v, v_min)
    # trapezoid over each grid interval's part above the cut (the voltage there >= v_min)
    lo = np.maximum(z[:, :-1], z_cut[:, None])
    width = np.maximum(z[:, 1:] - lo, 0.0)
    seg = 0.5 * (np.maximum(v[:, 1:], v_min) + np.maximum(v[:, :-1], v_min)) * width
    e = np.where(ok, q * seg.sum(axis=1), np.nan)
    return e, np.where(ok, z_cut, np.nan)


def time_to_empty_s(soc, cut_soc, capacity_ah, mean_current_a, *, idle_current_c: float = 0.01) -> np.ndarray:
    """Seconds until the cut-off SOC at the mean current (inf when not discharging)."""
    s, z, q, i = (np.asarray(a, dtype=float) for a in (soc, cut_soc, capacity_ah, mean_current_a))
    with np.errstate(divide="ignore", invalid="ignore"):
        t = 3600.0 * q * np.maximum(s - z, 0.0) / (-i)
    return np.where(i < -idle_current_c * q, t, np.inf)


def time_to_full_s(soc, capacity_ah, mean_current_a, *, soc_max: float = 1.0, idle_current_c: float = 0.01) -> np.ndarray:
    """Seconds until ``soc_max`` at the mean charge current (inf when not charging)."""
    s, q, i = (np.asarray(a, dtype=float) for a in (soc, capacity_ah, mean_current_a))
    with np.errstate(divide="ignore", invalid="ignore"):
        t = 3600.0 * q * np.maximum(soc_max - s, 0.0) / i
    return np.where(i > idle_current_c * q, t, np.inf)
