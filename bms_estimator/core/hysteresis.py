"""One-state OCV hysteresis with an instantaneous term (Plett's model), offline and online.

Model (current ``i`` positive = charge, as everywhere in this package)::

    A[k]    = exp(-|i[k]| gamma Ts / (3600 Q))                  (0 < A <= 1)
    h[k+1]  = A[k] h[k] + (1 - A[k]) sgn(i[k])                  (-1 <= h <= 1)
    s[k]    = sgn(i[k])  if |i[k]| > i_rest  else  s[k-1]       (instantaneous sign, held at rest)
    H[k]    = M h[k] + M0 s[k]                                  (voltage added to the OCV)

``h`` is the dynamic hysteresis state: it relaxes towards +1 while charging and
towards -1 while discharging, at a rate proportional to the charge throughput
(``gamma`` = e-folding per unit SOC: after ``1/gamma`` of SOC in one direction
``h`` has covered 63 % of the way), so it stays put at rest.  ``M`` [V] is its
amplitude (about half the charge-minus-discharge OCV gap of a slow test, less the
``I R`` drop), ``M0`` [V] the instantaneous part that flips with the current's
direction.  The charge branch sits above the discharge branch, so a positive
``M`` raises the voltage after charging.  ``H[k]`` uses the state at the start of
sample ``k`` (before sample ``k``'s current moved it) and the sign of sample
``k``'s current, the same order as the ECM's ZOH recursion.

Offline (:func:`hysteresis_trajectory`) one cell over time; online
(:class:`HysteresisState`) N cells, one sample per call, vectorised over cells.

The SOC estimator (:mod:`bms_estimator.core.soc`) runs :class:`HysteresisState`
for each cell and reads the OCV on the branch it gives (``OCV(soc) + h H(soc)``,
with ``H`` the table's half gap); ``diagnose`` fits ``M``, ``M0`` and ``gamma``
offline to show what the hysteresis explains in a recording.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .cells import all_cells, cell_vector

__all__ = [
    "HysteresisParams",
    "hysteresis_trajectory",
    "hysteresis_voltage",
    "HysteresisState",
]


@dataclass(frozen=True)
class HysteresisParams:
    """Parameters of the one-state hysteresis (see the module docstring).

    ``rest_fraction_c``: below ``rest_fraction_c * Q`` amperes the current counts as
    rest for the instantaneous sign (default C/50).
    """

    m_v: float
    m0_v: float
    gamma: float
    h0: float = 0.0
    rest_fraction_c: float = 0.02

    def as_dict(self) -> dict[str, float]:
        return {"m_v": self.m_v, "m0_v": self.m0_v, "gamma": self.gamma, "h0": self.h0,
                "rest_fraction_c": self.rest_fraction_c}


def _rates(current_a: np.ndarray, dt_s: float, capacity_ah: float, gamma: float) -> np.ndarray:
    return np.exp(-np.abs(current_a) * (gamma * dt_s / (3600.0 * capacity_ah)))


def hysteresis_trajectory(
    current_a: np.ndarray,
    dt_s: float,
    capacity_ah: float,
    gamma: float,
    *,
    h0: float = 0.0,
    s0: float = 0.0,
    rest_fraction_c: float = 0.02,
    unit_h0: bool = False,
) -> tuple[np.ndarray, np.ndarray] | tuple[np.ndarray, np.ndarray, np.ndarray]:
    """States ``h[k]`` (start of sample k) and ``s[k]`` (held sign) of one cell over time.

    With ``unit_h0=True`` also returns ``P[k] = prod_{l<k} A[l]``: ``h`` is linear in
    ``h0`` (``h = h(h0=0) + h0 P``), which lets a batch fit estimate ``M h0`` by
    linear least squares.

    The recursion is a first-order linear filter with a time-varying pole; it is
    solved in blocks of the log-cumulative pole (``h[k] = e^{L_k} (h0 + sum_l
    e^{-L_{l+1}} (1 - A_l) sgn_l)``, ``L_k = sum_{l<k} ln A_l``), restarting each block
    before ``|L|`` can overflow, so it is vectorised numpy throughout.
    """
    i = np.asarray(current_a, dtype=float)
    n = i.size
    a = _rates(i, dt_s, capacity_ah, gamma)
    sg = np.sign(i)
    # ln A = -|i| gamma Ts / (3600 Q), floored (A = e^-300 is as good as 0) so one block never overflows
    la = np.maximum(-np.abs(i) * (gamma * dt_s / (3600.0 * capacity_ah)), -300.0)
    a = np.exp(la)
    cum = np.concatenate([[0.0], np.cumsum(la)])  # L_k, k = 0..n
    h = np.empty(n)
    p = np.empty(n) if unit_h0 else None
    drive = (1.0 - a) * sg
    start, h_start, p_start = 0, float(h0), 1.0
    h_zero_start = 0.0
    hz = np.empty(n) if unit_h0 else None
    limit = 300.0
    while start < n:
        base = cum[start]
        # block end: where L drops by more than `limit` from the block start
        stop = int(np.searchsorted(-(cum[start:n + 1] - base), limit, side="right")) + start
        stop = min(max(stop, start + 1), n)
        rel = cum[start:stop + 1] - base  # L relative to the block start, 0 .. > -limit
        e_neg = np.exp(-rel[1:])  # e^{-L_{l+1}}, l = start..stop-1  (<= e^{limit})
        acc = np.concatenate([[0.0], np.cumsum(e_neg * drive[start:stop])])  # sum_{l<k}
        decay = np.exp(rel[:-1])  # e^{L_k}, k = start..stop-1
        h[start:stop] = decay * (h_start + acc[:-1])
        if unit_h0:
            p[start:stop] = p_start * decay
            hz[start:stop] = decay * (h_zero_start + acc[:-1])
            h_zero_start = float(np.exp(rel[-1]) * (h_zero_start + acc[-1]))
            p_start = float(p_start * np.exp(rel[-1]))
        h_start = float(np.exp(rel[-1]) * (h_start + acc[-1]))
        start = stop
    s = _held_sign(i, rest_fraction_c * capacity_ah, s0)
    if unit_h0:
        return hz, s, p
    return h, s


def _held_sign(i: np.ndarray, threshold_a: float, s0: float) -> np.ndarray:
    """sgn(i) where |i| > threshold, else the last such sign (s0 before the first)."""
    moving = np.abs(i) > threshold_a
    idx = np.where(moving, np.arange(i.size), -1)
    np.maximum.accumulate(idx, out=idx)
    return np.where(idx >= 0, np.sign(i[np.maximum(idx, 0)]), float(s0))


def hysteresis_voltage(
    current_a: np.ndarray, dt_s: float, capacity_ah: float, params: HysteresisParams, *, s0: float = 0.0
) -> np.ndarray:
    """``H[k] = M h[k] + M0 s[k]`` over a current profile (one cell)."""
    h, s = hysteresis_trajectory(current_a, dt_s, capacity_ah, params.gamma, h0=params.h0, s0=s0,
                                 rest_fraction_c=params.rest_fraction_c)
    return params.m_v * h + params.m0_v * s


class HysteresisState:
    """Online hysteresis of N cells (vectorised over cells), one sample per :meth:`update`.

    Args:
        n_cells: number of cells.
        capacity_ah: capacity per cell (scalar or (N,)), the one the coulomb count uses.
        params: hysteresis parameters (scalars shared by the cells, or (N,) arrays via
            ``m_v``/``m0_v``/``gamma`` of a params object holding arrays).
        dt_s: sample period.
    """

    def __init__(self, n_cells: int, capacity_ah: float | np.ndarray, params: HysteresisParams, dt_s: float = 1.0):
        self.n_cells = int(n_cells)
        self.dt_s = float(dt_s)
        self.capacity_ah = np.broadcast_to(np.asarray(capacity_ah, dtype=float), (self.n_cells,)).copy()
        self.m_v = np.broadcast_to(np.asarray(params.m_v, dtype=float), (self.n_cells,)).copy()
        self.m0_v = np.broadcast_to(np.asarray(params.m0_v, dtype=float), (self.n_cells,)).copy()
        self.gamma = np.broadcast_to(np.asarray(params.gamma, dtype=float), (self.n_cells,)).copy()
        self.rest_a = params.rest_fraction_c * self.capacity_ah
        self.h = np.full(self.n_cells, float(params.h0))
        self.s = np.zeros(self.n_cells)
        self.voltage_v = np.zeros(self.n_cells)

    def update(self, current_a: float | np.ndarray) -> np.ndarray:
        """Hysteresis voltage ``H[k]`` of this sample (then the state moves on with its current)."""
        i = cell_vector(current_a, self.n_cells)
        finite = np.isfinite(i)
        if not all_cells(finite):
            i = np.where(finite, i, 0.0)
        sg = np.sign(i)
        magnitude = np.abs(i)
        self.s = np.where(magnitude > self.rest_a, sg, self.s)
        self.voltage_v = self.m_v * self.h + self.m0_v * self.s
        a = np.exp(-magnitude * self.gamma * (self.dt_s / 3600.0) / self.capacity_ah)
        self.h = a * self.h + (1.0 - a) * sg
        return self.voltage_v

    def state_dict(self) -> dict[str, np.ndarray]:
        return {"h": self.h.copy(), "s": self.s.copy()}

    def load_state_dict(self, s: dict[str, np.ndarray]) -> None:
        for key in ("h", "s"):
            if np.shape(s[key]) != (self.n_cells,):
                raise ValueError(f"state field {key!r} has shape {np.shape(s[key])}, expected ({self.n_cells},)")
        self.h = np.asarray(s["h"], dtype=float).copy()
        self.s = np.asarray(s["s"], dtype=float).copy()
