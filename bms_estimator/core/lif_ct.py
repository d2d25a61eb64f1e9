"""Continuous-time 2-RC identification with a charge-transfer (Butler-Volmer) fast branch: ``lif-iv-ct``.

Why.  The polarisation resistance of the measured cells falls with the current
(README, pulse-resistance table); :mod:`bms_estimator.core.lif_bv` *fits* a gain
per branch for it, which rests on little data where the training file is gentle.
Butler-Volmer fixes the *shape* of the current dependence from what the model
already has.  For a symmetric charge-transfer step (alpha = 1/2)::

    eta(i) = (2 R T / F) asinh(i / (2 i_ex)),   small-signal  R_ct = d eta/di (0) = R T / (F i_ex)

so with the thermal voltage ``V_T = 2 R T / F`` (51.4 mV at 25 degC)::

    eta(i) = V_T asinh(i R_ct / V_T)

and the large-signal overpotential follows from the small-signal resistance and
the temperature alone: no new parameter.

Model (current ``i`` positive = charge).  The fast branch's resistance R1 is
charge transfer to a fixed share ``f`` (``IdentifierConfig.ct_fraction``, 1 by
default; a physical split, not fitted); R0 (the pulse table's 0.2 s resistance,
which does not fall) and the slow branch R2 stay linear::

    v_o    = R0 i + x1 + x2 + c0
    x1'    = (-x1 + (1 - f) R1 i + V_T asinh(i f R1 / V_T)) / tau1
    x2'    = (-x2 + R2 i) / tau2

i.e. branch 1 is driven by ``R1 i + w`` with the *kinetic excess*::

    w(i; R1) = V_T asinh(i f R1 / V_T) - f R1 i        (odd, ~ -(f R1 i)^3 / (6 V_T^2) for small i)

Identification (a Hammerstein input with a known nonlinearity).  ``w`` depends on
R1, unknown; the recursive IV of :class:`~bms_estimator.core.lif_iv.LifIvEstimator`
already keeps an *auxiliary model* with the last admissible parameters, refreshed
every ``iv_model_every`` samples.  Its R1 and tau1 make ``w`` a known input, and
its response through the fast branch, simulated sample by sample for period-mean
data (as the auxiliary model, :mod:`bms_estimator.core.ecm`)::

    p1 = exp(-Ts / tau1),  g1 = tau1 (1 - p1) / Ts
    d[k]     = s[k] g1 + w[k] (1 - g1)
    s[k+1]   = p1 s[k] + (1 - p1) w[k]

is taken off the measured overpotential: the corrected ``v_c = v_o - d`` is the
*linear* 2-RC model's output of ``i`` (exactly, once the auxiliary R1, tau1 are the
cell's), so the LIF regression on ``v_c``, its six columns, the theta -> (R0, R1,
tau1, R2, tau2, c0) map, the recursive IV with its linear auxiliary-model
instrument, the block start, trace limit, guard, restarts, c0 prior and OCV-bias
shift all apply unchanged.  The regression stays linear in theta; R1 enters the
nonlinearity only through the auxiliary model (a fixed point, as the instrument).

Simulation (``analysis.simulate_with_params``): the linear 2-RC model plus ``w``
through the fast branch, with the looked-up R1 at each sample, so a model identified
on a gentle file carries a lower polarisation resistance to an aggressive one.

Limits (measured, README "Without a fitted gain").  For ``|i| f R1 >> V_T`` the branch
voltage ``~ V_T ln(2 |i| f R1 / V_T)`` hardly depends on R1, so the fixed point
R1 = R1_aux is weakly determined and need not be unique: on one measured file two
solutions exist and a 2 K change of ``V_T``'s temperature switches between them.
On a linear cell the imposed shape costs (R1 12-13 % high on the synthetic cell).
"""

from __future__ import annotations

import numpy as np

from .arrhenius import KELVIN, R_GAS
from .identifier import IdentifierConfig
from .lif_iv import LifIvEstimator

__all__ = ["thermal_voltage", "kinetic_excess", "LifIvCtEstimator", "CT_KEYS"]

FARADAY = 96485.33212  # C / mol

#: the charge-transfer model's entries in a parameter dict: V_T (V) and the charge-transfer share of R1
CT_KEYS = ("ct_vt_v", "ct_fraction")


def thermal_voltage(temperature_c) -> np.ndarray | float:
    """``V_T = 2 R T / F`` (V) of a symmetric charge-transfer step at ``temperature_c`` (degC)."""
    return 2.0 * R_GAS * (np.asarray(temperature_c, dtype=float) + KELVIN) / FARADAY


def kinetic_excess(current_a, r1_ohm, fraction, vt_v) -> np.ndarray:
    """``w = V_T asinh(i f R1 / V_T) - f R1 i`` (V): what the fast branch takes beyond ``R1 i``."""
    r_ct = np.asarray(fraction, dtype=float) * np.asarray(r1_ohm, dtype=float)
    vt = np.asarray(vt_v, dtype=float)
    drop = np.asarray(current_a, dtype=float) * r_ct
    return vt * np.arcsinh(drop / vt) - drop


class LifIvCtEstimator(LifIvEstimator):
    """LIF + recursive IV for the 2-RC model whose fast branch is charge transfer (module docstring)."""

    def __init__(self, n_cells, dt_s, capacity_ah, config: IdentifierConfig = IdentifierConfig()):
        self.vt_v = float(thermal_voltage(config.ct_temperature_c))
        self.ct_fraction = float(config.ct_fraction)
        self._ct_state = np.zeros(int(n_cells))  # fast-branch response to the kinetic excess w
        super().__init__(n_cells, dt_s, capacity_ah, config)

    def _set_aux(self, params: np.ndarray) -> None:
        super()._set_aux(params)
        self._ct_r1 = params[:, 1].copy()  # the auxiliary model's R1: the nonlinearity's small-signal resistance

    def _ct_step(self, i_a: np.ndarray) -> np.ndarray:
        """The fast branch's period-mean response d to the kinetic excess, and its state one step on."""
        w = kinetic_excess(i_a, self._ct_r1, self.ct_fraction, self.vt_v)
        p, g = self._aux_pole[:, 0], self._aux_state_out[:, 0]
        d = self._ct_state * g + w * (1.0 - g)
        self._ct_state = p * self._ct_state + (1.0 - p) * w
        return d

    def rest(self, gap_s, cells):
        """As :meth:`LifIvEstimator.rest`; the fast branch's response to the kinetic excess relaxes too."""
        super().rest(gap_s, cells)
        decay = self._aux_pole[:, 0] ** (gap_s / self.dt_s)
        self._ct_state = np.where(cells, self._ct_state * decay, self._ct_state)

    def _regress(self, i, v, ok):
        if self._aux_age >= self.config.iv_model_every:
            self._refresh_aux()  # (LifIvEstimator._regress then finds it fresh)
        d = self._ct_step(np.where(np.isfinite(i), i, 0.0))
        return super()._regress(i, v - d, ok)

    def param_dict(self) -> dict[str, np.ndarray]:
        out = super().param_dict()
        out.update(ct_vt_v=np.full(self.n_cells, self.vt_v), ct_fraction=np.full(self.n_cells, self.ct_fraction))
        return out

    def predict_static(self, current_a):
        """Steady-state overpotential for a constant current: (R0+R1+R2) i + w(i; R1) + c0."""
        return super().predict_static(current_a) + kinetic_excess(current_a, self.params.r1_ohm, self.ct_fraction,
                                                                  self.vt_v)

    def state_dict(self):
        s = super().state_dict()
        s["ct_state"] = self._ct_state.copy()
        return s

    def load_state_dict(self, s):
        super().load_state_dict(s)
        state = np.asarray(s["ct_state"], dtype=float)
        if state.shape != self._ct_state.shape:
            raise ValueError("charge-transfer state does not match the number of cells")
        self._ct_state = state.copy()
