"""The D-second resistance the identified model misses, learnt online from the cell's own current steps.

The SOP's prediction (core.sop) for a constant current ``I`` held ``D`` s from a start ``a``::

    v_hat(D, I) = v_base + [OCV(s + c I) - OCV(s)] + R_D I

uses the identified ECM's ``R_D = R0 + sum_j R_j (1 - exp(-D / tau_j))``.  On a measured
cell the online identifier's slow branch wanders between pulses and the cell's
resistance falls with current, so ``R_D`` misses the cell's real D-second response by
a few milliohm (on the Panasonic 18650PF HPPC at 25 degC the model's 10 s pulse
prediction is 17 mV off in the median).  This module measures that miss on the cell
itself, every time the cell does what the SOP predicts from a known state: a current step out of
rest held for D s.  (Learning from every held step of a drive as well made the drive-cycle
back-test worse: the 10 s windows of a drive that hold their current start from RC states
the model tracks less well, and their dR carried that error to the next windows.)

Window.  At a sample ``a`` where the current steps out of rest, ``|i_a - i_{a-1}| >= step_c Q``
after ``rest_s`` of ``|i| < rest_c Q`` (a pulse from rest, as core.pulse_resistance), the
prediction basis of the period starting at ``a`` (``v_base``, ``R_D``, ``OCV(s)`` per
horizon, from the SOP of the sample before) is kept.  The window is scored when ``D``
samples of it have been seen, if the current held: every sample but the first (a
logger's ramp-in sample) within ``[(1 - hold) I_w, (1 + hold) I_w]`` of the window's
mean ``I_w``, and ``|I_w| >= step_c Q``.  Then (``v`` the measured voltage and ``s_end`` the estimator's SOC
at the window's end)::

    dR = (v - v_base - [OCV(s_end) - OCV(s)] - R_D I_w) / I_w

is the resistance the model missed over D s at that current, kept per cell, horizon and
current sign (discharge / charge) with the SOC it was seen at; the latest one counts
(the identifier's drift makes the most recent response the most relevant).  A step
inside an open window does not restart it (a logged step spread over two samples would
otherwise start the window one sample late); the hold test rejects a window whose
current moved.

Correction.  The SOP then uses ``R_D + dR`` for that sign and horizon (floored at
``R_D / 2``, so the predicted voltage stays increasing in ``I``), for cells whose ``dR``
was seen within ``max_age_s`` and within ``soc_band`` of the SOC now; otherwise
``dR = 0``, the identified model alone.  Causal: a window is used only once it has ended.

Vectorised over cells; no I/O.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated

import numpy as np
from annotated_types import Ge, Gt

from .bounds import check_bounds

__all__ = ["ResidualConfig", "ResidualResistance"]


@dataclass(frozen=True)
class ResidualConfig:
    enabled: bool = True
    step_c: Annotated[float, Gt(0)] = 0.25  # C: the current step that opens a window, and the least |I_w|
    # the step must come out of rest: |i| < rest_c C for rest_s before it (core.pulse_resistance's and the
    # back-test's pulse from rest)
    rest_c: Annotated[float, Gt(0)] = 0.02
    rest_s: Annotated[float, Ge(0)] = 60.0
    hold: Annotated[float, Ge(0)] = 0.5  # every sample of a window within (1 +- hold) I_w
    max_age_s: Annotated[float, Gt(0)] = 3600.0  # a dR older than this is not used
    soc_band: Annotated[float, Gt(0)] = 0.1  # nor one seen further than this from the SOC now

    def __post_init__(self) -> None:
        check_bounds(self)


class ResidualResistance:
    """dR per (sign, horizon, cell): row 0 discharge, row 1 charge (module docstring)."""

    def __init__(self, n_cells: int, dt_s: float, horizons_s, config: ResidualConfig = ResidualConfig()) -> None:
        self.n_cells = int(n_cells)
        self.dt_s = float(dt_s)
        self.config = config
        hz = np.asarray(horizons_s, dtype=float)
        self.n_h = len(hz)
        self.length = np.maximum(np.rint(hz / self.dt_s).astype(int), 1)[:, None]  # (H, 1) samples per window
        shape = (self.n_h, self.n_cells)
        self.dr_ohm = np.full((2,) + shape, np.nan)
        self.dr_soc = np.full((2,) + shape, np.nan)
        self.dr_seen_k = np.full((2,) + shape, -np.inf)  # the sample each dR was seen at
        self._k = 0
        self._age = np.full(shape, -1, dtype=np.int64)  # samples seen of the open window, -1 none
        self._base = np.zeros(shape)
        self._r_d = np.zeros(shape)
        self._ocv0 = np.zeros(shape)
        self._i_sum = np.zeros(shape)
        self._i_min = np.zeros(shape)
        self._i_max = np.zeros(shape)
        self._i_last = np.full(self.n_cells, np.nan)
        self._rest_n = np.zeros(self.n_cells)  # samples at rest before this one
        self._rest_need = round(config.rest_s / self.dt_s)
        self.windows_scored = 0
        self.groups = None  # see set_groups
        self.windows_scored_by_group: np.ndarray | None = None

    def set_groups(self, groups) -> None:
        """Cells in groups (a :class:`~bms_estimator.core.groups.CellGroups`), independent packs side by
        side: the windows scored are then also counted per group (``windows_scored_by_group``), so that
        the SOX part refreshes a group's correction when that group scored one, as it does alone.
        Everything else here is per cell already."""
        self.groups = groups
        self.windows_scored_by_group = np.zeros(groups.n, dtype=np.int64)

    def sample(self, current_a, voltage_v, ocv_end_v, soc, capacity_ah, basis) -> None:
        """One sample (after the estimator's update with it).

        ``basis``: (v_base (H, N), R_D (H, N), OCV(s) (N,)) of the SOP computed for the period
        this sample belongs to (the sample before's), or None; ``ocv_end_v`` = OCV at the
        estimator's SOC after this sample.
        """
        cfg = self.config
        i = np.asarray(current_a, dtype=float)
        self._k += 1
        q = np.asarray(capacity_ah, dtype=float)
        rested = self._rest_n >= self._rest_need
        step = (np.abs(i - self._i_last) >= cfg.step_c * q) & rested if rested.any() else None  # NaN -> False
        self._i_last = i
        self._rest_n = np.where(np.abs(i) < cfg.rest_c * q, self._rest_n + 1, 0.0)
        if basis is not None and step is not None and step.any():
            new = step & (self._age < 0)  # a step inside an open window does not restart it
            if new.any():
                base, r_d, ocv0 = basis
                self._age = np.where(new, 0, self._age)
                self._base = np.where(new, base, self._base)
                self._r_d = np.where(new, r_d, self._r_d)
                self._ocv0 = np.where(new, ocv0, self._ocv0)
                self._i_sum = np.where(new, 0.0, self._i_sum)
                self._i_min = np.where(new, np.inf, self._i_min)
                self._i_max = np.where(new, -np.inf, self._i_max)
        open_ = self._age >= 0
        if not open_.any():
            return
        self._i_sum = self._i_sum + np.where(open_, i, 0.0)
        later = open_ & (self._age > 0)  # the hold is checked after the first sample (a logged ramp-in)
        self._i_min = np.fmin(self._i_min, np.where(later, i, np.inf))
        self._i_max = np.fmax(self._i_max, np.where(later, i, -np.inf))
        self._age = np.where(open_, self._age + 1, -1)
        done = self._age >= self.length
        if not done.any():
            return
        with np.errstate(divide="ignore", invalid="ignore"):
            i_w = self._i_sum / self.length
            lo, hi = np.minimum((1 - cfg.hold) * i_w, (1 + cfg.hold) * i_w), np.maximum((1 - cfg.hold) * i_w,
                                                                                      (1 + cfg.hold) * i_w)
            held = (self._i_min >= lo) & (self._i_max <= hi) & (np.abs(i_w) >= cfg.step_c * np.asarray(capacity_ah))
            v = np.asarray(voltage_v, dtype=float)
            dr = (v - self._base - (np.asarray(ocv_end_v, dtype=float) - self._ocv0) - self._r_d * i_w) / i_w
        use = done & held & np.isfinite(dr)
        self._age = np.where(done, -1, self._age)
        if not use.any():
            return
        s = np.broadcast_to(np.asarray(soc, dtype=float), use.shape)
        for row, side in ((0, i_w < 0), (1, i_w > 0)):
            m = use & side
            self.dr_ohm[row] = np.where(m, dr, self.dr_ohm[row])
            self.dr_soc[row] = np.where(m, s, self.dr_soc[row])
            self.dr_seen_k[row] = np.where(m, self._k, self.dr_seen_k[row])
        self.windows_scored += int(np.count_nonzero(use))
        if self.groups is not None:
            self.windows_scored_by_group += self.groups.reduce(np.sum, use.sum(axis=0))

    def rest(self, gap_s: float, cells: np.ndarray) -> None:
        """``gap_s`` seconds without samples at zero current for ``cells`` (a bool mask), as
        ``gap_s / Ts`` samples at rest would have been seen: an open window is closed unscored (it
        would mix samples from before and after the gap), the cells count ``gap_s / Ts`` more
        samples at rest (a step right after the gap is a step out of rest), their last current is 0,
        and every dR learnt is ``gap_s`` older (``max_age_s`` counts the parked time).  The dR
        values themselves are kept."""
        n = float(gap_s) / self.dt_s
        self._age = np.where(cells, -1, self._age)
        self._rest_n = np.where(cells, self._rest_n + n, self._rest_n)
        self._i_last = np.where(cells, 0.0, self._i_last)
        self.dr_seen_k = np.where(cells, self.dr_seen_k - n, self.dr_seen_k)

    def state_dict(self) -> dict[str, np.ndarray]:
        """What a restart keeps: every dR learnt with its SOC and age (samples since it was seen), and each
        cell's time at rest and last current.  An open window is not kept (it would be scored against a
        prediction from before the restart)."""
        return {"dr_ohm": self.dr_ohm.copy(), "dr_soc": self.dr_soc.copy(),
                "dr_age_samples": self._k - self.dr_seen_k, "rest_samples": self._rest_n.copy(),
                "i_last_a": self._i_last.copy()}

    def load_state_dict(self, s) -> None:
        """The state of :meth:`state_dict`; ValueError naming the field whose shape does not fit."""
        shapes = {"dr_ohm": self.dr_ohm.shape, "dr_soc": self.dr_soc.shape, "dr_age_samples": self.dr_seen_k.shape,
                  "rest_samples": self._rest_n.shape, "i_last_a": self._i_last.shape}
        a = {}
        for k, shape in shapes.items():
            a[k] = np.asarray(s[k], dtype=float)
            if a[k].shape != shape:
                raise ValueError(f"residual state {k!r} has shape {a[k].shape}, expected {shape}")
        self.dr_ohm, self.dr_soc = a["dr_ohm"].copy(), a["dr_soc"].copy()
        self.dr_seen_k = self._k - a["dr_age_samples"]
        self._rest_n, self._i_last = a["rest_samples"].copy(), a["i_last_a"].copy()
        self._age = np.full(self._age.shape, -1, dtype=np.int64)

    def correction(self, soc) -> np.ndarray | None:
        """(2H, N) dR in ohm for the SOP's rows (discharge horizons, then charge); None when none applies."""
        if not self.config.enabled:
            return None
        fresh = (((self._k - self.dr_seen_k) * self.dt_s <= self.config.max_age_s)
                 & (np.abs(self.dr_soc - np.asarray(soc, float)) <= self.config.soc_band))
        if not fresh.any():
            return None
        return np.where(fresh, self.dr_ohm, 0.0).reshape(2 * self.n_h, self.n_cells)
