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

Time to full of a CC-CV charge (``time_to_full_s`` given the OCV and the cell now).  A charger
holds its current ``I_c`` until the terminal voltage reaches ``v_max``, then holds ``v_max`` while
the current tapers, and stops at ``I_end = end_current_c Q`` (C/20).  From the voltage ``v`` at
the current ``i`` now, with the overpotential the cell holds now kept (what the RC, diffusion and
hysteresis parts hold, as measured) and a change of current acting through the identified
steady-state resistance ``R_ss``, the voltage at SOC ``z`` and current ``I`` is
``v + OCV(z) - OCV(s) + R_ss (I - i)``, so the current the charger can give at ``z`` and the time to
full are::

    I(z) = min(I_c, i + (v_max - v - OCV(z) + OCV(s)) / R_ss),     I_c = max(I_m, i)
    t    = 3600 Q integral_{s}^{z_end} dz / I(z)

with ``z_end`` the first SOC where ``I(z)`` falls to ``I_end`` (``soc_max`` at most), by the
trapezoid rule on ``n_points`` SOCs from ``s`` to ``soc_max``, closer together toward the top
(``z_k = soc_max - (soc_max - s) (1 - k / (K - 1))^2``), where the taper is.  In the CV phase
(``v = v_max``) ``I(s) = i``: at the charger's own end current the time is 0.  Charging means
both ``I_m`` and ``i`` above ``idle_current_c * Q`` (else infinite): a charger that stopped shows
no time at once.  Before, ``3600 Q (soc_max - s) / I_m`` ignored the taper and never reached 0.
Measured on a synthetic Panasonic 18650PF CC-CV charge at 1C from 60 % (a 2-RC cell with a 1500 s
diffusion branch and hysteresis, ``tests/core/test_charge.py``): at the end of CC 644 s for 1664 s
left before, 1559 s now; the CV phase's median error 503 s before, 164 s now (the apparent
resistance ``eta / i`` in place of ``R_ss``: 422 s, its taper too slow); at the charger's stop
772 s before, 0 now; 5 min after it 1707 s before (rising with the decaying mean current), now
infinite from the first recomputation.

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
    end_current_c: Annotated[float, Gt(0)] = 0.05  # a CC-CV charge ends where its CV current falls to this (C)
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


def time_to_full_s(soc, capacity_ah, mean_current_a, *, soc_max: float = 1.0, idle_current_c: float = 0.01,
                   ocv: OcvFn | None = None, voltage_v=None, current_now_a=None, r_ss_ohm=None,
                   v_max: float = 4.2, end_current_c: float = 0.05, n_points: int = 21) -> np.ndarray:
    """Seconds until full: at the mean charge current to ``soc_max``; given ``ocv`` (the mean curve, a
    ``(K, N)`` SOC array to volts) and the cell now (``voltage_v``, ``current_now_a``, ``r_ss_ohm``), a
    CC-CV charge to ``v_max`` ending at ``end_current_c`` (module docstring).  Infinite when not charging."""
    s, q, i = (np.asarray(a, dtype=float) for a in (soc, capacity_ah, mean_current_a))
    if ocv is None:
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):  # as in time_to_empty_s
            t = 3600.0 * q * np.maximum(soc_max - s, 0.0) / i
        return np.where(i > idle_current_c * q, t, np.inf)
    v, i_now, r_ss = (np.asarray(a, dtype=float) for a in (voltage_v, current_now_a, r_ss_ohm))
    return _time_to_full_cccv(s, q, i, ocv, v, i_now, r_ss, soc_max=soc_max, idle_current_c=idle_current_c,
                              v_max=v_max, end_current_c=end_current_c, n_points=n_points)


def _time_to_full_cccv(s, q, i_m, ocv: OcvFn, v, i, r_ss, *, soc_max, idle_current_c, v_max, end_current_c,
                       n_points) -> np.ndarray:
    """:func:`time_to_full_s` of a CC-CV charge (module docstring), over the cells of a ``(N,)`` shape; a
    cell not charging, or with inputs not finite, gets inf."""
    shape = np.broadcast(s, q, i_m, v, i, r_ss).shape
    s, q, i_m, v, i, r_ss = (np.atleast_1d(_cells(a, shape)) for a in (s, q, i_m, v, i, r_ss))
    idle = idle_current_c * q
    ok = (i_m > idle) & (i > idle) & np.isfinite(s + q + v + r_ss) & (q > 0) & (r_ss > 0)
    r = np.where(ok, r_ss, 1.0)
    s_u = np.clip(np.where(ok, s, soc_max), 0.0, soc_max)
    frac = 1.0 - (1.0 - _fractions(int(n_points))) ** 2
    z = s_u + (soc_max - s_u) * frac[:, None]  # (K, N)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        o = np.asarray(ocv(z), dtype=float)
        i_end = end_current_c * q
        cur = np.minimum(np.maximum(i_m, i), i + (v_max - v - (o - o[0])) / r)  # I(z), (K, N)
        # the first grid point at or below the end current; the end between it and the one before
        below = cur <= i_end
        ends = below.any(axis=0)
        cells = np.arange(z.shape[1])
        k = np.where(ends, np.argmax(below, axis=0), z.shape[0] - 1)
        k0 = np.maximum(k - 1, 0)
        ca, cb, za, zb = cur[k0, cells], cur[k, cells], z[k0, cells], z[k, cells]
        f = np.where(ends & (ca > cb), np.clip((ca - i_end) / (ca - cb), 0.0, 1.0), 1.0)
        z_end = za + f * (zb - za)
        # the trapezoid of 1 / I over each interval's part below z_end, I never below the end current
        inv = 1.0 / np.maximum(cur, i_end)
        width = np.clip(np.minimum(z[1:], z_end) - z[:-1], 0.0, None)
        # (summed cell-major: each cell's sum the same bits alone as beside others; energy_left_wh's one_cell_sums)
        t = 3600.0 * q * np.ascontiguousarray((0.5 * (inv[1:] + inv[:-1]) * width).T).sum(axis=1)
    t = np.where(ok & np.isfinite(t), np.where(cur[0] <= i_end, 0.0, t), np.inf)
    return t.reshape(shape)
