"""Continuous-time 2-RC identification with the LIF and recursive instrumental variables.

The seed paper's future work. The LIF regression (:mod:`bms_estimator.core.lif`)::

    y = f1^2 v_o = phi' theta + e,   phi = [f1f2 v_o, f2^2 v_o, f1^2 i, f1f2 i, f2^2 i, T^2]

is an *equation-error* model: the measured v_o (voltage noise, OCV-model error)
sits in the regressor's first two columns as well as in y, and the filtered
noise f1^2 n - th1 f1f2 n - th2 f2^2 n in e is correlated with them, so least
squares (:class:`~bms_estimator.core.identifier.LifEstimator`) is biased.

Recursive IV (:class:`~bms_estimator.core.riv.RecursiveIv`, the math there) uses
the normal equations ``sum zeta (y - phi' theta) = 0`` with the instrument::

    zeta = [f1f2 x, f2^2 x, f1^2 i, f1f2 i, f2^2 i, T^2]

where x is the output of an *auxiliary model* driven by the measured current
only: the 2-RC model with the last admissible parameters (R0, R_j, tau_j, c0),
simulated sample by sample for period-mean data (see
:mod:`bms_estimator.core.ecm`)::

    p_j = exp(-Ts / tau_j),   g_j = tau_j (1 - p_j) / Ts
    x[k]       = R0 i[k] + sum_j (s_j[k] g_j + R_j i[k] (1 - g_j)) + c0
    s_j[k+1]   = p_j s_j[k] + R_j (1 - p_j) i[k]

x carries none of the voltage noise, so zeta is uncorrelated with e, and it
follows the noise-free v_o as well as the model does, so sum zeta phi' stays
well conditioned. The auxiliary parameters are refreshed from the last
admissible estimate every ``iv_model_every`` samples (CONTSID's ``rivsvf`` /
``rsrivc`` do the same), the RC states run on across refreshes. Because x
depends only on the current, the IV estimate approaches the output-error
(simulation) optimum, the criterion the validation simulation scores.

No refined (SRIVC-like) prefilter: filtering v_o, i and x by the auxiliary
model's ``a1 a2 / ((s+a1)(s+a2))`` before the LIF was measured worse (synthetic
spread of R0 1.4 -> 9.4 %, tau1 11 -> 24 %; worse on 54 of 66 measured 25 degC
pairs): the LIF's f2^2 already low-passes, 1/A(s) on top starves the fast branch.

Everything else is the LIF identifier's: the block least-squares start (no
instruments exist before a first model), the admissibility guard and reset to
the last admissible theta, the trace limit, restarts, the c0 prior, the OCV
bias shift (which moves x's history and c0 with v_o's).
"""

from __future__ import annotations

import numpy as np

from .identifier import IdentifierConfig, LifEstimator
from .lif import LifHistory
from .riv import RecursiveIv

__all__ = ["LifIvEstimator"]


class LifIvEstimator(LifEstimator):
    """LIF + weighted recursive IV with an auxiliary-model instrument, N cells at once."""

    rls_class = RecursiveIv

    def __init__(self, n_cells, dt_s, capacity_ah, config: IdentifierConfig = IdentifierConfig()):
        super().__init__(n_cells, dt_s, capacity_ah, config)
        n = self.n_cells
        self._aux_state = np.zeros((n, 2))  # RC voltages of the auxiliary model
        self._aux_age = 0  # samples since the last refresh of the auxiliary model
        self._zeta = np.zeros((n, self.n_params))
        self._refresh_aux()

    def _init_scales(self) -> None:
        super()._init_scales()
        self.history = LifHistory(self.n_cells, self.config.window, self.dt_s, 1.0, aux=True)

    def _refresh_aux(self) -> None:
        p = self.params
        self._set_aux(np.stack([p.r0_ohm, p.r1_ohm, p.tau1_s, p.r2_ohm, p.tau2_s, p.c0_v], axis=1))

    def _set_aux(self, params: np.ndarray) -> None:
        """Auxiliary-model coefficients from (N, 6) rows of r0, r1, tau1, r2, tau2, c0."""
        self._aux_params = params.copy()
        r0, r1, tau1, r2, tau2, c0 = params.T
        tau = np.stack([tau1, tau2], axis=1)
        r = np.stack([r1, r2], axis=1)
        pole = np.exp(-self.dt_s / tau)
        g = tau * (1.0 - pole) / self.dt_s
        self._aux_pole = pole
        self._aux_in = r * (1.0 - pole)  # state input gain
        self._aux_state_out = g  # state -> period-mean output
        self._aux_direct = r0 + (r * (1.0 - g)).sum(axis=1)  # current -> output within the period
        self._aux_c0 = c0.copy()
        self._aux_age = 0

    def _regress(self, i, v, ok):
        if self._aux_age >= self.config.iv_model_every:
            self._refresh_aux()
        self._aux_age += 1
        x = self._aux_step(np.where(np.isfinite(i), i, 0.0))
        y, phi, ready = super()._regress(i, v, ok, x)
        self._zeta = self.history.instruments(phi)
        return y, phi, ready

    def _aux_step(self, i_a: np.ndarray) -> np.ndarray:
        """The auxiliary model's output x for current i_a (A), and its RC states one step on."""
        x = self._aux_direct * i_a + (self._aux_state * self._aux_state_out).sum(axis=1) + self._aux_c0
        self._aux_state = self._aux_pole * self._aux_state + self._aux_in * i_a[:, None]
        return x

    def rest(self, gap_s, cells):
        """The window restarts (:meth:`Identifier.rest`); the auxiliary model's RC voltages relax,
        ``x_j <- x_j exp(-gap / tau_j)`` (zero current over the gap)."""
        super().rest(gap_s, cells)
        decay = self._aux_pole ** (gap_s / self.dt_s)  # exp(-gap / tau_j)
        self._aux_state = np.where(cells[:, None], self._aux_state * decay, self._aux_state)

    def _learn(self, phi, y, learn):
        return self.rls.update(phi, y, learn, zeta=self._zeta)

    def _shift_history(self, dv):
        super()._shift_history(dv)  # v_o and x histories
        self._aux_c0 = self._aux_c0 - dv
        self._aux_params[:, 5] = self._aux_c0

    def state_dict(self):
        s = super().state_dict()
        s.update(aux_state=self._aux_state.copy(), aux_params=self._aux_params.copy(),
                 aux_age=np.array(self._aux_age))
        return s

    def load_state_dict(self, s):
        super().load_state_dict(s)
        state = np.asarray(s["aux_state"], dtype=float)
        params = np.asarray(s["aux_params"], dtype=float)
        if state.shape != self._aux_state.shape or params.shape != self._aux_params.shape:
            raise ValueError("auxiliary-model state does not match the number of cells")
        self._set_aux(params)
        self._aux_state = state.copy()
        self._aux_age = int(s["aux_age"])
