"""State of health: capacity SOH with its uncertainty, and resistance SOH at a reference point.

Capacity SOH::

    SOH_Q = Q_est / Q_nominal,      sigma(SOH_Q) = sigma(Q_est) / Q_nominal

reported only once the estimate is justified (the SOC estimator's
``capacity_estimated``: its capacity uncertainty has halved from the prior), NaN
before: a capacity that is still the prior says nothing about ageing.

Resistance SOH.  R0 rises with ageing, but it rises far more as the cell cools (and
at the ends of the SOC range), so a raw R0 ratio would read every cold morning as
ageing.  R0 is brought to a reference temperature with an Arrhenius law::

    R0_ref = R0 exp(-(E_a/R) (1/T - 1/T_ref))          (T in kelvin)

and only samples inside the SOC band ``[soc_lo, soc_hi]`` (where R0 is flat in SOC)
from an identified model count.  The commissioning value ``R0_c`` is the mean of the
first ``commissioning_samples`` such R0_ref values; it is persisted in the state file
and then held.  Then::

    SOH_R = R0_ref / R0_c           (1.0 new; the field's end of life is about 2.0)

``R0_ref`` itself is smoothed with a first-order filter of time constant
``smoothing_s`` over the counted samples.  Vectorised over cells; no I/O.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Annotated

import numpy as np
from annotated_types import Ge, Gt

from .arrhenius import arrhenius_factor, cell_temperature_ok
from .bounds import check_bounds

__all__ = ["SohConfig", "ResistanceSoh", "capacity_soh", "r0_at_reference"]


@dataclass(frozen=True)
class SohConfig:
    reference_temperature_c: float = 25.0
    # E_a / R of R0, kelvin (fitted on the Panasonic 18650PF HPPC R0 at 25/10/0/-10 degC; see README)
    r0_activation_k: Annotated[float, Ge(0)] = 3000.0
    soc_lo: Annotated[float, Ge(0)] = 0.3
    soc_hi: Annotated[float, Gt(0)] = 0.8
    commissioning_samples: Annotated[int, Ge(1)] = 600
    smoothing_s: Annotated[float, Gt(0)] = 600.0

    def __post_init__(self) -> None:
        check_bounds(self)


def capacity_soh(capacity_ah, nominal_ah, capacity_sigma_ah, justified) -> tuple[np.ndarray, np.ndarray]:
    """(SOH_Q, its 1-sigma) per cell; NaN where the estimate is not justified."""
    q = np.asarray(capacity_ah, dtype=float)
    with np.errstate(divide="ignore", invalid="ignore"):
        soh = q / np.asarray(nominal_ah, dtype=float)
        sig = np.asarray(capacity_sigma_ah, dtype=float) / np.asarray(nominal_ah, dtype=float)
    j = np.asarray(justified, dtype=bool) & np.isfinite(soh)
    return np.where(j, soh, np.nan), np.where(j, sig, np.nan)


def r0_at_reference(r0_ohm, temperature_c, config: SohConfig = SohConfig()) -> np.ndarray:
    """R0 brought to the reference temperature (Arrhenius, module docstring)."""
    # exp(-B (1/T - 1/T_ref)), NaN where T is not a cell's temperature (missing, or a sensor fault
    # outside CELL_TEMPERATURE_RANGE_C: the SOH skips those samples); arrhenius_factor keeps its own errstate
    f = arrhenius_factor(config.reference_temperature_c, temperature_c, config.r0_activation_k)
    return np.where(cell_temperature_ok(temperature_c), np.asarray(r0_ohm, dtype=float) * f, np.nan)


class ResistanceSoh:
    """R0 at the reference point, its commissioning value and their ratio, for N cells."""

    def __init__(self, n_cells: int, dt_s: float, config: SohConfig = SohConfig()) -> None:
        self.n_cells = int(n_cells)
        self.dt_s = float(dt_s)
        self.config = config
        self.r0_ref_ohm = np.full(self.n_cells, np.nan)
        self.r0_commissioning_ohm = np.full(self.n_cells, np.nan)
        self._c_sum = np.zeros(self.n_cells)
        self._c_n = np.zeros(self.n_cells, dtype=np.int64)

    def update(self, r0_ohm, temperature_c, soc, identified, samples: int = 1) -> None:
        """One R0 reading per cell; ``samples``: how many samples it stands for (a caller that
        updates every k-th sample, with ``dt_s`` = k Ts, passes k: the commissioning count stays
        in samples)."""
        c = self.config
        r = r0_at_reference(r0_ohm, temperature_c, c)
        s = np.asarray(soc, dtype=float)
        use = np.asarray(identified, dtype=bool) & np.isfinite(r) & (r > 0) & (s >= c.soc_lo) & (s <= c.soc_hi)
        if not use.any():
            return
        a = 1.0 - math.exp(-self.dt_s / c.smoothing_s)
        smoothed = np.where(use, self.r0_ref_ohm + a * (r - self.r0_ref_ohm), self.r0_ref_ohm)
        known = np.isfinite(self.r0_ref_ohm)
        self.r0_ref_ohm = smoothed if known.all() else np.where(use & ~known, r, smoothed)
        commissioned = np.isfinite(self.r0_commissioning_ohm)
        if commissioned.all():  # held from then on: nothing more to count
            return
        todo = use & ~commissioned
        self._c_sum = np.where(todo, self._c_sum + samples * r, self._c_sum)
        self._c_n = np.where(todo, self._c_n + samples, self._c_n)
        done = todo & (self._c_n >= c.commissioning_samples)
        with np.errstate(divide="ignore", invalid="ignore"):
            self.r0_commissioning_ohm = np.where(done, self._c_sum / self._c_n, self.r0_commissioning_ohm)

    @property
    def ratio(self) -> np.ndarray:
        """SOH_R = R0_ref / R0_c (NaN until both are known)."""
        with np.errstate(divide="ignore", invalid="ignore"):
            return self.r0_ref_ohm / self.r0_commissioning_ohm

    def state_dict(self) -> dict[str, np.ndarray]:
        return {"r0_ref_ohm": self.r0_ref_ohm.copy(), "r0_commissioning_ohm": self.r0_commissioning_ohm.copy(),
                "c_sum": self._c_sum.copy(), "c_n": self._c_n.copy()}

    def load_state_dict(self, s) -> None:
        for k in ("r0_ref_ohm", "r0_commissioning_ohm", "c_sum", "c_n"):
            if np.asarray(s[k]).shape != (self.n_cells,):
                raise ValueError(f"soh state {k!r} has shape {np.asarray(s[k]).shape}, expected ({self.n_cells},)")
        self.r0_ref_ohm = np.asarray(s["r0_ref_ohm"], dtype=float).copy()
        self.r0_commissioning_ohm = np.asarray(s["r0_commissioning_ohm"], dtype=float).copy()
        self._c_sum = np.asarray(s["c_sum"], dtype=float).copy()
        self._c_n = np.asarray(s["c_n"], dtype=np.int64).copy()
