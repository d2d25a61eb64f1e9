"""SOP, SOE and SOH of N cells, one sample per call, on top of a :class:`~bms_estimator.core.soc.SocEstimator`.

Per sample, after ``SocEstimator.update`` (reads only its public attributes: ``soc``,
``temperature_c``, ``capacity_ah``, ``capacity_stated_ah``, ``capacity_estimated``,
``params``, ``ocv``, ``identifier.identified``)::

    RC voltages   x_j[k+1] = p_j x_j[k] + R_j (1 - p_j) i[k],  p_j = exp(-Ts/tau_j)   (identified R_j, tau_j)
    SOP           core.sop.sop_limits at the start of the next period (x_j[k+1], v[k] moved by it)
    SOE           core.soe.energy_left_wh at SoeConfig.rate_c; time to empty at the mean
                  current  i_m += (1 - exp(-Ts/tau_m)) (i - i_m), time to full of a CC-CV charge to
                  v_max from the voltage and current now (core.soe); these and the capacity SOH are
                  recomputed every SoxConfig.slow_period_s (10 s) and held in between
    energy        E_dis += v i Ts / 3600 for i < 0 (Wh out, never decreasing), E_chg += v i Ts / 3600 for
                  i > 0 (Wh in, never decreasing; kept in the state, not an output); E_net (Wh out since
                  the last full cell) goes down again with charge.  Full: soc >= full_soc, or the end of a
                  CC-CV charge, 0 < i <= full_current_c Q_stated at v >= v_max - full_voltage_tol_v with the
                  mean current i_m > 0 (such a
                  charge ends at 98-99 % of the tables' scale, which the SOC alone, at 0.99, missed: on a
                  synthetic Panasonic 18650PF charge from empty, told 10 % off at its start, the SOC ended at
                  0.987-0.988 and E_net at -11.5 Wh, a net energy *received* since a full cell never seen)
    SOH           core.soh: capacity SOH (once justified) and resistance SOH at the reference point
                  (both on the slow cadence, the R0 reading counting for slow_period_s of samples)
    margin        b = v - OCV(s) - R0 i - sum_j x_j; rms_D^2 += a (b_k - b_{k-D/Ts})^2 - ...: the model's
                  D-second error, which moves the SOP bounds inward (core.sop, "Model-error margin")
    rest          T s parked without samples (SoxEstimator.rest): x_j *= exp(-T/tau_j), i_m *= exp(-T/tau_m),
                  the residual history restarts; the margin's rms_D, SOH and energy kept, the margin's
                  weight aged by exp(-T/margin_tau_s) (the errors after a long park replace it fast)

The RC voltages are tracked here from the identified parameters (the same ZOH recursion
as core.ecm), so this module does not depend on how the SOC filter keeps its own.

Speed (200 cells, ``bms-estimator bench``'s ``sox_ms_200_cells``).  Profiled with cProfile
and per-line timing, the SOX part cost 1.21 ms per sample: the SOP 0.44 ms (6 OCV table
calls on ``(6, 200)`` arrays), its pack pass 0.16 ms (2 more), the SOE 0.18 ms (a
``(21, 200)`` OCV grid and four ``take_along_axis``), the tracking 0.14 ms (one more OCV
call), the rest the outputs.  Almost none of it was arithmetic: numpy's per-call cost
on small arrays was (a sum over the 2-element RC axis 20 us, five of them; ``nan_to_num``
9 us; 23 ``broadcast_to`` and 20 ``errstate`` contexts 2-5 us each; every OCV call re-located
the cells' temperatures).  Now: every horizon and both directions are one ``(6, N)``
Newton solve; the OCV and its slope share one grid location
(:class:`~bms_estimator.core.ocv_surface.OcvAtTemperatures`, the temperatures located once
per sample and kept while unchanged); the pack's power comes out of the cells' last OCV call;
the RC sums are ``einsum``/column adds; one ``errstate`` per solve; 5 OCV calls per sample
instead of 10.  The limits are unchanged (bit-identical on the bench pack; the powers
to 1e-15).  The energy left, time to empty/full and both SOH figures (slow quantities)
are recomputed every ``slow_period_s``.  After it: 0.44 ms (0.68 ms on the 10 s refresh).
A second round (:meth:`SoxEstimator.update`): the estimator's parameters, SOC and counting
capacity are read once per sample for both halves; the OCV at the SOC now (the model error)
and the OCV and slope at the next period's start (the SOP's anchor) are one ``(2, N)`` lookup;
masked updates are skipped while every cell is valid; the resistance SOH's outputs are held
with the slow ones (it only changes on the slow cadence).  Bit-identical outputs
(tests/core/test_sop_fast.py); 0.39-0.48 ms against 0.45-0.50 ms before, measured
interleaved under load.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Annotated

import numpy as np
from annotated_types import Ge

from .bounds import check_bounds
from .cells import rest_arguments
from .groups import CellGroups
from .soe import SoeConfig, energy_left_wh, time_to_empty_s, time_to_full_s
from .soh import ResistanceSoh, SohConfig, capacity_soh
from .ocv_surface import OcvAtTemperatures
from .sop import SopConfig, sop_and_pack_limits
from .sop_residual import ResidualConfig, ResidualResistance

__all__ = ["SoxConfig", "SoxEstimator", "rest_estimators"]


@dataclass(frozen=True)
class SoxConfig:
    sop: SopConfig = field(default_factory=SopConfig)
    soe: SoeConfig = field(default_factory=SoeConfig)
    soh: SohConfig = field(default_factory=SohConfig)
    residual: ResidualConfig = field(default_factory=ResidualConfig)  # the learnt R_D correction (core.sop_residual)
    full_soc: float = 0.99  # the net energy delivered restarts at this SOC
    # ... and where a charge's CV phase ends: charging at v_max (within full_voltage_tol_v) at a current at or
    # under full_current_c of the stated capacity (a CC-CV charger stops at C/20-C/10; module docstring, energy)
    full_current_c: Annotated[float, Ge(0)] = 0.1
    full_voltage_tol_v: Annotated[float, Ge(0)] = 0.01
    # energy left, time to empty/full and capacity SOH are recomputed every slow_period_s and held
    # in between (they move by well under 1 % in 10 s; the SOP and the energy counters run every sample)
    slow_period_s: Annotated[float, Ge(0)] = 10.0

    def __post_init__(self) -> None:
        check_bounds(self)


class SoxEstimator:
    """The state of power, energy and health of the cells a SocEstimator tracks."""

    def __init__(self, n_cells: int, dt_s: float, config: SoxConfig = SoxConfig()) -> None:
        self.n_cells = int(n_cells)
        self.dt_s = float(dt_s)
        self.config = config
        self.x_v = np.zeros((self.n_cells, 2))  # RC voltages at the start of the next period
        self.mean_current_a = np.zeros(self.n_cells)
        self.energy_discharged_wh = np.zeros(self.n_cells)
        self.energy_delivered_wh = np.zeros(self.n_cells)  # net, since the last full cell
        self.energy_charged_wh = np.zeros(self.n_cells)  # Wh in (fleet analytics: energy per drive)
        self._slow_every = max(int(round(config.slow_period_s / self.dt_s)), 1)  # samples
        # the resistance SOH is updated on the slow cadence, each reading standing for that many samples
        self.resistance = ResistanceSoh(self.n_cells, self.dt_s * self._slow_every, config.soh)
        self._ok = np.zeros(self.n_cells, dtype=bool)
        self.v_anchor = np.full(self.n_cells, np.nan)  # the voltage at the next period's start, at i_anchor
        self.v_now = np.full(self.n_cells, np.nan)  # the last valid voltage (the time to full's anchor)
        self.i_anchor = np.zeros(self.n_cells)
        self.soc_anchor = np.full(self.n_cells, np.nan)
        self._x_prev = np.zeros((self.n_cells, 2))
        self.outputs: dict[str, np.ndarray] = {}
        self.pack: dict[str, np.ndarray] = {}
        # model-error margin (core.sop): the residual b the ECM leaves, its history over the
        # longest horizon, and the mean square of its change over each horizon
        hz = np.asarray(config.sop.horizons_s, dtype=float)
        self._lag = np.maximum(np.rint(hz / self.dt_s).astype(int), 1)
        self._b_hist = np.full((int(self._lag.max()) + 1, self.n_cells), np.nan)
        self._b_head = 0
        self.error_ms_v2 = np.zeros((len(hz), self.n_cells))  # mean square n-step error per horizon
        # the weight of the evidence behind it (1 = a full margin_tau_s of samples, the steady state);
        # a park ages it (rest), the samples after it rebuild it
        self.margin_weight = np.ones((len(hz), self.n_cells))
        self._margin_aged = False
        self._slow_due = 0
        self._slow: dict[str, np.ndarray] = {}
        self._slow_r: dict[str, np.ndarray] = {}
        self._ocv_at_last = None
        self._limit_keys = [tuple(f"{k}_max_{d:g}s_{u}" for k, u in (("i_discharge", "a"), ("i_charge", "a"),
                                                                     ("p_discharge", "w"), ("p_charge", "w")))
                            for d in hz]
        self.residual = ResidualResistance(self.n_cells, self.dt_s, hz, config.residual)
        self._anchor = None  # (SOC, OCV, slope) at the next period's start, from the last track
        self._basis = None  # the last SOP's prediction basis, for the residual's windows
        self._dr = None  # its correction now, (2H, N) or None
        self._dr_seen = -1
        # the exponential averages' weights per sample (mean current; model-error margin)
        self._a_mean = 1.0 - np.exp(-self.dt_s / config.soe.mean_current_tau_s)
        self._a_margin = 1.0 - np.exp(-self.dt_s / config.sop.margin_tau_s)
        self.groups: CellGroups | None = None  # see set_groups
        self._one_pack = CellGroups([self.n_cells], self.n_cells)  # pack_outputs: all the cells as one group
        self._one_cell_groups = False  # see set_groups

    def set_groups(self, sizes) -> None:
        """Cells in consecutive groups of ``sizes``, independent packs side by side (the batch's
        stacked drives), as ``Identifier.set_groups``: what this part shares across its cells is
        then kept per group, so that each group's outputs and state are the ones it has alone, bit
        for bit (tests/core/test_sox_groups.py, tests/fleet/test_fleet_stack.py).  On a fresh part.

        What one pack shares, and how it goes per group:

        * the learnt-resistance correction (``sop_residual``) is refreshed for every cell when any
          cell scores a window (and on the slow cadence): per group, refreshed for the cells of a
          group that scored one (its cells' ages and SOC bands read now), the others' held;
        * the slow cadence (energy left, time to empty/full, SOH; restarted by :meth:`rest`) and
          the resistance SOH's reading on it: a counter per group;
        * the pack limits (the weakest valid cell, the power summed over the string, no valid
          cell giving 0) and :meth:`pack_outputs_by_group` (weakest cell, sums, extremes): over
          each group's cells, with the arithmetic of a pack of that size
          (:class:`~bms_estimator.core.groups.CellGroups`);
        * every other all-cells shortcut here (``ok.all()``, ``fresh.all()``, ``rested.any()``,
          ``open_.any()``, ``known.all()``, the OCV table's ``inside``, ``use.any()``) only picks a
          path whose per-cell values are those of the other path; no product of this part goes
          through BLAS (whose kernels, and so the last bit, depend on the width);
        * groups of one cell (the batch's stacked one-cell drives): the energy left's sum over its
          SOC grid cell-major (``core.soe.energy_left_wh``'s ``one_cell_sums``), the pairwise sum a
          one-cell part's single column gets.

        The service's one pack (no groups) takes none of these paths."""
        if self.outputs or self.residual.windows_scored:
            raise ValueError("set_groups needs a fresh SOX part")
        self.groups = g = CellGroups(sizes, self.n_cells)
        self._one_cell_groups = bool(g.n > 1 and (g.sizes == 1).all())
        self.residual.set_groups(g)
        self._dr_seen = np.full(g.n, -1, dtype=np.int64)
        self._slow_due = np.zeros(g.n, dtype=np.int64)

    # ---------------------------------------------------------------- OCV at the cells' temperatures
    @staticmethod
    def ocv_at(est) -> OcvAtTemperatures:
        """OCV and slope of SOC arrays whose last axis is the cells, at each cell's temperature now."""
        return OcvAtTemperatures(est.ocv, est.temperature_c)

    def _ocv_at_cached(self, est) -> OcvAtTemperatures:
        """:meth:`ocv_at`, kept while the temperatures (and the OCV object) are the same as last sample's."""
        t = np.asarray(est.temperature_c, dtype=float)
        c = self._ocv_at_last
        if c is not None and c[0] is est.ocv and c[1].shape == t.shape and np.array_equal(c[1], t):
            return c[2]
        f = self.ocv_at(est)
        self._ocv_at_last = (est.ocv, t.copy(), f)
        return f

    @classmethod
    def ocv_functions(cls, est):
        """(OCV, dOCV/dSOC) of SOC arrays whose last axis is the cells, at each cell's temperature."""
        f = cls.ocv_at(est)
        return f.ocv, f.slope

    def update(self, est, current_a, voltage_v, valid=None) -> None:
        """One period, after ``est.update`` with the same current and voltages: track, then compute."""
        f = self._ocv_at_cached(est)  # the cells' temperatures located once for both
        m = self._inputs(est)  # the estimator's model and SOC read once for both
        with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
            self._track(est, current_a, voltage_v, valid, f, m)
        self._compute(est, f, m, self._anchor)

    def _inputs(self, est) -> dict:
        """What both halves read from the estimator, once per sample: its parameters (the RC pairs
        stacked ``(N, 2)``), SOC and the capacity its count uses."""
        p = est.params
        # (N, 2) views of (2, N) arrays: each RC pair's column is a contiguous row for core.sop
        return dict(p=p, r=np.array([p["r1_ohm"], p["r2_ohm"]], dtype=float).T,
                    tau=np.array([p["tau1_s"], p["tau2_s"]], dtype=float).T,
                    soc=np.asarray(est.soc, dtype=float), q=np.asarray(est.counting_capacity_ah, dtype=float))

    def track(self, est, current_a, voltage_v, valid=None) -> None:
        """The per-sample states only (RC voltages, mean current, energy, model error, learnt R_D); cheap."""
        f = self.ocv_at(est)
        with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
            self._track(est, current_a, voltage_v, valid, f, self._inputs(est))

    def _track(self, est, current_a, voltage_v, valid, ocv_at, m) -> None:
        n = self.n_cells
        if np.ndim(current_a) == 0:  # one pack current (the usual case): no per-cell broadcast
            i0 = float(current_a)
            i_use = np.full(n, i0 if np.isfinite(i0) else 0.0)
            v = np.asarray(voltage_v, dtype=float)
            if v.shape != (n,):
                v = np.broadcast_to(v, (n,))
            ok = np.isfinite(v) if np.isfinite(i0) else np.zeros(n, dtype=bool)
        else:
            i = np.broadcast_to(np.asarray(current_a, dtype=float), (n,))
            v = np.broadcast_to(np.asarray(voltage_v, dtype=float), (n,))
            ok = np.isfinite(v) & np.isfinite(i)
            i_use = np.where(np.isfinite(i), i, 0.0)
        if valid is not None:
            ok &= np.asarray(valid, dtype=bool)
        p, r, tau, soc, q = m["p"], m["r"], m["tau"], m["soc"], m["q"]
        ok_all = bool(ok.all())  # the usual case: every masked update below is a plain one
        good = np.isfinite(r[:, 0] + r[:, 1] + tau[:, 0] + tau[:, 1]) & (np.minimum(tau[:, 0], tau[:, 1]) > 0)
        all_good = bool(good.all())
        pj = np.exp(-self.dt_s / (tau if all_good else np.where(good[:, None], tau, 1.0)))
        x_prev = self._x_prev = self.x_v
        x_next = pj * x_prev + (r if all_good else np.where(good[:, None], r, 0.0)) * (1.0 - pj) * i_use[:, None]
        self.x_v = x_next if all_good else np.where(good[:, None], x_next, 0.0)
        # the voltage at the next period's start at this period's current: v moved by the RC change
        dx = self.x_v - x_prev
        v_next = v + dx[:, 0] + dx[:, 1]
        self.v_anchor = v_next if ok_all else np.where(ok, v_next, self.v_anchor)
        self.v_now = v if ok_all else np.where(ok, v, self.v_now)
        self.i_anchor = i_use if ok_all else np.where(ok, i_use, self.i_anchor)
        # the SOC at the next period's start
        self.soc_anchor = soc + i_use * self.dt_s / (3600.0 * q)
        self.mean_current_a = self.mean_current_a + self._a_mean * (i_use - self.mean_current_a)
        e = v * i_use * self.dt_s / 3600.0
        if not ok_all:
            e = np.where(ok, e, 0.0)
        self.energy_discharged_wh += np.maximum(-e, 0.0)
        self.energy_charged_wh += np.maximum(e, 0.0)
        self.energy_delivered_wh = np.where(self._full(est, soc, i_use, v), 0.0, self.energy_delivered_wh - e)
        # OCV at the SOC now (the model error) and OCV and slope at the next period's start (the
        # SOP's, see _compute) in one table lookup
        z = np.empty((2, n))
        z[0] = soc
        np.clip(self.soc_anchor, 0.0, 1.0, out=z[1])
        o, d = ocv_at.ocv_slope(z)
        self._anchor = (z[1], o[1], d[1])
        self._track_error(p, i_use, v, ok, ok_all, o[0])
        self.residual.sample(i_use if ok_all else np.where(ok, i_use, np.nan), v, o[0], soc, q, self._basis)
        self._ok = ok

    def _full(self, est, soc, i_use, v) -> np.ndarray:
        """The cells full now (the net energy delivered restarts): at or above ``full_soc``, or at the end of a
        CC-CV charge (module docstring, energy).  (Inside :meth:`track`'s errstate: a NaN voltage is not full.)"""
        cfg = self.config
        q = np.asarray(getattr(est, "capacity_stated_ah", est.counting_capacity_ah), dtype=float)
        at_cv_end = ((i_use > 0.0) & (i_use <= cfg.full_current_c * q) & (v >= cfg.sop.v_max - cfg.full_voltage_tol_v)
                     & (self.mean_current_a > 0.0))  # (a charge: not a regen blip at the top of a drive)
        return (soc >= cfg.full_soc) | at_cv_end

    def _track_error(self, p, i_use, v, ok, ok_all, ocv_soc) -> None:
        """b_k = v - OCV(s) - R0 i - sum x (x before this period's step); e = b_k - b_{k-n} per horizon.
        (Inside :meth:`track`'s errstate.)"""
        x = self._x_prev
        b = v - ocv_soc - p["r0_ohm"] * i_use - (x[:, 0] + x[:, 1])
        if not ok_all:
            b = np.where(ok, b, np.nan)
        size = self._b_hist.shape[0]
        self._b_head = (self._b_head + 1) % size
        self._b_hist[self._b_head] = b
        past = self._b_hist[(self._b_head - self._lag) % size]  # (H, N)
        e = b[None, :] - past
        a = self._a_margin
        fresh = np.isfinite(e)
        if self._margin_aged:
            self._age_margin_update(e, fresh, a)
        elif fresh.all():
            self.error_ms_v2 = self.error_ms_v2 + a * (e ** 2 - self.error_ms_v2)
        else:
            self.error_ms_v2 = np.where(fresh, self.error_ms_v2 + a * (np.where(fresh, e, 0.0) ** 2
                                                                       - self.error_ms_v2), self.error_ms_v2)

    def _age_margin_update(self, e, fresh, a) -> None:
        """The margin's update while the evidence behind it is aged by a park (:meth:`rest`): the
        weighted average of the kept mean square (weight ``W``) and the errors seen since,
        ``W_k = (1 - a) W_{k-1} + a`` and ``rms^2 += (a / W_k) (e^2 - rms^2)`` per horizon where
        ``e`` is fresh.  ``W = 1`` is the usual update (gain ``a``); once every weight is back within
        1e-9 of 1 the usual path resumes."""
        w = np.where(fresh, self.margin_weight + a * (1.0 - self.margin_weight), self.margin_weight)
        e2 = np.where(fresh, e, 0.0) ** 2
        self.error_ms_v2 = np.where(fresh, self.error_ms_v2 + (a / w) * (e2 - self.error_ms_v2), self.error_ms_v2)
        if w.min() > 1.0 - 1e-9:
            w = np.ones_like(w)
            self._margin_aged = False
        self.margin_weight = w

    def rest(self, gap_s: float, cells: np.ndarray | None = None, *, est) -> None:
        """``gap_s`` = T seconds without samples, the pack parked (zero current), as
        :meth:`SocEstimator.rest <bms_estimator.core.soc.SocEstimator.rest>` assumes: what the SOX
        model says happened to ``cells`` (a bool mask; all by default) meanwhile.  ``est``: the SOC
        estimator whose model the SOX reads (its identified ``R0``, ``tau_j``, as :meth:`update`).
        Cells not named are untouched; ``rest(0)`` changes nothing.

        * The RC voltages relax as the ZOH recursion at ``i = 0`` does over ``T / Ts`` periods,
          ``x_j <- p_j^(T/Ts) x_j = exp(-T / tau_j) x_j`` (relaxed fully where the model has no
          finite ``tau_j > 0``, as :meth:`update` tracks them).
        * The anchor (the voltage at the next period's start) is the voltage at rest:
          ``v_a <- v_a - R0 i_a - sum_j (x_j - x_j')`` with ``i_a <- 0``; its SOC does not move.
        * The mean current decays as ``T / Ts`` samples of zero would leave it, in closed form:
          ``i_m <- (1 - a_m)^(T/Ts) i_m = exp(-T / tau_m) i_m`` (SoeConfig ``mean_current_tau_s``).
        * The residual history restarts (a change ``b_k - b_{k-n}`` across the gap would mix
          samples from before and after it; the margin takes new errors again once ``n`` samples
          are in); the margin's mean square ``rms_D^2`` is kept: it is the model's error under
          load, and a park is no evidence that the model fits better.  (Fed the parked samples,
          it would decay toward the error at rest, measurement noise included: on the synthetic
          cell of tests/core/test_sox_rest.py, 1 mV noise: 1.40-1.47 mV RMS over the 2-30 s horizons
          after 2 h, against 1.44-1.70 mV kept; the limits 0.2 % apart.)  But the evidence behind it
          ages: it describes the model at the temperature and state of before the park, and the
          cell after a park of hours (cooled or warmed, relaxed) may miss by more or by less.  Its
          weight, a full ``margin_tau_s`` of samples in the steady state, decays over the park with
          that same time constant, ``W <- max(W exp(-T / margin_tau_s), W_min)`` (a 10 s park: 0.98;
          2 h: the floor), ``W_min = min(1, n_max a)`` the weight of the longest horizon's ``n_max``
          samples (``a = 1 - exp(-Ts / margin_tau_s)``: 0.05 at 1 s with the 30 s horizon), and the
          errors after the park are averaged with it (:meth:`_age_margin_update`).  So the park
          itself moves the margin not at all, and after a park of hours the errors of the first
          horizon or two after it replace it, where after a park of seconds they take the usual
          ``margin_tau_s``.
        * The learnt D-second resistance's open windows close unscored, its dRs age by ``T`` and
          the cells count ``T / Ts`` samples at rest (:meth:`ResidualResistance.rest`); the last
          SOP's prediction basis is dropped for them (a window it would open is not scored).
        * Kept: the energy counters (no current, no energy) and the resistance SOH (the
          commissioning R0 and R0 at the reference point: a parked pack does not forget its health).
        * The slow outputs (energy left, time to empty/full, SOH) are recomputed at the next sample.
        """
        gap, sel = rest_arguments(gap_s, cells, self.n_cells)
        if gap == 0.0 or not sel.any():
            return
        m = self._inputs(est)
        tau = m["tau"]
        with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
            good = np.isfinite(tau) & (tau > 0)
            f = np.where(good, np.exp(-gap / np.where(good, tau, 1.0)), 0.0)  # (N, 2)
            x_rested = f * self.x_v
            dv = np.asarray(m["p"]["r0_ohm"], dtype=float) * self.i_anchor + (self.x_v - x_rested).sum(axis=1)
        self.x_v = np.where(sel[:, None], x_rested, self.x_v)
        self.v_anchor = np.where(sel & np.isfinite(dv), self.v_anchor - dv, self.v_anchor)
        self.i_anchor = np.where(sel, 0.0, self.i_anchor)
        cfg = self.config
        self.mean_current_a = np.where(sel, math.exp(-gap / cfg.soe.mean_current_tau_s) * self.mean_current_a,
                                       self.mean_current_a)
        self._b_hist[:, sel] = np.nan
        w_min = min(1.0, float(self._lag.max()) * self._a_margin)  # the longest horizon's samples
        self.margin_weight = np.where(sel, np.maximum(math.exp(-gap / cfg.sop.margin_tau_s) * self.margin_weight,
                                                      w_min), self.margin_weight)
        self._margin_aged = True
        self.residual.rest(gap, sel)
        if self._basis is not None:  # (v_base (H, N), R_D (H, N), OCV(s) (N,)) from before the gap
            base, r_d, ocv_s = self._basis
            self._basis = (np.where(sel, np.nan, base), r_d, ocv_s)
        if self.groups is None:
            self._slow_due = 0
        else:  # the rested cells' packs
            self._slow_due = np.where(self.groups.reduce(np.any, sel), 0, self._slow_due)

    #: the keys of :attr:`outputs` after the limits' (held slow outputs, energy counters, resistance SOH)
    _SLOW_KEYS = ("energy_left_wh", "time_to_empty_s", "time_to_full_s", "soh_capacity", "soh_capacity_sigma")
    _ENERGY_KEYS = ("energy_delivered_wh", "energy_discharged_wh")
    _RESISTANCE_KEYS = ("soh_resistance", "r0_ref_ohm")

    @property
    def output_keys(self) -> tuple[str, ...]:
        """The per-cell keys :attr:`outputs` holds from the first :meth:`update` on, in its order
        (empty before it): the limits per horizon, then the SOE, energy and SOH figures."""
        return (*(k for keys in self._limit_keys for k in keys), *self._SLOW_KEYS, *self._ENERGY_KEYS,
                *self._RESISTANCE_KEYS)

    #: the pack figures of :meth:`pack_outputs` after the limits', in its order
    _PACK_KEYS = ("energy_left_wh", "energy_delivered_wh", "energy_discharged_wh", "time_to_empty_s",
                  "time_to_full_s", "soh_capacity_min", "soh_resistance_max")

    @property
    def pack_output_keys(self) -> tuple[str, ...]:
        """The keys :meth:`pack_outputs` gives from the first :meth:`update` on, in its order (the
        service's pack payload keys): per horizon the pack current and power limits, discharge then
        charge, then the pack's energy, time and SOH figures."""
        return (*(f"{u}_{k}_max_{d:g}s_{unit}" for d in self.config.sop.horizons_s
                  for k in ("discharge", "charge") for u, unit in (("i", "a"), ("p", "w"))), *self._PACK_KEYS)

    def pack_energy_wh(self, cells_wh) -> float:
        """A pack energy from its cells' (Wh per cell): ``n_parallel * sum(cells_wh)`` (every cell of the
        series string counted, each standing for its ``n_parallel`` equal cells)."""
        return float(self.config.sop.n_parallel * np.sum(cells_wh))

    @property
    def v_margin(self) -> np.ndarray:
        """(H, N) volts the limits keep the prediction inside the bounds (module docstring of core.sop)."""
        return self.config.sop.margin_sigmas * np.sqrt(self.error_ms_v2)

    def model(self, est, m: dict | None = None) -> dict[str, np.ndarray]:
        """Keyword arguments of core.sop's functions for the state now (anchor, SOC, capacity, model).

        ``m``: :meth:`_inputs` of ``est`` now, when the caller has it already."""
        m = self._inputs(est) if m is None else m
        return dict(voltage_v=self.v_anchor, current_now_a=self.i_anchor, soc=np.clip(self.soc_anchor, 0.0, 1.0),
                    capacity_ah=m["q"], r0_ohm=m["p"]["r0_ohm"], r_ohm=m["r"], tau_s=m["tau"], x_v=self.x_v)

    def compute(self, est) -> None:
        """SOP, SOE and SOH from the tracked state (after :meth:`track`)."""
        self._compute(est, self.ocv_at(est), self._inputs(est))

    def _compute(self, est, f: OcvAtTemperatures, m: dict, anchor: tuple | None = None) -> None:
        """``anchor``: (SOC, OCV, slope) at the next period's start from :meth:`_track` of this sample."""
        cfg = self.config
        if anchor is None:
            kw, ocv_slope_s = self.model(est, m), None
        else:  # the SOC (clipped), OCV and slope at the next period's start, from _track
            kw = dict(voltage_v=self.v_anchor, current_now_a=self.i_anchor, soc=anchor[0], capacity_ah=m["q"],
                      r0_ohm=m["p"]["r0_ohm"], r_ohm=m["r"], tau_s=m["tau"], x_v=self.x_v)
            ocv_slope_s = anchor[1:]
        if self.groups is not None:
            slow = self._compute_grouped_dr(kw["soc"])
        else:
            slow = self._slow_due <= 0 or not self._slow
            if slow or self.residual.windows_scored != self._dr_seen:  # a new dR, or its age/SOC checked on the slow cadence
                self._dr = self.residual.correction(kw["soc"])
                self._dr_seen = self.residual.windows_scored
        res, self.pack = sop_and_pack_limits(temperature_c=est.temperature_c, ocv=f.ocv, docv_dsoc=f.slope,
                                             ocv_slope=f.ocv_slope, config=cfg.sop, v_margin=self.v_margin,
                                             n_parallel=cfg.sop.n_parallel, valid=np.isfinite(self.v_anchor),
                                             dr_ohm=self._dr, ocv_slope_s=ocv_slope_s, groups=self.groups, **kw)
        self.sop = res
        self._basis = res.basis
        if self.groups is not None:
            self._slow_grouped(est, f, m, kw, slow)
        elif slow:
            self._slow = self._energy_and_capacity(est, f.ocv, kw)
            self.resistance.update(kw["r0_ohm"], est.temperature_c, m["soc"], self._identified(est) & self._ok,
                                   samples=self._slow_every)
            # the resistance SOH changes only here: its outputs are held like the slow ones
            self._slow_r = dict(zip(self._RESISTANCE_KEYS, (self.resistance.ratio, self.resistance.r0_ref_ohm.copy())))
            self._slow_due = self._slow_every
        self._slow_due -= 1
        out = {}
        for h, (k_ia, k_ic, k_pa, k_pc) in enumerate(self._limit_keys):
            out[k_ia] = res.discharge_a[h]
            out[k_ic] = res.charge_a[h]
            out[k_pa] = res.discharge_w[h]
            out[k_pc] = res.charge_w[h]
        out.update(self._slow)
        for key in self._ENERGY_KEYS:
            out[key] = getattr(self, key).copy()
        out.update(self._slow_r)
        self.outputs = out

    def _identified(self, est) -> np.ndarray:
        return np.asarray(getattr(est.identifier, "identified", np.ones(self.n_cells, bool)), dtype=bool)

    def _compute_grouped_dr(self, soc) -> np.ndarray | None:
        """With groups: the learnt correction refreshed for the cells of the groups that are on the slow
        cadence or scored a window since their last refresh, the others' held (as each group alone holds
        its own); returns the groups on the slow cadence per cell (None: none)."""
        g = self.groups
        slow_g = (self._slow_due <= 0) if self._slow else np.ones(g.n, dtype=bool)
        renew = slow_g | (self.residual.windows_scored_by_group != self._dr_seen)
        if renew.any():
            new = self.residual.correction(soc)
            if renew.all() or (new is None and self._dr is None):
                self._dr = new
            else:  # a group without a fresh dR has 0 (as None alone: R_D + 0, floored at R_D / 2, is R_D)
                cells = renew[g.of]
                old = np.zeros_like(new) if self._dr is None else self._dr
                self._dr = np.where(cells, 0.0 if new is None else new, old)
            self._dr_seen = np.where(renew, self.residual.windows_scored_by_group, self._dr_seen)
        return slow_g[g.of] if slow_g.any() else None

    def _slow_grouped(self, est, f, m, kw, slow) -> None:
        """The slow outputs and the resistance SOH's reading, for the cells of the groups on the slow cadence
        (``slow``, per cell, or None), the others' held."""
        if slow is None:
            return
        new = self._energy_and_capacity(est, f.ocv, kw)
        everyone = bool(slow.all())
        self._slow = new if everyone or not self._slow else {k: np.where(slow, v, self._slow[k]) for k, v in new.items()}
        # ResistanceSoh.update is per cell: the cells not read keep their values, as their groups alone do
        self.resistance.update(kw["r0_ohm"], est.temperature_c, m["soc"], self._identified(est) & self._ok & slow,
                               samples=self._slow_every)
        self._slow_r = dict(zip(self._RESISTANCE_KEYS, (self.resistance.ratio, self.resistance.r0_ref_ohm.copy())))
        self._slow_due = np.where(self.groups.reduce(np.any, slow), self._slow_every, self._slow_due)

    def _energy_and_capacity(self, est, ocv, kw) -> dict[str, np.ndarray]:
        """The slow outputs (every ``SoxConfig.slow_period_s``): energy left, time to empty/full, capacity SOH."""
        cfg = self.config
        soc, q, r = kw["soc"], kw["capacity_ah"], kw["r_ohm"]
        r_ss = kw["r0_ohm"] + r[:, 0] + r[:, 1]
        e_left, z_cut = energy_left_wh(soc, q, r_ss, ocv, v_min=cfg.sop.v_min, soc_min=cfg.sop.soc_min, config=cfg.soe,
                                       one_cell_sums=self._one_cell_groups)
        tte = time_to_empty_s(soc, z_cut, q, self.mean_current_a, idle_current_c=cfg.soe.idle_current_c)
        # a CC-CV charge to v_max from the cell's voltage and current now (core.soe)
        ttf = time_to_full_s(soc, q, self.mean_current_a, soc_max=cfg.sop.soc_max, idle_current_c=cfg.soe.idle_current_c,
                             ocv=ocv, voltage_v=self.v_now, current_now_a=kw["current_now_a"], r_ss_ohm=r_ss,
                             v_max=cfg.sop.v_max, end_current_c=cfg.soe.end_current_c, n_points=cfg.soe.n_points)
        ekf = getattr(est, "ekf", None)
        pq = getattr(ekf, "p", None)
        rel_sigma = np.sqrt(np.maximum(pq[:, 3, 3], 0.0)) if pq is not None and np.ndim(pq) == 3 and pq.shape[1] > 3 \
            else np.full(self.n_cells, np.nan)
        soh_q, soh_q_sigma = capacity_soh(est.capacity_ah, est.capacity_stated_ah, rel_sigma * est.capacity_ah,
                                          est.capacity_estimated)
        return dict(zip(self._SLOW_KEYS, (e_left, tte, ttf, soh_q, soh_q_sigma)))

    def pack_outputs(self) -> dict[str, float]:
        """Pack figures: the SOP per horizon, and the sums/extremes of the cell figures (keys:
        :attr:`pack_output_keys`; none before the first :meth:`update`): the one pack of all the
        cells, as floats."""
        return {key: float(v[0]) for key, v in self._pack_figures(self._one_pack).items()}

    def pack_outputs_by_group(self) -> dict[str, np.ndarray]:
        """:meth:`pack_outputs` of each group (:meth:`set_groups`), one ``(G,)`` array per key: column ``g``
        holds the floats group ``g``'s :meth:`pack_outputs` has alone, bit for bit."""
        if self.groups is None:
            raise ValueError("pack_outputs_by_group needs cell groups (set_groups); one pack: pack_outputs")
        return self._pack_figures(self.groups)

    def _pack_figures(self, g: CellGroups) -> dict[str, np.ndarray]:
        """The pack figures of each group of ``g``, ``(G,)`` per key: the limits (``(H,)`` of one pack, or
        ``(H, G)``), the weakest cell's energy left times the group's cells (the weakest cell ends the series
        string's discharge), its cells' energy sums, the extremes of time and SOH."""
        out: dict[str, np.ndarray] = {}
        for h, d in enumerate(self.config.sop.horizons_s):
            tag = f"{d:g}s"
            for k in ("discharge", "charge"):
                if self.pack:
                    out[f"i_{k}_max_{tag}_a"] = np.reshape(self.pack[f"{k}_a"][h], -1)
                    out[f"p_{k}_max_{tag}_w"] = np.reshape(self.pack[f"{k}_w"][h], -1)
        o = self.outputs
        if o:
            np_ = self.config.sop.n_parallel
            with np.errstate(all="ignore"):
                out["energy_left_wh"] = np_ * g.nanmin(o["energy_left_wh"]) * g.sizes
                out["energy_delivered_wh"] = np_ * g.reduce(np.sum, o["energy_delivered_wh"])
                out["energy_discharged_wh"] = np_ * g.reduce(np.sum, o["energy_discharged_wh"])
                out["time_to_empty_s"] = g.reduce(np.min, o["time_to_empty_s"])
                out["time_to_full_s"] = g.reduce(np.max, o["time_to_full_s"])
                out["soh_capacity_min"] = g.nanmin(o["soh_capacity"])
                out["soh_resistance_max"] = g.nanmax(o["soh_resistance"])
        return out

    def state_dict(self) -> dict[str, np.ndarray]:
        s = {f"soh.{k}": v for k, v in self.resistance.state_dict().items()}
        s.update({f"residual.{k}": v for k, v in self.residual.state_dict().items()})
        s.update({"x_v": self.x_v.copy(), "mean_current_a": self.mean_current_a.copy(),
                  "error_ms_v2": self.error_ms_v2.copy(), "margin_weight": self.margin_weight.copy(),
                  "energy_discharged_wh": self.energy_discharged_wh.copy(),
                  "energy_delivered_wh": self.energy_delivered_wh.copy(),
                  "energy_charged_wh": self.energy_charged_wh.copy()})
        return s

    def load_state_dict(self, s) -> None:
        self._slow = {}  # the held slow outputs (the resistance SOH among them) are recomputed next sample
        self.resistance.load_state_dict({k[4:]: v for k, v in s.items() if k.startswith("soh.")})
        residual = {k[9:]: v for k, v in s.items() if k.startswith("residual.")}
        if residual:  # states saved before it was kept: learnt again
            self.residual.load_state_dict(residual)
        for k in ("x_v", "mean_current_a", "energy_discharged_wh", "energy_delivered_wh", "error_ms_v2"):
            a = np.asarray(s[k], dtype=float)
            if a.shape != getattr(self, k).shape:
                raise ValueError(f"sox state {k!r} has shape {a.shape}, expected {getattr(self, k).shape}")
            setattr(self, k, a.copy())
        # states saved before the margin's weight was kept: full weight (the margin as it was)
        w = np.asarray(s.get("margin_weight", np.ones(self.margin_weight.shape)), dtype=float)
        if w.shape != self.margin_weight.shape:
            raise ValueError(f"sox state 'margin_weight' has shape {w.shape}, expected {self.margin_weight.shape}")
        self.margin_weight = w.copy()
        self._margin_aged = bool((w < 1.0).any())
        # states saved before it was counted: the energy charged counts from the restore
        a = np.asarray(s.get("energy_charged_wh", np.zeros(self.n_cells)), dtype=float)
        if a.shape != (self.n_cells,):
            raise ValueError(f"sox state 'energy_charged_wh' has shape {a.shape}, expected ({self.n_cells},)")
        self.energy_charged_wh = a.copy()


def rest_estimators(est, sox: SoxEstimator | None, gap_s: float) -> None:
    """The pack parked for ``gap_s`` seconds without samples: the SOP/SOE/SOH part (if any) rests
    first, with the model it tracked the last sample with, then the SOC estimator
    (:meth:`SoxEstimator.rest`, ``SocEstimator.rest``).  The one order every caller keeps."""
    if sox is not None:
        sox.rest(gap_s, est=est)
    est.rest(gap_s)
