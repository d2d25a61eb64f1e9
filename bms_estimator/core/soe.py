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
from functools import lru_cache
from typing import Annotated, Callable

import numpy as np
from annotated_types import Ge, Gt

from .bounds import check_bounds

__all__ = ["SoeConfig", "energy_left_wh", "time_to_empty_s", "time_to_full_s"]

OcvFn = Callable[[np.ndarray], np.ndarray]


@dataclass(frozen=True)
class SoeConfig:
    rate_c: Annotated[float, Ge(0)] = 0.5  # the stated discharge rate of the energy left, C
    n_points: Annotated[int, Ge(3)] = 21  # SOC grid of the integral
    idle_current_c: Annotated[float, Gt(0)] = 0.01  # below this mean current (C), no time to empty/full
    mean_current_tau_s: Annotated[float, Gt(0)] = 300.0  # the "recent" mean current's time constant

    def __post_init__(self) -> None:
        check_bounds(self)


@lru_cache(maxsize=8)
def _fractions(n: int) -> np.ndarray:
    f = np.linspace(0.0, 1.0, n)
    f.setflags(write=False)
    return f


def _cells(a, shape) -> np.ndarray:
    a = np.asarray(a, dtype=float)
    return a if a.shape == shape else np.broadcast_to(a, shape)


def energy_left_wh(soc, capacity_ah, r_ss_ohm, ocv: OcvFn, *, v_min: float, soc_min: float = 0.0,
                   config: SoeConfig = SoeConfig(), one_cell_sums: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """(energy left in Wh, cut-off SOC) per cell at ``config.rate_c`` (module docstring).

    ``ocv`` maps a ``(K, N)`` SOC array to volts (each column at its cell's temperature).
    Non-finite inputs give NaN for that cell.

    The grid is ``(K, N)``, the cells along the last axis: the loaded voltage ``v_k`` at
    ``z_k = soc_min + (s - soc_min) k / (K - 1)``; the cut-off lies between the highest
    grid point below v_min and the next (linear there); the lowest grid SOC when no point
    is below, the top when the top already is.

    ``one_cell_sums``: each cell's sum over its grid as a one-cell call sums it, for independent
    one-cell packs side by side (the batch's stacked one-cell drives). numpy sums a ``(K, 1)``
    array's one contiguous column pairwise (eight partial sums), a ``(K, N)`` one row by row: the
    last bit differs. Summed cell-major (each cell's ``K`` values one contiguous row), every cell
    gets the pairwise sum.
    """
    s = np.asarray(soc, dtype=float)
    q = _cells(capacity_ah, s.shape)
    r = _cells(r_ss_ohm, s.shape)
    ok = np.isfinite(s) & np.isfinite(q) & (q > 0) & np.isfinite(r)
    s_u = np.where(ok, s, soc_min)
    k_pts = int(config.n_points)
    frac = _fractions(k_pts)
    span = np.maximum(s_u, soc_min) - soc_min
    z = soc_min + span * frac[:, None]  # (K, N)
    v = np.asarray(ocv(z), dtype=float) - np.where(ok, r, 0.0) * (config.rate_c * np.where(ok, q, 0.0))
    below = v < v_min
    any_below = below.any(axis=0)
    k = np.where(any_below, k_pts - 1 - np.argmax(below[::-1], axis=0), 0)
    k1 = np.minimum(k + 1, k_pts - 1)
    cells = np.arange(v.shape[1])
    va, vb = v[k, cells], v[k1, cells]
    za, zb = soc_min + span * frac[k], soc_min + span * frac[k1]
    with np.errstate(divide="ignore", invalid="ignore"):
        f = np.clip((v_min - va) / (vb - va), 0.0, 1.0)
    z_cut = np.where(any_below, np.where(k1 > k, za + f * (zb - za), zb), z[0])
    # trapezoid over each grid interval's part above the cut (the voltage there >= v_min)
    width = np.maximum(z[1:] - np.maximum(z[:-1], z_cut), 0.0)
    vm = np.maximum(v, v_min)
    seg = 0.5 * (vm[1:] + vm[:-1]) * width
    total = np.ascontiguousarray(seg.T).sum(axis=1) if one_cell_sums else seg.sum(axis=0)
    e = np.where(ok, q * total, np.nan)
    return e, np.where(ok, z_cut, np.nan)


def time_to_empty_s(soc, cut_soc, capacity_ah, mean_current_a, *, idle_current_c: float = 0.01) -> np.ndarray:
    """Seconds until the cut-off SOC at the mean current (inf when not discharging)."""
    s, z, q, i = (np.asarray(a, dtype=float) for a in (soc, cut_soc, capacity_ah, mean_current_a))
    # a mean current decayed to a subnormal (a long rest) overflows here; it is idle, and masked below
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        t = 3600.0 * q * np.maximum(s - z, 0.0) / (-i)
    return np.where(i < -idle_current_c * q, t, np.inf)


def time_to_full_s(soc, capacity_ah, mean_current_a, *, soc_max: float = 1.0, idle_current_c: float = 0.01) -> np.ndarray:
    """Seconds until ``soc_max`` at the mean charge current (inf when not charging)."""
    s, q, i = (np.asarray(a, dtype=float) for a in (soc, capacity_ah, mean_current_a))
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):  # as in time_to_empty_s
        t = 3600.0 * q * np.maximum(soc_max - s, 0.0) / i
    return np.where(i > idle_current_c * q, t, np.inf)
