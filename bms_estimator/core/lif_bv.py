"""Continuous-time 2-RC identification with a kinetic (Butler-Volmer-like) term: ``lif-iv-bv``.

Why.  On the measured cells the polarisation resistance falls with the current
magnitude (the README's pulse-resistance table: the 10 s HPPC resistance of the
Panasonic cell falls from 78.7 to 58.0 mOhm between 0.5 C and 6 C pulses at
0 degC, the 1 s part stays): charge-transfer kinetics (Butler-Volmer,
``eta = (R T / alpha F) asinh(i / 2 i_ex)``), which the linear 2-RC model cannot
carry over from a gentle drive cycle to an aggressive one.

Model (current ``i`` positive = charge; the kinetic input is odd, ~ -i^3 / (6 i0^2) for
small currents and ~ -i + i0 ln(2|i|/i0) sign(i) for large ones)::

    u(i)   = i0 asinh(i / i0) - i                         (the kinetic input, A)
    v_o    = R0 i + x1 + x2 + c0
    x_j'   = -x_j / tau_j + (R_j i + K_j u) / tau_j

i.e. the chord resistance of RC branch j at a constant current i is
``R_j - K_j (1 - asinh(i/i0) / (i/i0))``: R_j for small currents, falling
towards R_j - K_j for large ones when K_j > 0.  The ohmic R0 stays linear: the
measured pulse resistance at 0.2 s does not change with the current, the fall
is in the polarisation (README, pulse-resistance table); a K0 u term beside R0
(three columns instead of two) measured no better on the 25 degC pairs
(median 11.2 against 10.8 mV on 36 of them).  ``i0`` is fixed per cell, in
C-rate (``IdentifierConfig.bv_current_c``, 1 C by default).

Linear in the parameters.  With a_j = 1/tau_j the ODE of the 2-RC model gains
two terms in u::

    v_o'' = th1 v_o' + th2 v_o + th3 i'' + th4 i' + th5 i + th6 + th7 u' + th8 u
    th7 = K1 a1 + K2 a2,   th8 = a1 a2 (K1 + K2)

so the LIF regression (:mod:`bms_estimator.core.lif`) takes two more columns
``[f1f2 u, f2^2 u]`` and both RLS and the recursive IV apply unchanged.
``(K1, K2)`` follow from ``(th1, th2, th7, th8)`` exactly as ``(R1, R2)`` from
``(th1, th2, th4, th5)`` with R0 = 0
(:func:`~bms_estimator.core.params.ct_physical_from_theta`).  The prior is
K = 0 (the 2-RC model), so an unexcited u direction stays linear.

Identification: :class:`~bms_estimator.core.lif_iv.LifIvEstimator`'s recursive
IV, its auxiliary model carrying the kinetic term too (the instrument is the LIF
of its simulated output), and the same block start, trace limit, restarts, c0
prior and OCV-bias shift.  The admissibility guard adds ``|K_j| <= R_j`` (no
branch resistance below zero at any current, nor more than doubled).  Requiring
``K_j >= 0`` (Butler-Volmer only lowers the resistance) measured worse: the
guard then rejects every update of a cell whose data show no current
dependence (median 11.7 against 10.8 mV on the same 36 pairs).  Projecting the
estimate onto ``K_j >= 0`` instead (clipping K in theta, the rest kept) helped
on measured pairs but ran R2 of one synthetic seed in four to zero (README).
"""

from __future__ import annotations

import numpy as np

from .identifier import IdentifierConfig
from .lif import LifHistory
from .lif_iv import LifIvEstimator
from .params import PhysicalParams, ct_physical_from_theta, ct_theta_from_physical

__all__ = ["kinetic_input", "LifIvBvEstimator", "KINETIC_KEYS"]

#: the kinetic gains in a parameter dict (ohm), and the kinetic current scale i0 (A)
KINETIC_KEYS = ("k1_ohm", "k2_ohm", "i0_a")


def kinetic_input(current_a: np.ndarray, i0_a: np.ndarray | float) -> np.ndarray:
    """``u = i0 asinh(i / i0) - i``: the odd, sub-linear part of a Butler-Volmer overpotential."""
    i = np.asarray(current_a, dtype=float)
    return i0_a * np.arcsinh(i / i0_a) - i


class LifIvBvEstimator(LifIvEstimator):
    """LIF + recursive IV for the 2-RC model with a kinetic term (module docstring), N cells at once."""

    n_params = 8
    # of the history's 9 columns (6 of the 2-RC model, f1^2 u, f1f2 u, f2^2 u) the model's 8
    _cols = np.array([0, 1, 2, 3, 4, 5, 7, 8])

    def __init__(self, n_cells, dt_s, capacity_ah, config: IdentifierConfig = IdentifierConfig()):
        self._i0_c = float(config.bv_current_c)
        super().__init__(n_cells, dt_s, capacity_ah, config)
        self.i0_a = self._i0_c * self.i_ref_a

    def _init_scales(self) -> None:
        self.history = LifHistory(self.n_cells, self.config.window, self.dt_s, 1.0, aux=True, extra_inputs=1)
        scale = self.history.scale[None, :] * np.ones((self.n_cells, 1))
        scale[:, 2:5] *= self.i_ref_a[:, None]
        scale[:, 6:9] *= self.i_ref_a[:, None]
        self._scale = scale[:, self._cols]

    def _theta_s_from_physical(self, r0, r1, tau1, r2, tau2, c0, k=(0.0, 0.0)):
        th = ct_theta_from_physical(r0, r1, tau1, r2, tau2, c0)
        th_k = ct_theta_from_physical(0.0, k[0], tau1, k[1], tau2)[..., 3:5]
        return np.concatenate([th, np.broadcast_to(th_k, th[..., 3:5].shape)], axis=-1) * self._scale

    def _kinetic(self, theta_s: np.ndarray) -> np.ndarray:
        """(N, 2) kinetic gains K1, K2 (ohm, branches fast first) of a scaled theta."""
        th = theta_s / self._scale
        zero = np.zeros((len(th), 1))
        p = ct_physical_from_theta(np.concatenate([th[:, :2], zero, th[:, 6:8], zero], axis=1))
        return np.stack([p.r1_ohm, p.r2_ohm], axis=1)

    def _physical(self, theta_s):
        p = ct_physical_from_theta(theta_s[:, :6] / self._scale[:, :6], tau_min_s=self.config.tau_min_s,
                                   tau_max_s=self.config.tau_max_s)
        k = self._kinetic(theta_s)
        r = np.stack([p.r1_ohm, p.r2_ohm], axis=1)
        with np.errstate(invalid="ignore"):
            ok = p.admissible & np.all(np.isfinite(k) & (np.abs(k) <= r), axis=1)
        return PhysicalParams(*p._arrays(), admissible=ok)

    def _regress(self, i, v, ok):
        y, phi, ready = super()._regress(i, v, ok)
        self._zeta = self._zeta[:, self._cols]
        return y, phi[:, self._cols], ready

    @property
    def kinetic_ohm(self) -> np.ndarray:
        """(N, 2) K1, K2 of the last admissible estimate (zero until identified)."""
        return self._kinetic(self.theta_good)

    def param_dict(self) -> dict[str, np.ndarray]:
        out = super().param_dict()
        k = self.kinetic_ohm
        out.update(k1_ohm=k[:, 0], k2_ohm=k[:, 1], i0_a=self.i0_a)
        return out

    def _extra_inputs(self, i_c):
        return kinetic_input(i_c, self._i0_c)[None, :]

    # the auxiliary model (instrument) with the kinetic term -----------------------------
    def _refresh_aux(self) -> None:
        p = self.params
        k = self.kinetic_ohm
        self._set_aux(np.stack([p.r0_ohm, p.r1_ohm, p.tau1_s, p.r2_ohm, p.tau2_s, p.c0_v, *k.T], axis=1))

    def _set_aux(self, params: np.ndarray) -> None:
        """Auxiliary-model coefficients from (N, 8) rows of r0, r1, tau1, r2, tau2, c0, k1, k2."""
        super()._set_aux(params[:, :6])
        self._aux_params = params.copy()
        k = params[:, 6:8]
        self._aux_k_in = k * (1.0 - self._aux_pole)
        self._aux_k_direct = (k * (1.0 - self._aux_state_out)).sum(axis=1)

    def _aux_step(self, i_a):
        u = kinetic_input(i_a, self.i0_a)
        x = (self._aux_direct * i_a + self._aux_k_direct * u + (self._aux_state * self._aux_state_out).sum(axis=1)
             + self._aux_c0)
        self._aux_state = self._aux_pole * self._aux_state + self._aux_in * i_a[:, None] + self._aux_k_in * u[:, None]
        return x

    def predict_static(self, current_a):
        """Steady-state overpotential for a constant current: (R0+R1+R2) i + (K1+K2) u(i) + c0."""
        return super().predict_static(current_a) + self.kinetic_ohm.sum(axis=1) * kinetic_input(current_a, self.i0_a)
