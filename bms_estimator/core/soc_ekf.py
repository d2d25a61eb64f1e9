"""Extended Kalman filter on SOC, a diffusion branch, the capacity and the overpotential's gain, driven by identified parameters.

The field's common answer to "online parameters plus SOC" is Plett's EKF on an
equivalent-circuit model with the parameters from an online identifier (RLS +
EKF).  This one adds what the measured drive cycles showed the 2-RC model
lacks: under a sustained current the cells build a slow (diffusion)
overpotential with a time constant of 10^3 s, beyond the identified slow branch
(tau2 <= 500 s), 30-60 mV at 1C on the LG HG2.  Left out, it reads as an SOC
error and the filter drags the SOC down through every long discharge.  It is a
third RC branch with a fixed time constant ``tau_d`` whose resistance ``r_d`` the
filter learns itself (a joint EKF): at a start from rest ``v_d = 0`` is known,
so the first minutes of current teach ``r_d`` rather than move the SOC.
The counting capacity is a state too (``dq`` relative to the capacity in use),
learnt from the same residual: a capacity error makes the SOC drift with the
charge, which no RC branch explains over the whole discharge.

State and model per cell, current ``i`` positive = charge, period ``Ts``::

    x = [z, v_d, r_d, dq, g]               (SOC, diffusion voltage and resistance, relative
                                            capacity error: the capacity is Q (1 + dq), relative
                                            error of the predicted overpotential)

    z[k+1]   = z[k] + i[k] Ts / (3600 Q (1 + dq))
    v_d[k+1] = ad v_d[k] + r_d[k] (1 - ad) i[k],   ad = exp(-Ts / tau_d)
    r_d[k+1] = r_d[k],   dq[k+1] = dq[k],   g[k+1] = g[k]     (random walks)

    vj[k+1]  = aj vj[k] + Rj (1 - aj) i[k],        aj = exp(-Ts / tau_j)     (R1, tau1, R2, tau2 identified; R2 floored, below)

    v[k]     = OCV(z[k], T) + h[k] H(z[k], T) + (1 + g[k]) eta[k] + v_d[k] + e[k],
    eta[k]   = R0 i[k] + v1[k] + v2[k]          (the identified model's overpotential)

``h`` is the one-state hysteresis (known from the current, not a state here) and
``H`` the table's half gap.  The two identified RC voltages follow the identified
model and are not filter states: the identifier has already fitted them, and
left free they would soak up errors that belong to the SOC (a 6-state filter
with them was measured no better and costs twice as much).  Linearised::

    F = I except F[1,1] = ad, F[1,2] = (1 - ad) i, F[0,3] = -i Ts / (3600 Q)
    C = [dOCV/dz, 1, 0, 0, eta]

Why ``g``.  The identified (or, before the identifier has a model, the prior)
overpotential is wrong by a fraction that persists for minutes to hours: a prior
resistance 1.5-2x low on a cold cell, a slow branch the identifier traded against
its c0.  Treated only as noise, that error is read again at every sample as SOC.
As a state the filter explains a shortfall that scales with the load by ``g`` and
moves the SOC only by what the load does not explain: the voltage at low current,
and the OCV curve's shape.  On LG 0 degC la92 from a correct start ``g`` rises to
+0.6 in 5 min and +0.87 in 20 on the prior, and the SOC error at 20 min is -2.1 %
against -2.9 % without it (README, SOC matrix: 60 to 63 of 72 runs within 2 %).  ``g`` starts with sigma ``overpotential_gain_sigma_prior`` and
restarts at 0 with sigma ``overpotential_gain_sigma`` when the identifier first has a
model of the cell (the prediction it corrected is then gone); ``1 + g`` is kept at
0.2 or more (the overpotential keeps its sign).

After each update the capacity takes in ``dq`` (``Q <- Q (1 + dq)``, ``dq <- 0``).
While the SOC is uncertain apart from the capacity, and in the steep ends of the OCV
curve (slope above ``capacity_learn_max_slope_v``), the row of ``K`` for ``dq`` is
zero: an SOC error being corrected, or the table's own error near empty, would
otherwise read as a capacity error.  The Joseph form keeps ``P`` right for that
suboptimal gain.  "Apart from the capacity" is the SOC's sigma given ``dq``::

    sigma_z|q = sqrt(P_zz - P_zq^2 / P_qq)   held while above capacity_learn_max_soc_sigma

A capacity error moves the count by ``dq`` times the charge counted, so over a long
discharge the capacity's share of ``P_zz`` grows until the SOC's whole sigma stays
above the gate, and a gate on it would hold the capacity exactly where learning it
matters (on Panasonic hwfet_a from a correct start the capacity stayed at the
table's 3.00 Ah against the reference's 2.89; now 2.93).  What is left once that
share is taken out is the start error still being corrected.  On the SOC matrix a tie in runs within 2 %
(72 / 108 / 81 of 72 / 124 / 90 as before) with the capacity nearer ``Q_ref`` (mean
error 1.65 to 1.44 %), and on cells whose capacity is not their tables' (README, "A
cell that is not the one its tables were measured on") 339 against 337 of 360, the
capacity's mean error 1.8-2.5 % down to 1.4-1.9 %.

    predict   x- = f(x, i),           P- = F P F' + Qn
    update    S = C P- C' + Rv,       K = P- C' / S,
              x = x- + K (v - v_hat), P = (I - K C) P- (I - K C)' + K Rv K'   (Joseph form)

Noise, stated in the cell's terms rather than tuned per file:

* ``Qn[z]`` = (``current_sigma_c`` Ts / 3600)^2 + ``drift_sigma_per_h``^2 Ts / 3600: a
  current-sensor noise (as a C-rate, so it fits any cell size) and a random walk for what
  the count cannot see.  The capacity's uncertainty reaches the SOC through ``dq``
  (``F[0,3]``, its variance starting at ``capacity_sigma``^2), not as noise; ``Qn[v_d]`` = (``rc_sigma_v``)^2
  Ts / tau_d (the diffusion voltage follows its resistance and the current; free to
  wander, it would soak up an SOC error); ``Qn[r_d]`` = (``diffusion_r_drift_ohm_ah`` / Q)^2 Ts / 3600;
  ``Qn[dq]`` = ``capacity_drift_per_h``^2 Ts / 3600 (ageing and temperature).
* ``dq`` starts at 0 with sigma ``capacity_sigma``; ``Qn[g]`` = ``overpotential_gain_drift_per_h``^2 Ts / 3600.
* ``r_d`` starts at its prior mean ``diffusion_r_prior_ohm_ah / Q`` times the Arrhenius
  factor of the cell's start temperature, ``exp(B (1/T - 1/T_ref))`` (the caller's; B
  ``diffusion_r_activation_k``, T_ref the tables' reference temperature, 25 degC), with
  sigma ``diffusion_r_sigma_ohm_ah / Q`` (resistances per C-rate, so the same numbers
  fit any cell size); ``v_d`` starts at 0 with sigma ``diffusion_v_sigma_v`` (the cell
  may not be at rest).
* ``Rv`` = (``voltage_sigma_v``^2 + (rho |R0 i + v1 + v2|)^2 + (``ocv_table_sigma_soc`` dOCV/dz)^2)
  ``correlation_s / Ts`` + (``(1 - |h|) H``)^2.  The table term: a C/20 OCV table places the curve to about a
  percent of SOC, so where the curve is steep (near empty) a reading is worth that percent,
  not the few tenths its slope alone would give.  Without it, on LG udds at 25 degC, the
  filter's sigma fell to 0.5 % near empty while its error was 3.3 %; with it 0.7-0.9 % at
  3.0 % (still over-confident there: near empty the model's overpotential falls 50-100 mV
  short at the true SOC).  The model's voltage error is not white: it stays for a
  minute or more, so one sample carries only ``Ts / correlation_s`` of an
  independent reading's information.  It grows with the load: the predicted
  overpotential is uncertain by a fraction rho of itself, ``overpotential_sigma_prior``
  while the identifier still runs on its prior (whose resistance is 1.5-2x low on
  a cold cell) and ``overpotential_sigma`` once it has identified the cell.  So the
  filter reads the SOC mostly where the OCV shows through: at low current and
  after the RC voltages have decayed.  Inside a hysteresis transition (``|h| < 1``)
  the branch is uncertain by up to ``H``, so the filter trusts the voltage less there.

Why a prior mean above 0.  Under a steady mean current ``r_d`` and an SOC offset are
the same signal: only the OCV curve's shape over a long discharge separates them, so
``r_d`` stays near where it starts (from 0 it learnt 0.000-0.026 ohm Ah on the
measured drive cycles, where the cells show 30-60 mV of slow overpotential at 1C).
Started at 0, every such cell's slow overpotential was read as a low SOC; started at
the cells' own order of magnitude (0.04 ohm Ah: 40 mV at 1C at 25 degC), and larger in
the cold as every resistance is, the SOC matrix went from 63 to 70 of 72 runs within
2 % (README, SOC matrix).

Why a floor on the slow branch.  Under a steady mean current the identifier's
slow branch and its c0 are nearly the same regressor, and the equation-error fit
may put the slow overpotential into c0: on LG 0 degC us06 its R2 falls to 0-7
mOhm while c0 takes -100 to -244 mV.  The filter does not use c0 (it would read
the SOC error twice), so with such an R2 it predicts too little overpotential and
reads the rest as a low SOC (-3 % through the drive).  The caller therefore runs
the filter on a slow branch no smaller than ``slow_branch_floor`` times the
identifier's own prior at the cell temperature (R2 on the prior's Arrhenius line,
with the prior's tau2 where the floor applies): the identifier may say the cell's
slow branch is larger than the prior's, never that it is smaller.  What a cell
really has less of, ``g`` takes off (``1 + g`` down to 0.2).  The published R2 is
the identifier's, unfloored.  On the SOC matrix: 70 to 72 of 72 runs within 2 %,
the later starts 104 to 108 of 124 (README, SOC matrix; the grid and what it
costs: docs/soc_experiments.md).

The 1-sigma SOC uncertainty is ``sqrt(P[0, 0])`` (:attr:`soc_sigma`).
Everything is vectorised over cells: ``P`` is ``(N, 5, 5)``, the update is a
rank-1 correction (one scalar measurement per cell), with no matrix inverse.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated

import numpy as np
from annotated_types import Ge, Gt

from .arrhenius import RESISTANCE_ACTIVATION_K, arrhenius_factor
from .bounds import check_bounds
from .cells import all_cells, any_cell, clip

__all__ = ["SocEkfConfig", "SocEkf"]

_N = 5  # z, v_d, r_d, dq, g
_TINY_VARIANCE = 1e-30  # a capacity variance at 0 (never, after predict's noise) divides by this instead

#: A rest longer than this counts as this long [s]; no rest grows the SOC's variance past a uniform SOC's
#: over [0, 1] (:meth:`SocEkf.rest`)
REST_GAP_MAX_S = 1e9
SOC_VARIANCE_MAX = 1.0 / 12.0


@dataclass(frozen=True)
class SocEkfConfig:
    """Noise model of the SOC EKF (module docstring); the defaults serve both cells in ../shared/data."""

    initial_soc_sigma: Annotated[float, Gt(0)] = 0.10  # 1-sigma of a start SOC that is given, not measured
    ocv_start_soc_sigma: Annotated[float, Gt(0)] = 0.03  # 1-sigma of a start SOC read from the OCV at rest
    capacity_sigma: Annotated[float, Gt(0)] = 0.05  # relative uncertainty of the counting capacity at a start
    capacity_drift_per_h: Annotated[float, Ge(0)] = 0.002  # its random walk per sqrt(hour)
    # the capacity learns only while the SOC is this sure apart from the capacity's own share
    # (sigma of z given dq): before, a start error still being corrected would read as a
    # capacity error (a Schmidt-style gain: the row of K is zeroed)
    capacity_learn_max_soc_sigma: Annotated[float, Gt(0)] = 0.02
    # nor in the steep ends of the OCV curve (slope above this, V per unit SOC: below about 10 %
    # SOC on both cells), where the table's own error (C/20 polarisation, a 50-100 mV hysteresis
    # gap) is largest and a capacity learnt there pulled the count off over the last few percent
    capacity_learn_max_slope_v: Annotated[float, Gt(0)] = 1.5
    drift_sigma_per_h: Annotated[float, Ge(0)] = 0.003  # SOC random walk the count cannot see, per sqrt(hour)
    current_sigma_c: Annotated[float, Gt(0)] = 0.01  # current-sensor noise as a C-rate (0.03 A on a 3 Ah cell)
    rc_sigma_v: Annotated[float, Gt(0)] = 0.001  # process noise of the diffusion voltage per sample, times sqrt(Ts / tau_d)
    voltage_sigma_v: Annotated[float, Gt(0)] = 0.015  # model voltage error at no load (OCV table, slow dynamics, ...)
    # the OCV table's own error as an SOC: a C/20 table places the curve to about a percent of SOC,
    # so in the steep ends a voltage reading says less about the SOC than the slope alone implies
    ocv_table_sigma_soc: Annotated[float, Ge(0)] = 0.01
    correlation_s: Annotated[float, Gt(0)] = 300.0  # how long that error stays correlated
    # relative uncertainty of the predicted overpotential (R0 i + v1 + v2): before the identifier
    # has a model of its own (the prior's resistance is 1.5-2x low on a cell at 0 degC) and after
    overpotential_sigma_prior: Annotated[float, Ge(0)] = 1.0
    overpotential_sigma: Annotated[float, Ge(0)] = 0.4
    diffusion_tau_s: Annotated[float, Gt(0)] = 1200.0  # time constant of the diffusion branch
    # prior mean of its resistance at the reference temperature, ohm * Ah (per C-rate): the slow
    # overpotential the cells have, 30-60 mV at 1C on the LG HG2 (module docstring)
    diffusion_r_prior_ohm_ah: Annotated[float, Ge(0)] = 0.04
    # its Arrhenius temperature B = E_a / R_gas, kelvin: the prior mean at the start temperature
    # (0: the same at every temperature)
    diffusion_r_activation_k: Annotated[float, Ge(0)] = RESISTANCE_ACTIVATION_K
    diffusion_r_sigma_ohm_ah: Annotated[float, Gt(0)] = 0.05  # prior sigma of its resistance, ohm * Ah (per C-rate)
    diffusion_r_drift_ohm_ah: Annotated[float, Ge(0)] = 0.01  # its random walk per sqrt(hour), ohm * Ah
    diffusion_v_sigma_v: Annotated[float, Gt(0)] = 0.005  # sigma of its voltage at a start (a larger one soaks up a start error)
    # the relative error g of the predicted overpotential as a state (module docstring): its
    # sigma on the prior and once identified (the same fractions as rho above: one states how far
    # the prediction is off for good, the other how much it scatters), and its random walk
    overpotential_gain_sigma_prior: Annotated[float, Ge(0)] = 1.0
    overpotential_gain_sigma: Annotated[float, Ge(0)] = 0.4
    overpotential_gain_drift_per_h: Annotated[float, Ge(0)] = 0.2
    # the identified slow branch the filter runs is at least this share of the identifier's prior's
    # at the cell temperature (R2 on the prior's Arrhenius line, with the prior's tau2 where it
    # applies; module docstring, "Why a floor on the slow branch"); 0: the identified branch as it is
    slow_branch_floor: Annotated[float, Ge(0)] = 1.0
    max_soc_step: Annotated[float, Gt(0)] = 0.01  # at most this SOC correction per sample (a bad sample cannot jump it)

    def __post_init__(self) -> None:
        check_bounds(self)


class SocEkf:
    """The filter's state and covariance for N cells; the SOC itself is owned by the caller.

    The caller (:class:`~bms_estimator.core.soc.SocEstimator`) counts the SOC and
    passes the counted step in; :meth:`predict` moves the other states and the
    covariance, :meth:`correct` returns the SOC correction and updates the rest.
    """

    def __init__(self, n_cells: int, dt_s: float, capacity_ah: np.ndarray, config: SocEkfConfig = SocEkfConfig()):
        self.n_cells = int(n_cells)
        self.dt_s = float(dt_s)
        self.config = config
        self.q_ref_ah = np.broadcast_to(np.asarray(capacity_ah, dtype=float), (self.n_cells,)).copy()
        self.x = np.zeros((self.n_cells, _N))  # x[:, 0] unused: the caller owns the SOC
        self.v_rc = np.zeros((self.n_cells, 2))  # the identified RC pairs' voltages
        # the covariance is stored element-major, (5, 5, N): every element is a contiguous vector
        # over the cells, so the row and column operations below run at memory speed
        self._pt = np.zeros((_N, _N, self.n_cells))
        self._pt[0, 0] = config.initial_soc_sigma**2
        self._pt[1, 1] = config.diffusion_v_sigma_v**2
        self._pt[2, 2] = (config.diffusion_r_sigma_ohm_ah / self.q_ref_ah) ** 2
        self._pt[3, 3] = config.capacity_sigma**2
        self.x[:, 2] = config.diffusion_r_prior_ohm_ah / self.q_ref_ah  # at the reference temperature
        self._pt[4, 4] = config.overpotential_gain_sigma_prior**2
        # per-period constants of predict (config and period are fixed)
        self._a_d = np.exp(-self.dt_s / config.diffusion_tau_s)  # the diffusion branch's decay
        h_frac = self.dt_s / 3600.0
        self._h_frac = h_frac
        self._q00 = (config.current_sigma_c * h_frac) ** 2 + config.drift_sigma_per_h**2 * h_frac
        self._q11 = config.rc_sigma_v**2 * (self.dt_s / config.diffusion_tau_s)  # driven by r_d, not free
        self._q33 = config.capacity_drift_per_h**2 * h_frac
        self._q44 = config.overpotential_gain_drift_per_h**2 * h_frac
        self._r_scale = max(config.correlation_s / self.dt_s, 1.0)  # correct's

    @property
    def p(self) -> np.ndarray:
        """The covariance, ``(N, 5, 5)`` (a view of the element-major store)."""
        return np.moveaxis(self._pt, 2, 0)

    @p.setter
    def p(self, value: np.ndarray) -> None:
        self._pt = np.ascontiguousarray(np.moveaxis(np.asarray(value, dtype=float), 0, 2))

    @property
    def capacity_variance(self) -> np.ndarray:
        """The relative capacity's variance, ``p[:, 3, 3]`` (a view, without the (N, 5, 5) view's moveaxis)."""
        return self._pt[3, 3]

    @property
    def soc_sigma(self) -> np.ndarray:
        return np.sqrt(np.maximum(self._pt[0, 0], 0.0))

    @property
    def v_diffusion(self) -> np.ndarray:
        """The diffusion branch's voltage."""
        return self.x[:, 1]

    @property
    def r_diffusion_ohm(self) -> np.ndarray:
        return self.x[:, 2]

    @property
    def overpotential_gain(self) -> np.ndarray:
        """``g``: the predicted overpotential is ``(1 + g)`` times the identified model's."""
        return self.x[:, 4]

    def restart_gain(self, cells: np.ndarray) -> None:
        """``g`` back to 0 with sigma ``overpotential_gain_sigma`` (the identifier has a new model), cross terms dropped."""
        sel = np.asarray(cells, dtype=bool)
        self._pt[4, :, sel] = 0.0
        self._pt[:, 4, sel] = 0.0
        self._pt[4, 4, sel] = self.config.overpotential_gain_sigma**2
        self.x[sel, 4] = 0.0

    def take_diffusion_prior_at(self, temperature_c: np.ndarray, previous_c: np.ndarray, reference_c: float,
                                cells: np.ndarray) -> None:
        """``r_d`` of ``cells`` brought from the Arrhenius factor at ``previous_c`` to the one at
        ``temperature_c`` (module docstring): from the prior mean, its prior at that temperature.

        A temperature that is not finite or out of range counts as the reference (factor 1).
        """
        k = self.config.diffusion_r_activation_k
        ratio = arrhenius_factor(temperature_c, reference_c, k) / arrhenius_factor(previous_c, reference_c, k)
        self.x[:, 2] = np.where(cells, self.x[:, 2] * ratio, self.x[:, 2])

    def set_soc_sigma(self, sigma: float | np.ndarray, cells: np.ndarray | None = None) -> None:
        """Restart the SOC variance (a new start SOC) of some cells; its cross terms dropped."""
        sel = np.ones(self.n_cells, dtype=bool) if cells is None else np.asarray(cells, dtype=bool)
        s2 = np.broadcast_to(np.asarray(sigma, dtype=float) ** 2, (self.n_cells,))
        self._pt[0, :, sel] = 0.0
        self._pt[:, 0, sel] = 0.0
        self._pt[0, 0, sel] = s2[sel]

    def grow_soc_variance(self, variance: np.ndarray, cells: np.ndarray) -> None:
        """Add ``variance`` to the SOC's (``P[0, 0]``) of ``cells``: an uncertainty the count took on
        that the model's noise does not hold (a period counted with a guessed current)."""
        self._pt[0, 0] = np.where(cells, self._pt[0, 0] + variance, self._pt[0, 0])

    def predict(self, current_a: np.ndarray, dz: np.ndarray, capacity_ah: np.ndarray,
                r_ohm: np.ndarray, tau_s: np.ndarray, live: np.ndarray) -> None:
        """One period of current ``current_a``: states forward, covariance grows (``live`` cells only).

        ``dz`` is the counted SOC step, ``r_ohm`` and ``tau_s`` the identified ``(N, 2)`` RC pairs.
        """
        cfg = self.config
        a = np.exp(-self.dt_s / np.maximum(tau_s, 1e-9))
        a_d = self._a_d
        v_rc = a * self.v_rc + r_ohm * (1.0 - a) * current_a[:, None]
        x = self.x.copy()
        x[:, 1] = a_d * self.x[:, 1] + self.x[:, 2] * (1.0 - a_d) * current_a
        # P- = F P F' with F the identity but for F[1,1] = ad, F[1,2] and F[0,3]: rows, then
        # columns, in place of two dense (N, 5, 5) products
        f12 = (1.0 - a_d) * current_a
        f03 = -dz
        every = all_cells(live)  # the usual case: in place, no (5, 5, N) select
        p = self._pt if every else self._pt.copy()
        for rows in (True, False):
            q = p if rows else p.swapaxes(0, 1)
            q[0] += f03 * q[3]
            q[1] *= a_d
            q[1] += f12 * q[2]
        p[0, 0] += self._q00
        p[1, 1] += self._q11
        p[2, 2] += (cfg.diffusion_r_drift_ohm_ah / capacity_ah) ** 2 * self._h_frac
        p[3, 3] += self._q33
        p[4, 4] += self._q44
        if every:
            self.x, self.v_rc = x, v_rc
        else:
            self.x = np.where(live[:, None], x, self.x)
            self._pt = np.where(live, p, self._pt)
            self.v_rc = np.where(live[:, None], v_rc, self.v_rc)

    def rest(self, gap_s: float, capacity_ah: np.ndarray, tau_s: np.ndarray, cells: np.ndarray) -> None:
        """``gap_s`` seconds at zero current without samples (the pack parked): :meth:`predict` with
        ``i = 0`` applied ``n = gap_s / Ts`` times, in closed form.

        At ``i = 0`` the RC and diffusion voltages relax, ``v_j <- exp(-gap / tau_j) v_j`` and
        ``v_d <- a_d^n v_d = exp(-gap / tau_d) v_d``; ``r_d``, ``dq`` and ``g`` stay.  ``F`` is
        then ``diag(1, a_d, 1, 1, 1)`` and the noise ``Qn`` diagonal (module docstring, with
        ``dz = 0``), so

            P_n = F^n P F^n' + sum_{k<n} F^k Qn F^k'
                = D P D + diag(n Qn[z], Qn[v_d] (1 - a_d^2n) / (1 - a_d^2), n Qn[r_d], n Qn[dq], n Qn[g]),
            D = diag(1, a_d^n, 1, 1, 1):

        the SOC's variance grows by the filter's own random walk (``drift_sigma_per_h^2`` per
        hour, plus the current sensor's per-period term ``n`` times), the diffusion voltage's
        settles at its stationary value.  ``n`` need not be whole (the formula is the same).
        ``tau_s`` is the identified ``(N, 2)`` pairs'; only ``cells`` change.

        The SOC's variance is capped at a uniform SOC's over [0, 1] (``SOC_VARIANCE_MAX`` = 1/12,
        sigma 29 %: knowing nothing), its row and column scaled with it; the random walk reaches it
        after about a year.  A gap longer than ``REST_GAP_MAX_S`` (1e9 s, 32 years) counts as that
        long: a gap of 1e300 s no longer overflows the covariance.
        """
        gap_s = min(gap_s, REST_GAP_MAX_S)
        n = gap_s / self.dt_s
        a_dn = float(np.exp(-gap_s / self.config.diffusion_tau_s))
        a_rc = np.exp(-gap_s / np.maximum(tau_s, 1e-9))
        p = self._pt.copy()
        p[1] *= a_dn
        p[:, 1] *= a_dn
        a_d2 = self._a_d * self._a_d
        p[0, 0] += n * self._q00
        p[1, 1] += self._q11 * (1.0 - a_dn * a_dn) / (1.0 - a_d2)
        p[2, 2] += n * (self.config.diffusion_r_drift_ohm_ah / capacity_ah) ** 2 * self._h_frac
        p[3, 3] += n * self._q33
        p[4, 4] += n * self._q44
        # the SOC never less known than knowing nothing: its variance capped at a uniform SOC's, its row
        # and column scaled with it (P stays positive semi-definite)
        if np.any(p[0, 0] > SOC_VARIANCE_MAX):
            s = np.sqrt(SOC_VARIANCE_MAX / np.maximum(p[0, 0], SOC_VARIANCE_MAX))
            p[0] *= s
            p[:, 0] *= s
        self._pt = np.where(cells, p, self._pt)
        self.x[:, 1] = np.where(cells, a_dn * self.x[:, 1], self.x[:, 1])
        self.v_rc = np.where(cells[:, None], a_rc * self.v_rc, self.v_rc)

    def read_at_rest(self, innovation_v: np.ndarray, slope_v: np.ndarray, r_v: np.ndarray,
                     cells: np.ndarray, gate_sigma: float) -> tuple[np.ndarray, np.ndarray]:
        """One voltage of a relaxed cell as an independent OCV reading: a Kalman update with
        ``C = [dOCV/dz, 1, 0, 0, 0]`` (no load: ``g`` has nothing to scale), variance ``r_v``,
        neither the correlation scaling nor the per-sample step cap of :meth:`correct` (one
        reading, not one of a correlated stream)::

            S = C P C' + r_v,  K = P C' / S,  x <- x + K e,  P <- P - P C' C P / S

        A reading more than ``gate_sigma`` of its sigmas from the prediction (``|e| > gate sqrt(S)``)
        contradicts the model (a charge while parked): it is not fused, and returned as such.
        Returns the SOC correction of the fused ``cells`` (0 elsewhere) and the contradicted cells.
        """
        p = self._pt
        pc = p[:, 0] * slope_v + p[:, 1]  # (5, N)
        s = pc[0] * slope_v + pc[1] + r_v
        contradicted = cells & (np.abs(innovation_v) > gate_sigma * np.sqrt(s))
        fuse = cells & ~contradicted
        k = pc / s
        dx = (k * np.where(fuse, innovation_v, 0.0)).T
        self._pt = np.where(fuse, p - pc[:, None, :] * k[None, :, :], p)
        x = self.x + dx
        x[:, 2] = np.maximum(x[:, 2], 0.0)  # a resistance is never negative
        self.x = np.where(fuse[:, None], x, self.x)
        return dx[:, 0], contradicted

    def correct(self, innovation_v: np.ndarray, slope_v: np.ndarray, hyst_uncertain_v: np.ndarray,
                use: np.ndarray, model_uncertain_v: np.ndarray | float = 0.0,
                overpotential_v: np.ndarray | float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """Measurement update; returns the SOC correction and the relative capacity correction per cell.

        ``innovation_v`` = measured - predicted voltage (with ``(1 + g)`` times the identified
        overpotential, :attr:`v_rc` and :attr:`v_diffusion`), ``slope_v`` = dOCV/dz,
        ``hyst_uncertain_v`` = (1 - |h|) H, ``model_uncertain_v`` = rho |eta|,
        ``overpotential_v`` = eta = R0 i + v1 + v2 (``g``'s column of C).
        """
        cfg = self.config
        p = self._pt
        # P C' with C = [slope, 1, 0, 0, eta]: columns, not a product; (5, N)
        pc = p[:, 0] * slope_v + p[:, 1] + p[:, 4] * overpotential_v
        table_v = cfg.ocv_table_sigma_soc * slope_v
        r_v = ((cfg.voltage_sigma_v**2 + np.square(model_uncertain_v) + table_v * table_v)
               * self._r_scale + hyst_uncertain_v**2)
        s = pc[0] * slope_v + pc[1] + pc[4] * overpotential_v + r_v
        k = pc / s
        # the SOC's uncertainty apart from the capacity's share (module docstring): P_zz - P_zq^2 / P_qq
        var_z = p[0, 0] - p[0, 3] * p[0, 3] / np.maximum(p[3, 3], _TINY_VARIANCE)
        held = (var_z > cfg.capacity_learn_max_soc_sigma**2) | (slope_v > cfg.capacity_learn_max_slope_v)
        any_held = any_cell(held)  # (none, the usual sample: the selects below would leave every value as it is)
        if any_held:
            k[3] = np.where(held, 0.0, k[3])
        every = all_cells(use)  # the usual sample: the selects by use would copy their first argument
        e = innovation_v if every else np.where(use, innovation_v, 0.0)
        dx = (k * e).T
        dz = clip(dx[:, 0], -cfg.max_soc_step, cfg.max_soc_step)  # np.clip's ufunc, without its wrappers
        # Joseph form, (I - K C) P (I - K C)' + K R K', for K = pc / S - d e3 (d = pc3 / S where the
        # capacity row is held, else 0) expands to  P - pc pc' / S + S d^2 e3 e3':  one outer product
        pp = np.multiply(pc[:, None, :], k[None, :, :], out=np.empty_like(p))  # pc pc' / S (k = pc / S here)
        pp[:, 3] = pc * (pc[3] / s)  # the held capacity row of k is not pc / S
        p_new = np.subtract(p, pp, out=pp)
        if any_held:  # (adding 0.0 would change nothing either: after predict the variance is never -0.0)
            p_new[3, 3] += np.where(held, pc[3] ** 2 / s, 0.0)
        self._pt = p_new if every else np.where(use, p_new, p)
        x = self.x + dx
        x[:, 2] = np.maximum(x[:, 2], 0.0)  # a resistance is never negative
        x[:, 4] = np.maximum(x[:, 4], -0.8)  # nor does the overpotential change its sign
        dq = clip(x[:, 3], -0.01, 0.01)  # the caller's capacity takes it in
        x[:, 3] = 0.0
        if every:
            self.x = x
            return dz, dq
        self.x = np.where(use[:, None], x, self.x)
        return np.where(use, dz, 0.0), np.where(use, dq, 0.0)

    def state_dict(self) -> dict[str, np.ndarray]:
        return {"x": self.x.copy(), "p": self.p.copy(), "v_rc": self.v_rc.copy()}

    def load_state_dict(self, s: dict[str, np.ndarray]) -> None:
        """A saved state; one saved before ``g`` existed (4 states) takes ``g = 0`` with sigma ``overpotential_gain_sigma``."""
        x = np.asarray(s.get("x"), dtype=float)
        p = np.asarray(s.get("p"), dtype=float)
        n = self.n_cells
        if x.shape == (n, _N - 1) and p.shape == (n, _N - 1, _N - 1):
            x = np.concatenate([x, np.zeros((n, 1))], axis=1)
            p = np.pad(p, ((0, 0), (0, 1), (0, 1)))
            p[:, 4, 4] = self.config.overpotential_gain_sigma**2
        if p.shape != self.p.shape or x.shape != self.x.shape:
            raise ValueError(f"EKF state has shape {np.shape(s.get('p'))}, expected {self.p.shape}")
        if not (np.all(np.isfinite(x)) and np.all(np.isfinite(p))):
            raise ValueError("EKF state holds non-finite values")
        self.x = x.copy()
        self.p = p
        if "v_rc" in s:
            self.v_rc = np.asarray(s["v_rc"], dtype=float).copy()
