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

Hook into the SOC estimator (optional, nothing in ``core/soc.py`` depends on
this module): the estimator forms ``v_o = v - OCV(soc)``; a hysteresis-aware
estimator forms ``v_o = v - OCV(soc) - H``.  :class:`HysteresisCompensatedSoc`
does exactly that without touching :class:`~bms_estimator.core.soc.SocEstimator`
(it hands ``v - H`` to the estimator, which is the same thing, since the
estimator subtracts the OCV itself) and shows the gain online: it keeps the
exponentially weighted mean square of the one-step-ahead voltage prediction
error of the compensated estimator and of an uncompensated shadow estimator
(optional, twice the cost) and reports ``gain_pct = 100 (1 - rms_with / rms_without)``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = [
    "HysteresisParams",
    "hysteresis_trajectory",
    "hysteresis_voltage",
    "HysteresisState",
    "HysteresisCompensatedSoc",
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
        i = np.broadcast_to(np.asarray(current_a, dtype=float), (self.n_cells,))
        i = np.where(np.isfinite(i), i, 0.0)
        sg = np.sign(i)
        self.s = np.where(np.abs(i) > self.rest_a, sg, self.s)
        self.voltage_v = self.m_v * self.h + self.m0_v * self.s
        a = np.exp(-np.abs(i) * self.gamma * (self.dt_s / 3600.0) / self.capacity_ah)
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


class HysteresisCompensatedSoc:
    """Optional wrapper: a :class:`~bms_estimator.core.soc.SocEstimator` that sees ``v - H``.

    The estimator forms ``v_o = v - OCV(soc)``; feeding it ``v - H`` makes that
    ``v_o = v - OCV(soc) - H``, the hysteresis-aware overpotential, with no change to
    the estimator.  The identified parameters, c0 compensation and capacity then
    refer to the hysteresis-free cell.

    Online gain: the model identified so far is simulated alongside (RC states
    advanced every sample with the identifier's current R0, R1, tau1, R2, tau2, c0,
    exact ZOH with step-mean output as in :func:`~bms_estimator.core.ecm.simulate_ecm`),
    and the squared difference between its voltage (``OCV(soc) + H + ...``) and the
    measured one is averaged over an exponential window of ``gain_window_s``
    (``rms_with_mv``).  With ``shadow=`` an uncompensated estimator (a second
    ``SocEstimator`` on the raw voltage, twice the cost) is simulated the same way
    (``rms_without_mv``) and ``gain_pct = 100 (1 - rms_with / rms_without)`` per cell
    (NaN without a shadow).
    """

    def __init__(self, estimator, hysteresis: HysteresisState, *, shadow=None, gain_window_s: float = 600.0):
        self.estimator = estimator
        self.hysteresis = hysteresis
        self.shadow = shadow
        n = estimator.n_cells
        self._alpha = min(1.0, estimator.dt_s / float(gain_window_s))
        self._sim = _RunningSimulation(n, estimator.dt_s)
        self._sim_shadow = _RunningSimulation(n, estimator.dt_s) if shadow is not None else None
        self.mse_with = np.full(n, np.nan)
        self.mse_without = np.full(n, np.nan)

    def _track(self, mse: np.ndarray, err: np.ndarray) -> np.ndarray:
        e2 = err * err
        fresh = ~np.isfinite(mse)
        upd = np.where(fresh, e2, (1.0 - self._alpha) * mse + self._alpha * e2)
        return np.where(np.isfinite(e2), upd, mse)

    def update(self, current_a, voltage_v, valid=None) -> None:
        est = self.estimator
        n = est.n_cells
        i = np.broadcast_to(np.asarray(current_a, dtype=float), (n,))
        v = np.broadcast_to(np.asarray(voltage_v, dtype=float), (n,))
        hv = self.hysteresis.update(i)
        est.update(current_a, v - hv, valid)
        self.mse_with = self._track(self.mse_with, est.v_o - self._sim.step(est, i))
        if self.shadow is not None:
            self.shadow.update(current_a, voltage_v, valid)
            self.mse_without = self._track(self.mse_without, self.shadow.v_o - self._sim_shadow.step(self.shadow, i))

    @property
    def rms_with_mv(self) -> np.ndarray:
        return 1e3 * np.sqrt(self.mse_with)

    @property
    def rms_without_mv(self) -> np.ndarray:
        return 1e3 * np.sqrt(self.mse_without)

    @property
    def gain_pct(self) -> np.ndarray:
        with np.errstate(invalid="ignore", divide="ignore"):
            return 100.0 * (1.0 - np.sqrt(self.mse_with / self.mse_without))

    # pass-throughs the service reads
    @property
    def soc(self) -> np.ndarray:
        return self.estimator.soc

    @property
    def params(self) -> dict[str, np.ndarray]:
        return self.estimator.params

    @property
    def hysteresis_v(self) -> np.ndarray:
        return self.hysteresis.voltage_v


class _RunningSimulation:
    """Free-running simulation of an estimator's current 2-RC model (N cells), step by step.

    ``step`` returns the simulated overpotential of this sample
    ``R0 i + sum_j mean_j + c0`` with the parameters the estimator holds after its
    update; the estimator's ``v_o`` is the measured voltage less the OCV it used
    (and less ``H`` for the compensated one), so the simulation error of the
    voltage is ``v_o - sim``.
    """

    def __init__(self, n_cells: int, dt_s: float):
        self.dt_s = float(dt_s)
        self.x = np.zeros((n_cells, 2))

    def step(self, est, current_a: np.ndarray) -> np.ndarray:
        p = est.params
        r = np.stack([p["r1_ohm"], p["r2_ohm"]], axis=1)
        tau = np.stack([p["tau1_s"], p["tau2_s"]], axis=1)
        ok = np.all(np.isfinite(r) & np.isfinite(tau) & (tau > 0), axis=1)
        tau = np.where(ok[:, None], tau, 1.0)
        r = np.where(ok[:, None], r, 0.0)
        pole = np.exp(-self.dt_s / tau)
        g = tau * (1.0 - pole) / self.dt_s
        ii = current_a[:, None]
        mean = self.x * g + r * ii * (1.0 - g)
        self.x = pole * self.x + r * (1.0 - pole) * ii
        return p["r0_ohm"] * current_a + mean.sum(axis=1) + p["c0_v"]


def _scalar_reference(current_a, dt_s, capacity_ah, gamma, h0=0.0) -> np.ndarray:
    """Plain loop of the recursion (tests compare the vectorised solution with it)."""
    h, out = float(h0), []
    for x in np.asarray(current_a, dtype=float):
        out.append(h)
        a = math.exp(-abs(x) * gamma * dt_s / (3600.0 * capacity_ah))
        h = a * h + (1.0 - a) * (1.0 if x > 0 else (-1.0 if x < 0 else 0.0))
    return np.asarray(out)
