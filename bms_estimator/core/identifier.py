"""Online 2-RC identifiers: continuous-time LIF (the paper's method) and the DT ARX baseline.

Both share the same machinery (:class:`~bms_estimator.core.rls.WeightedRls`,
vectorised over N cells) and the same *admissibility guard*: after each update
theta is mapped to (R0, R1, C1, R2, C2, c0); a cell whose new theta is not
physical (negative R or C, complex or repeated poles, a time constant outside
``[tau_min_s, tau_max_s]``) has its estimate itself reset to its last admissible
theta - not just its output - and the rejection is counted.  Resetting the
estimate is what stops the slow pole from running away to 1e3..1e6 s and c0 to
volts during weakly exciting stretches: a bound on the output alone would let
the hidden estimate drift on.  A cell rejected sample after sample is stuck
against the admissible set (the slow pole absorbing a drifting OCV error, say):
after ``restart_after_rejections`` in a row its identification restarts from a
fresh block.  Until a cell's block-LS initialisation is done the cell reports a
prior; a block whose least-squares theta is not physical (too short to place the
slow pole) grows sample by sample up to ``init_max_samples``, after which the
cell starts from the prior.  The prior's resistances are stated at 25 degC and
brought to each cell's start temperature, when the caller knows it, on a cell not
yet identified (:meth:`Identifier.take_prior_at`), by the resistances' Arrhenius line
``R(T) = R(25 degC) exp(B (1/T - 1/T_ref))`` (``prior_activation_k``, the project's
B = 2500 K; x2.2 at 0 degC, x4.4 at -20 degC), the time constants kept.  A cold
cell whose block start does not turn physical (on six of the seven measured LG
drive cycles at 0 and -10 degC, for the first 1240 s) then runs on resistances of
its own order, not a warm cell's.

Currents are regressed in C-rate (``i / I_ref``, ``I_ref`` = capacity in A for
1C) and the LIF columns are time-scaled by the window, so the same tuning
serves a 2 Ah cell and a 200 Ah cell, and any window length.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace
from typing import Annotated, Literal

import numpy as np
from annotated_types import Ge, Gt, Interval

from .arrhenius import RESISTANCE_ACTIVATION_K, arrhenius_factor
from .bounds import check_bounds
from .cells import all_cells, any_cell, cell_vector
from .lif import LifHistory
from .params import (
    PhysicalParams,
    ct_c0_from_theta,
    ct_physical_from_rows,
    ct_theta_from_physical,
    dt_physical_from_theta,
    dt_theta_from_physical,
)
from .rls import RlsConfig, WeightedRls

#: identification methods: continuous time with RLS (the paper's), with recursive IV, with recursive IV and a
#: kinetic (Butler-Volmer) term, with recursive IV and a charge-transfer (Butler-Volmer) fast branch, discrete-time ARX
METHODS = ("lif", "lif-iv", "lif-iv-bv", "lif-iv-ct", "arx")

__all__ = ["METHODS", "IdentifierConfig", "Identifier", "LifEstimator", "ArxEstimator"]


@dataclass(frozen=True)
class IdentifierConfig:
    """Tuning of the online identifiers; the defaults serve both cells in ../shared/data.

    Resistances of the prior are given times the capacity (ohm * Ah), i.e. per
    C-rate, so that they fit any cell size.
    """

    method: Literal["lif", "lif-iv", "lif-iv-bv", "lif-iv-ct", "arx"] = "lif"  # "lif" (continuous time, RLS), "lif-iv" (continuous time, recursive IV), "lif-iv-bv" (lif-iv plus a kinetic term, core/lif_bv.py), "lif-iv-ct" (lif-iv with a charge-transfer fast branch, core/lif_ct.py) or "arx" (DT baseline)
    window: Annotated[int, Ge(1)] = 20  # LIF window L in samples
    forgetting: Annotated[float, Interval(ge=0.9, le=1.0)] = 0.9995  # RLS forgetting factor per sample (memory ~ 1/(1-lambda) samples)
    error_on_v: Annotated[float, Ge(0)] = 0.0  # turn adaptation on above this windowed RMS error (0 = always on)
    error_off_v: Annotated[float, Ge(0)] = 0.0  # turn it off below this one
    error_window: Annotated[int, Ge(1)] = 30  # samples in the windowed error
    trace_max: Annotated[float, Gt(0)] = 1e3  # covariance trace limit (scaled regressors)
    init_samples: Annotated[int, Ge(1)] = 120  # shortest block-LS initialisation window, samples
    # The block grows while its LS theta is not physical (a block too short to see the slow
    # pole); past this many samples (or init_samples, if longer) the cell starts from the prior.
    init_max_samples: Annotated[int, Ge(1)] = 1200
    # A cell whose estimate the guard has rejected this many samples in a row is stuck
    # against the admissible set (the slow pole absorbing a drifting OCV error, say): its
    # identification restarts from a fresh block (0 = never).
    restart_after_rejections: Annotated[int, Ge(0)] = 300
    tau_min_s: Annotated[float, Gt(0)] = 1.0  # admissible fast time constant, lower bound
    tau_max_s: Annotated[float, Gt(0)] = 500.0  # admissible slow time constant, upper bound (the runaway guard)
    # Prior c0 = 0 as a pseudo-measurement each learning sample, weighted relative to one
    # data sample (0 = off, the paper's estimate).  For identification along a *given*
    # SOC path (fit, compare): c0 is then an OCV-model error, and the prior stops it
    # trading off against the slow branch.  Off in the SOC estimator, where c0 carries
    # the SOC error the compensation needs.
    c0_prior_weight: Annotated[float, Ge(0)] = 0.0
    # Stabilised forgetting (core/rls.py): forgetting toward the prior model below, which keeps in each
    # column this share of the information a full memory of data holds (0 = off, plain forgetting).
    # What stops c0 and the slow branch drifting together under a steady current
    stabilised_forgetting: Annotated[float, Ge(0)] = 0.0
    stabilised_every: Annotated[int, Ge(1)] = 30  # its step every this many learning samples
    c0_max_v: Annotated[float, Gt(0)] = 0.5  # admissible |c0|: an OCV bias beyond this is not an SOC error but a broken fit
    # lif-iv: the auxiliary model that makes the instruments takes the last admissible
    # parameters every this many samples
    iv_model_every: Annotated[int, Ge(1)] = 10
    # lif-iv-bv: the kinetic term's current scale i0 in C-rate, fixed (u = i0 asinh(i/i0) - i)
    bv_current_c: Annotated[float, Gt(0)] = 1.0
    # lif-iv-ct: the share of the fast branch's R1 that is charge transfer (fixed, not fitted) and the
    # temperature of its thermal voltage V_T = 2 R T / F
    ct_fraction: Annotated[float, Interval(gt=0.0, le=1.0)] = 1.0
    ct_temperature_c: Annotated[float, Interval(gt=-273.15, le=200.0)] = 25.0
    # the prior model (ohm * Ah, class docstring): what a cell reports until its block-LS start is
    # done, and where it starts if that start is not physical; its time constants are moved inside
    # [tau_min_s, tau_max_s] (and tau1 below tau2 / 2) where they are not
    prior_r0_ohm_ah: Annotated[float, Gt(0)] = 0.06
    prior_r1_ohm_ah: Annotated[float, Gt(0)] = 0.03
    prior_tau1_s: Annotated[float, Gt(0)] = 10.0
    prior_r2_ohm_ah: Annotated[float, Gt(0)] = 0.03
    prior_tau2_s: Annotated[float, Gt(0)] = 200.0
    # their Arrhenius temperature B = E_a / R_gas, kelvin: the prior's resistances at the cell's
    # temperature at its first sample (module docstring; 0: the same at every temperature)
    prior_activation_k: Annotated[float, Ge(0)] = RESISTANCE_ACTIVATION_K

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise ValueError(f"unknown identification method {self.method!r}: use {', '.join(map(repr, METHODS))}")
        check_bounds(self)
        if not self.tau_min_s < self.tau_max_s:
            raise ValueError(f"tau_min_s must be below tau_max_s, got {self.tau_min_s} and {self.tau_max_s}")
        if self.error_off_v > self.error_on_v:
            raise ValueError(f"error_off_v must not exceed error_on_v, got {self.error_off_v} > {self.error_on_v}")

    def rls(self) -> RlsConfig:
        return RlsConfig(
            forgetting=self.forgetting,
            error_on=self.error_on_v,
            error_off=self.error_off_v,
            error_window=self.error_window,
            trace_max=self.trace_max,
            init_samples=self.init_samples,
            prior_share=self.stabilised_forgetting,
            prior_every=self.stabilised_every,
        )

    def with_(self, **changes) -> "IdentifierConfig":
        return replace(self, **changes)

    def as_dict(self) -> dict:
        return asdict(self)


class Identifier:
    """Common part of the CT and DT identifiers (N cells, one sample per call)."""

    n_params = 6
    rls_class: type[WeightedRls] = WeightedRls  # the recursive estimator of theta

    def __init__(self, n_cells: int, dt_s: float, capacity_ah: float | np.ndarray, config: IdentifierConfig):
        if n_cells < 1:
            raise ValueError(f"n_cells must be >= 1, got {n_cells}")
        if dt_s <= 0:
            raise ValueError(f"dt_s must be positive, got {dt_s}")
        self.n_cells = int(n_cells)
        self.dt_s = float(dt_s)
        self.config = config
        self.i_ref_a = np.broadcast_to(np.asarray(capacity_ah, dtype=float), (self.n_cells,)).copy()
        if np.any(self.i_ref_a <= 0):
            raise ValueError("capacity_ah must be positive")
        self.rls = self.rls_class(self.n_cells, self.n_params, config.rls())
        self._init_scales()
        self._set_prior(np.ones(self.n_cells))
        self.identified = np.zeros(self.n_cells, dtype=bool)
        # cells whose first admissible model came in this sample (whoever used the prior's can restart)
        self.newly_identified = np.zeros(self.n_cells, dtype=bool)
        self.rejections = np.zeros(self.n_cells, dtype=np.int64)
        self.restarts = np.zeros(self.n_cells, dtype=np.int64)
        self._rejected_run = np.zeros(self.n_cells, dtype=np.int64)  # consecutive rejections
        self.updates = 0
        self.error = np.full(self.n_cells, np.nan)
        self.accepted = np.zeros(self.n_cells, dtype=bool)  # learnt an admissible theta this sample
        self.params: PhysicalParams = self._physical(self.theta_good)

    def _prior_at(self, factor: np.ndarray) -> np.ndarray:
        """The prior model's scaled theta with its resistances times ``factor`` (per cell)."""
        config = self.config
        q = self.i_ref_a
        tau1, tau2 = self._prior_tau_s()
        return self._theta_s_from_physical(
            config.prior_r0_ohm_ah / q * factor,
            config.prior_r1_ohm_ah / q * factor,
            np.full(self.n_cells, tau1),
            config.prior_r2_ohm_ah / q * factor,
            np.full(self.n_cells, tau2),
            np.zeros(self.n_cells),
        )

    def _prior_tau_s(self) -> tuple[float, float]:
        """The prior's time constants, moved inside the guard's bounds: the prior must itself pass
        the guard, whatever bounds the user set."""
        config = self.config
        tau2 = min(config.prior_tau2_s, 0.9 * config.tau_max_s)
        tau1 = min(max(config.prior_tau1_s, 1.1 * config.tau_min_s, 1.5 * self.dt_s), 0.5 * tau2)
        return tau1, tau2

    def prior_slow_branch(self, temperature_c: np.ndarray, reference_c: float) -> tuple[np.ndarray, np.ndarray]:
        """The prior's slow branch at ``temperature_c`` (per cell): ``(R2 [ohm], tau2 [s])``, the
        resistance on the prior's Arrhenius line (module docstring), the time constant kept."""
        factor = arrhenius_factor(temperature_c, reference_c, self.config.prior_activation_k)
        r2 = self.config.prior_r2_ohm_ah / self.i_ref_a * factor
        return r2, np.full(self.n_cells, self._prior_tau_s()[1])

    def _set_prior(self, factor: np.ndarray) -> None:
        """The prior model with its resistances times ``factor`` (per cell): where the block start pulls
        and where a cell starts (theta_ref, theta_good)."""
        self._prior_theta_s = self._prior_at(factor)
        self.rls.theta_ref = self._prior_theta_s.copy()  # unexcited directions of the block start
        self.theta_good = self._prior_theta_s.copy()  # last admissible scaled theta

    def take_prior_at(self, temperature_c: np.ndarray, reference_c: float, cells: np.ndarray) -> None:
        """The prior's resistances brought to ``temperature_c`` on ``cells`` (module docstring).

        Only a cell not yet identified takes it (one that is keeps its own model, restored or
        learnt); a temperature that is not finite or out of range gives the reference's prior.
        """
        sel = np.asarray(cells, dtype=bool) & ~self.identified
        if not any_cell(sel):
            return
        prior = self._prior_at(arrhenius_factor(temperature_c, reference_c, self.config.prior_activation_k))
        for theta_s in (self._prior_theta_s, self.rls.theta_ref, self.theta_good):
            theta_s[sel] = prior[sel]
        self.params = self._physical(self.theta_good).select(sel, self.params)

    # -- to be provided by subclasses -------------------------------------------
    def _init_scales(self) -> None:
        raise NotImplementedError

    def _theta_s_from_physical(self, r0, r1, tau1, r2, tau2, c0) -> np.ndarray:
        raise NotImplementedError

    def _physical(self, theta_s: np.ndarray) -> PhysicalParams:
        raise NotImplementedError

    def _regress(self, current_a: np.ndarray, v_o: np.ndarray,
                 ok: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Push a sample (``ok``: the cells whose sample is good); return (y, phi_s, ready mask)."""
        raise NotImplementedError

    def _shift_theta(self, theta_s: np.ndarray, dv: np.ndarray) -> None:
        raise NotImplementedError

    def _shift_history(self, dv: np.ndarray) -> None:
        raise NotImplementedError

    # -- public ---------------------------------------------------------------
    def update(self, current_a: np.ndarray, v_o: np.ndarray, valid: np.ndarray | None = None) -> None:
        """One sample for all cells.

        Args:
            current_a: cell current (N,) or scalar, positive = charge.
            v_o: overpotential v - OCV(soc) per cell (N,).
            valid: cells whose sample is good; the others are held (their
                regressor window is marked contaminated and they do not learn
                until it has been flushed).
        """
        i = cell_vector(current_a, self.n_cells)
        v = np.asarray(v_o, dtype=float)
        ok = np.isfinite(v) & np.isfinite(i)
        if valid is not None:
            ok &= np.asarray(valid, dtype=bool)
        y, phi, ready = self._regress(i, v, ok)
        learn = ready & np.isfinite(y) & np.logical_and.reduce(np.isfinite(phi), axis=1)
        was_init = self.rls.initialised.copy()
        every_init = all_cells(was_init)  # the usual sample: no cell starts now
        # (every cell learning, the usual sample: y itself, the values the select gives; read only)
        learn_all = all_cells(learn)
        self.error = self._learn(phi, y if learn_all else np.where(learn, y, 0.0), learn)
        if self.config.c0_prior_weight > 0:
            self._c0_prior(learn & was_init)
        theta = self.rls.theta
        new = None if every_init else self.rls.initialised & ~was_init  # (None: no cell new)
        params = self._physical(theta)
        admissible = params.admissible & (np.abs(params.c0_v) <= self.config.c0_max_v)
        params = PhysicalParams(*params._arrays(), admissible=admissible, dynamics_ok=params.dynamics_ok)
        good = admissible & self.rls.initialised
        bad_start = None if new is None else new & ~good
        if bad_start is not None and any_cell(bad_start):
            self._retry_start(bad_start, theta)
        rejected = self.rls.initialised & ~params.admissible
        if new is not None:
            rejected &= ~new
        accepted = good if learn_all else good & learn
        self._guard(rejected, accepted)
        self.accepted = accepted
        self._keep_admissible(good, theta, params)
        self.updates += 1

    def _retry_start(self, bad_start: np.ndarray, theta: np.ndarray) -> None:
        """A fresh block-LS start that is not physical: the block grows by a sample and is solved
        again; once it is ``init_max_samples`` long the cell starts from the prior (in ``theta``)."""
        longest = max(self.config.init_max_samples, self.config.init_samples)
        grow = bad_start & (self.rls.block_samples < longest)
        if any_cell(grow):
            self.rls.extend_block(grow)
        give_up = bad_start & ~grow
        theta[give_up] = self._prior_theta_s[give_up]

    def _guard(self, rejected: np.ndarray, accepted: np.ndarray) -> None:
        """The admissibility guard (module docstring): a rejected cell's estimate goes back to its
        last admissible theta; one rejected ``restart_after_rejections`` times in a row restarts."""
        if any_cell(rejected):
            self.rejections += rejected
            self.rls.reset_theta(rejected, self.theta_good)
            self._rejected_run = np.where(rejected, self._rejected_run + 1,
                                          np.where(accepted, 0, self._rejected_run))
        else:  # the usual sample: nothing rejected
            self._rejected_run = np.where(accepted, 0, self._rejected_run)
        n_stuck = self.config.restart_after_rejections
        if n_stuck > 0:
            stuck = self._rejected_run >= n_stuck
            if any_cell(stuck):
                self.rls.restart(stuck)
                self._rejected_run[stuck] = 0
                self.restarts += stuck

    def _keep_admissible(self, good: np.ndarray, theta: np.ndarray, params: PhysicalParams) -> None:
        """The ``good`` cells' theta and parameters become their last admissible ones (and the cells
        identified; :attr:`newly_identified` those identified for the first time)."""
        if all_cells(self.identified):  # the usual sample: nothing new
            if any_cell(self.newly_identified):
                self.newly_identified = np.zeros(self.n_cells, dtype=bool)
        else:
            self.newly_identified = good & ~self.identified
        if all_cells(good):  # every cell admissible (the usual sample): the selects below would copy
            self.theta_good = theta.copy()  # (theta is the RLS's own, updated in place)
            self.identified[:] = True
            self.params = params
        else:
            self.theta_good = np.where(good[:, None], theta, self.theta_good)
            self.identified |= good
            self.params = params.select(good, self.params) if any_cell(good) else self.params

    def _learn(self, phi: np.ndarray, y: np.ndarray, learn: np.ndarray) -> np.ndarray:
        """One step of the recursive estimator; returns its a-priori error."""
        return self.rls.update(phi, y, learn)

    def _c0_gain(self, theta_s: np.ndarray) -> np.ndarray:
        """g with c0 = theta_s[:, 5] / g (per cell); g > 0 where c0 is defined."""
        raise NotImplementedError

    def _c0_prior(self, cells: np.ndarray) -> None:
        """One pseudo-measurement ``c0 = 0`` (linearised at theta) for the selected cells."""
        g = self._c0_gain(self.rls.theta)
        ok = cells & (g > 0)
        if not any_cell(ok):
            return
        h = np.zeros((self.n_cells, self.n_params))
        h[:, 5] = np.sqrt(self.config.c0_prior_weight) / np.where(ok, g, 1.0)  # h' theta = sqrt(w) c0
        self.rls.pseudo_update(h, np.zeros(self.n_cells), ok)

    def rest(self, gap_s: float, cells: np.ndarray) -> None:
        """``gap_s`` seconds of the ``cells`` without samples (the pack parked, the bus silent).

        Their regressor window restarts: it is marked contaminated, as after a bad sample, so
        they learn again only once it holds ``2L + 1`` samples after the gap (a window across
        the gap would see the cell's relaxation as a step in ``v_o``: an identification
        transient).  What was learnt stays: theta, the RLS covariance P and the guard's state.
        """
        self._taint = np.where(cells, self._window_samples, self._taint)

    def set_groups(self, sizes) -> None:
        """Cells in consecutive groups of ``sizes``, independent packs side by side (the batch's stacked
        drives): what is shared across the cells (the RLS error window's head, a step taken when any
        cell learns, the LIF product's width) is then kept per group, so each group's results are
        the ones it has alone, bit for bit. On a fresh identifier."""
        self.rls.set_groups(sizes)
        history = getattr(self, "history", None)
        if history is not None:
            history.set_groups(sizes)

    def shift_bias(self, dv: np.ndarray, cells: np.ndarray | None = None) -> None:
        """Move an OCV bias ``dv`` (V, per cell) out of the model: v_o history and c0 both shift.

        Called when the SOC estimator re-reads SOC from OCV + dv; afterwards
        v_o = v - OCV(new soc) = old v_o - dv, so the stored history and c0 must
        drop by dv too, or the correction would be applied twice.
        """
        d = cell_vector(dv, self.n_cells)  # read only
        # the callers shift when any cell has a shift (``cells`` given: any of those): with groups of
        # independent packs (rls.set_groups) a group without one keeps its parameters, as alone
        moved = self.rls.group_any(d.astype(bool) if cells is None else cells) if self.rls.grouped else None
        if cells is not None:
            d = np.where(np.asarray(cells, dtype=bool), d, 0.0)
        finite = np.isfinite(d)
        if not all_cells(finite):
            d = np.where(finite, d, 0.0)
        self._shift_history(d)
        self._shift_theta(self.rls.theta, d)
        self._shift_theta(self.theta_good, d)
        params = self._physical_after_shift(self.theta_good)
        self.params = params if moved is None or all_cells(moved) else params.select(moved, self.params)

    def _physical_after_shift(self, theta_s: np.ndarray) -> PhysicalParams:
        """``_physical(theta_s)`` for ``theta_s`` = :attr:`theta_good` just moved by :meth:`_shift_theta`
        (a model whose shift moves c0 alone takes the rest from :attr:`params`)."""
        return self._physical(theta_s)

    @property
    def c0_v(self) -> np.ndarray:
        return self.params.c0_v

    def param_dict(self) -> dict[str, np.ndarray]:
        """The current parameters by name (N,) each: the 2-RC ones, and a model extension's."""
        return self.params.as_dict()

    def predict_static(self, current_a: np.ndarray) -> np.ndarray:
        """Steady-state overpotential for a constant current (R0+R1+R2) i + c0."""
        p = self.params
        return (p.r0_ohm + p.r1_ohm + p.r2_ohm) * current_a + p.c0_v

    def state_dict(self) -> dict[str, np.ndarray]:
        out = {f"rls.{k}": v for k, v in self.rls.state_dict().items()}
        out.update(
            theta_good=self.theta_good.copy(),
            identified=self.identified.copy(),
            rejections=self.rejections.copy(),
            restarts=self.restarts.copy(),
            rejected_run=self._rejected_run.copy(),
            updates=np.array(self.updates),
            prior_theta=self._prior_theta_s.copy(),  # at the start temperature: a restart's block pulls to it
        )
        return out

    def load_state_dict(self, s: dict[str, np.ndarray]) -> None:
        self.rls.load_state_dict({k[4:]: v for k, v in s.items() if k.startswith("rls.")})
        tg = np.asarray(s["theta_good"], dtype=float)
        if tg.shape != self.theta_good.shape:
            raise ValueError(f"theta_good has shape {tg.shape}, expected {self.theta_good.shape}")
        self.theta_good = tg.copy()
        self.identified = np.asarray(s["identified"], dtype=bool).copy()
        self.newly_identified = np.zeros(self.n_cells, dtype=bool)
        self.rejections = np.asarray(s["rejections"], dtype=np.int64).copy()
        self.restarts = np.asarray(s.get("restarts", np.zeros(self.n_cells)), dtype=np.int64).copy()
        self._rejected_run = np.asarray(s.get("rejected_run", np.zeros(self.n_cells)), dtype=np.int64).copy()
        self.updates = int(s["updates"])
        prior = s.get("prior_theta")  # (a state saved before the prior followed the temperature: the 25 degC one)
        if prior is not None:
            prior = np.asarray(prior, dtype=float)
            if prior.shape != self._prior_theta_s.shape or not np.all(np.isfinite(prior)):
                raise ValueError(f"prior_theta has shape {prior.shape} or non-finite values, expected "
                                 f"{self._prior_theta_s.shape}")
            self._prior_theta_s = prior.copy()
            self.rls.theta_ref = prior.copy()
        self.params = self._physical(self.theta_good)


class LifEstimator(Identifier):
    """Continuous-time 2-RC identification with the linear integral filter (LIF) and WRLS.

    Model and filter (see :mod:`bms_estimator.core.lif`)::

        f1^2 v_o = th1 f1f2 v_o + th2 f2^2 v_o + th3 f1^2 i + th4 f1f2 i + th5 f2^2 i + th6 (L Ts)^2

    regressed on time- and current-scaled columns; theta maps to the physical
    parameters by :func:`bms_estimator.core.params.ct_physical_from_theta`.
    A cell learns only when its whole 2L+1 window holds valid samples.
    """

    def __init__(self, n_cells, dt_s, capacity_ah, config: IdentifierConfig = IdentifierConfig()):
        super().__init__(n_cells, dt_s, capacity_ah, config)
        self._window_samples = self.history.length  # a sample taints the window this long
        self._taint = np.full(self.n_cells, self._window_samples, dtype=np.int64)
        self._v_hold = np.zeros(self.n_cells)

    def _init_scales(self) -> None:
        # the history scales by the window only; currents enter in C-rate, so the
        # current columns of theta carry the cell's own 1C current
        self.history = LifHistory(self.n_cells, self.config.window, self.dt_s, 1.0)
        self._scale = self.history.scale[None, :] * np.ones((self.n_cells, 1))
        self._scale[:, 2:5] *= self.i_ref_a[:, None]
        self._scale_rows = np.ascontiguousarray(self._scale.T)  # (6, N): _physical's divisor

    def _theta_s_from_physical(self, r0, r1, tau1, r2, tau2, c0):
        return ct_theta_from_physical(r0, r1, tau1, r2, tau2, c0) * self._scale

    def _physical(self, theta_s):
        # ct_physical_from_theta(theta_s / self._scale), the division written parameter-first (contiguous rows)
        rows = np.divide(theta_s.T, self._scale_rows, out=np.empty((6, self.n_cells)))
        return ct_physical_from_rows(rows, tau_min_s=self.config.tau_min_s, tau_max_s=self.config.tau_max_s)

    def _regress(self, i, v, ok, aux=None):
        # hold the last valid overpotential for a bad sample; the window stays tainted for 2L+1 samples
        v_in = np.where(ok, v, self._v_hold)
        self._v_hold = v_in
        i_c = i / self.i_ref_a
        if not (all_cells(ok) and not any_cell(self._taint)):  # (every window clean and every sample good: stays 0)
            self._taint = np.where(ok, np.maximum(self._taint - 1, 0), self.history.length)
        i_c = np.where(np.isfinite(i_c), i_c, 0.0)
        y, phi = self.history.push(v_in, i_c, aux, self._extra_inputs(i_c))
        # history.push scaled the current columns by 1/T, 1/T^2 only (i_ref = 1); currents came in C-rate
        return y, phi, (self._taint == 0) & self.history.ready

    def _extra_inputs(self, i_c: np.ndarray) -> np.ndarray | None:
        """Further model inputs (m, N) from the current in C-rate (none in the 2-RC model)."""
        return None

    def _physical_after_shift(self, theta_s):
        # the shift moved th6 alone; R0, the RC pairs and their checks are functions of th1..th5 of
        # theta_good, which self.params holds for every cell (it is set wherever theta_good is), so
        # only c0 = -th6 / th2 is new: the values _physical gives, without redoing the rest
        if type(self)._physical is not LifEstimator._physical or self.params.dynamics_ok is None:
            return self._physical(theta_s)
        return self.params.with_c0(ct_c0_from_theta(theta_s[:, 5] / self._scale[:, 5],
                                                    theta_s[:, 1] / self._scale[:, 1]))

    def _c0_gain(self, theta_s):
        # c0 = -th6_s / th2_s (s2 = s6 = T^2)
        return -theta_s[:, 1]

    def _shift_theta(self, theta_s, dv):
        # th6 = -th2 c0  ->  c0 - dv  gives  th6 + th2 dv ; both scaled by T^2
        theta_s[:, 5] += theta_s[:, 1] * dv

    def _shift_history(self, dv):
        self.history.shift_v_o(dv)
        self._v_hold = self._v_hold - dv

    def state_dict(self):
        s = super().state_dict()
        s.update({f"lif.{k}": v for k, v in self.history.state_dict().items()})
        s["taint"] = self._taint.copy()
        s["v_hold"] = self._v_hold.copy()
        return s

    def load_state_dict(self, s):
        self.history.load_state_dict({k[4:]: v for k, v in s.items() if k.startswith("lif.")})
        self._taint = np.asarray(s["taint"], dtype=np.int64).copy()
        self._v_hold = np.asarray(s["v_hold"], dtype=float).copy()
        super().load_state_dict(s)


class ArxEstimator(Identifier):
    """Discrete-time ARX baseline (the paper's comparison), same WRLS machinery::

        v_o[k] = A1 v_o[k-1] + A2 v_o[k-2] + B0 i[k] + B1 i[k-1] + B2 i[k-2] + K

    mapped back to the 2-RC parameters through the ZOH relations in
    :func:`bms_estimator.core.params.dt_physical_from_theta`.
    """

    def __init__(self, n_cells, dt_s, capacity_ah, config: IdentifierConfig = IdentifierConfig()):
        super().__init__(n_cells, dt_s, capacity_ah, config)
        self._hist = np.zeros((n_cells, 4))  # v_o[k-1], v_o[k-2], i[k-1], i[k-2] (C-rate)
        self._count = 0
        self._window_samples = 3  # a sample taints the regressor this long
        self._taint = np.full(self.n_cells, self._window_samples, dtype=np.int64)
        self._v_hold = np.zeros(self.n_cells)

    def _init_scales(self) -> None:
        self._scale = np.ones((self.n_cells, 6))
        self._scale[:, 2:5] = self.i_ref_a[:, None]

    def _theta_s_from_physical(self, r0, r1, tau1, r2, tau2, c0):
        return dt_theta_from_physical(r0, r1, tau1, r2, tau2, c0, dt_s=self.dt_s) * self._scale

    def _physical(self, theta_s):
        return dt_physical_from_theta(
            theta_s / self._scale, dt_s=self.dt_s,
            tau_min_s=self.config.tau_min_s, tau_max_s=self.config.tau_max_s,
        )

    def _regress(self, i, v, ok):
        v_in = np.where(ok, v, self._v_hold)
        self._v_hold = v_in
        i_c = np.where(np.isfinite(i), i / self.i_ref_a, 0.0)
        phi = np.empty((self.n_cells, 6))
        phi[:, 0] = self._hist[:, 0]
        phi[:, 1] = self._hist[:, 1]
        phi[:, 2] = i_c
        phi[:, 3] = self._hist[:, 2]
        phi[:, 4] = self._hist[:, 3]
        phi[:, 5] = 1.0
        self._hist[:, 1] = self._hist[:, 0]
        self._hist[:, 0] = v_in
        self._hist[:, 3] = self._hist[:, 2]
        self._hist[:, 2] = i_c
        self._count += 1
        self._taint = np.where(ok, np.maximum(self._taint - 1, 0), self._window_samples)
        return v_in, phi, (self._taint == 0) & (self._count >= 3)

    def _c0_gain(self, theta_s):
        # K = c0 (1 - A1 - A2)
        return 1.0 - theta_s[:, 0] - theta_s[:, 1]

    def _shift_theta(self, theta_s, dv):
        # K = c0 (1 - A1 - A2): c0 -> c0 - dv
        theta_s[:, 5] -= dv * (1.0 - theta_s[:, 0] - theta_s[:, 1])

    def _shift_history(self, dv):
        self._hist[:, 0] -= dv
        self._hist[:, 1] -= dv
        self._v_hold = self._v_hold - dv

    def state_dict(self):
        s = super().state_dict()
        s.update(arx_hist=self._hist.copy(), arx_count=np.array(self._count), taint=self._taint.copy(),
                 v_hold=self._v_hold.copy())
        return s

    def load_state_dict(self, s):
        self._hist = np.asarray(s["arx_hist"], dtype=float).copy()
        self._count = int(s["arx_count"])
        self._taint = np.asarray(s["taint"], dtype=np.int64).copy()
        self._v_hold = np.asarray(s["v_hold"], dtype=float).copy()
        super().load_state_dict(s)
