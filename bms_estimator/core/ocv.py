"""Open-circuit voltage as a function of state of charge: OCV(SOC), its inverse and slope.

Conventions: ``soc`` is a fraction (0 = empty, 1 = full), voltages in V, current
positive = charge, charge ``Q`` in Ah (``Q = integral I dt / 3600``).

1. Interpolation.  The knots ``(soc_k, ocv_v_k)`` (both strictly increasing) are
   joined by a monotone cubic Hermite curve whose interior knot slopes are the
   PCHIP slopes (``scipy.interpolate.PchipInterpolator``, Fritsch-Carlson
   harmonic means) and whose two end slopes are the end secants
   ``m_lo = (ocv_1 - ocv_0)/(soc_1 - soc_0)`` and
   ``m_hi = (ocv_n - ocv_{n-1})/(soc_n - soc_{n-1})``.  (PCHIP's own end rule
   can give a zero end slope; the secant keeps the curve strictly increasing and,
   with interior slopes <= 3 x secant, inside the Fritsch-Carlson monotone
   region.)
2. Extrapolation.  Beyond the knot range (``[0, 1]`` for a full curve) the curve
   continues linearly with the end slopes, so it is C1 and never NaN::

       ocv(s) = ocv_0 + m_lo (s - soc_0)   for s < soc_0
       ocv(s) = ocv_n + m_hi (s - soc_n)   for s > soc_n

3. Fast evaluation.  The curve is sampled once on a uniform grid of 2001 SOCs
   and evaluated by direct indexing, ``k = floor((s - soc_0)/h)``, plus linear
   interpolation inside the cell (O(1) per query).  ``soc_from_ocv`` is the
   exact inverse of that piecewise-linear table (a uniform-OCV seed table picks
   the segment, the linear piece is solved), so ``soc_from_ocv(ocv(s)) == s``
   to rounding and both directions are exactly monotone.  The table differs
   from the cubic by ``<= h^2 max|ocv''| / 8``: median 0.2 uV, at most 0.35 mV in
   the steep first 0.5 % SOC of the Panasonic C/20 curve.  Measured on 2000
   unsorted cells: ``ocv`` 38 us, ``soc_from_ocv`` 80 us, ``docv_dsoc`` 28 us,
   against ~100 us for one ``PchipInterpolator`` call and ~140 us for
   ``np.interp`` on the same table (binary search per query); a scalar call
   takes 1-3 us.
4. Slope.  ``docv_dsoc`` is the spline derivative (sampled on the same grid),
   the end slope beyond the knots, floored at ``MIN_SLOPE_V`` so that it is
   strictly positive (an estimator's Jacobian never vanishes).
5. Hysteresis.  ``hysteresis(soc)`` is half the charge-minus-discharge gap
   (>= 0), PCHIP-interpolated, held constant beyond the knots, 0 if none.
6. Temperature.  A curve is measured at one temperature, ``temperature_c``
   (the test's median cell temperature, ``None`` when unknown).  Tables at
   several temperatures are combined by :class:`~bms_estimator.core.ocv_surface.OcvSurface`.
"""

from __future__ import annotations

import math
import warnings
from typing import Any, Sequence

import numpy as np
from scipy.interpolate import CubicHermiteSpline, PchipInterpolator

from .cells import any_cell, clip

__all__ = ["OcvCurve", "MIN_SLOPE_V", "hppc_gap_charges", "median_temperature_c"]

#: Floor of ``docv_dsoc`` [V per unit SOC].
MIN_SLOPE_V = 1e-3
#: Dense uniform SOC grid used for fast evaluation.
GRID_POINTS = 2001
#: Uniform OCV grid of the inverse's seed table.
INVERSE_GRID_POINTS = 8001
#: A user OCV table may dip by up to this much [V] and be repaired with a warning.
MAX_OCV_DIP_V = 5e-3
#: A user OCV table should span at least this SOC range; beyond its knots the curve is extrapolated along
#: its end secants (module docstring, 2.), which for a table that stops short is a guess, warned of once.
#: (The shipped and measured tables start at 0-2.2 % SOC: C/20 at 0, HPPC rests at 1.5-2.2 %.)
OCV_SOC_COVERAGE = (0.1, 0.9)
#: A table's ocv_v must lie in this range [V] (a single cell's open-circuit voltage).
OCV_RANGE_V = (0.0, 10.0)
#: A cell's temperature lies in this range [degC]; outside it a value is in kelvin or Fahrenheit, or a
#: sensor's fault code (the recordings' temperature_c and the tables' are held to it: the estimator reads
#: the OCV tables and its priors at the cell temperature)
CELL_TEMPERATURE_RANGE_C = (-60.0, 150.0)
#: A C/20 test's discharge branch holds at least this share of all the charge its file discharges.
C20_BRANCH_SHARE_MIN = 0.5
#: Step of the strictly-increasing repair [V].
_EPS_V = 1e-6
#: Optional one-value-per-table CSV columns (the test's temperature, its C/20 discharge capacity).
_CONSTANT_COLUMNS = ("temperature_c", "capacity_ah")


def _strictly_increasing(y: np.ndarray, eps: float) -> np.ndarray:
    """Smallest-change repair making ``y`` strictly increasing by at least ``eps``.

    ``z_k = max_{j<=k}(y_j - eps j) + eps k``, so ``z_k - z_{k-1} >= eps`` and
    ``z_k >= y_k`` (flat spots and dips are lifted to a ramp of slope ``eps``).
    """
    ramp = eps * np.arange(y.size)
    return np.maximum.accumulate(y - ramp) + ramp


def _as_float_array(x: Any) -> tuple[np.ndarray, bool]:
    arr = np.asarray(x, dtype=np.float64)
    return arr, arr.ndim == 0


def _out(arr: np.ndarray, scalar: bool) -> np.ndarray | float:
    return float(arr) if scalar else arr


class OcvCurve:
    """Monotone OCV(SOC) curve with inverse, slope and optional hysteresis.

    Args:
        soc: knot SOCs, strictly increasing, inside ``[0, 1]``.
        ocv_v: knot OCVs [V], strictly increasing, same length (>= 2).
        hysteresis_v: optional half charge-minus-discharge gap [V], >= 0.
        capacity_discharge_ah, capacity_charge_ah: branch throughputs measured
            by :meth:`from_c20` (``None`` otherwise; :meth:`from_hppc` sets the
            discharge one to the coulomb-counted capacity it used).
        temperature_c: the cell temperature the table was measured at [degC]
            (``None`` when unknown).

    Raises:
        ValueError: shapes, NaN, non-monotone knots, negative hysteresis.
    """

    def __init__(
        self,
        soc: Sequence[float] | np.ndarray,
        ocv_v: Sequence[float] | np.ndarray,
        hysteresis_v: Sequence[float] | np.ndarray | None = None,
        *,
        capacity_discharge_ah: float | None = None,
        capacity_charge_ah: float | None = None,
        temperature_c: float | None = None,
    ) -> None:
        s = np.array(soc, dtype=np.float64)
        v = np.array(ocv_v, dtype=np.float64)
        if s.ndim != 1 or v.ndim != 1 or s.size != v.size:
            raise ValueError(f"soc and ocv_v must be 1-D of equal length, got {s.shape} and {v.shape}")
        if s.size < 2:
            raise ValueError("an OCV curve needs at least 2 points")
        if not (np.all(np.isfinite(s)) and np.all(np.isfinite(v))):
            raise ValueError("soc and ocv_v must be finite (no NaN/inf)")
        if s[0] < -1e-9 or s[-1] > 1 + 1e-9:
            raise ValueError(f"soc must lie in [0, 1], got {s[0]:.6g}..{s[-1]:.6g}")
        if np.any(np.diff(s) <= 0):
            k = int(np.flatnonzero(np.diff(s) <= 0)[0]) + 1
            raise ValueError(f"soc must be strictly increasing (index {k}: {s[k - 1]!r} -> {s[k]!r})")
        if np.any(np.diff(v) <= 0):
            k = int(np.flatnonzero(np.diff(v) <= 0)[0]) + 1
            raise ValueError(
                f"ocv_v must be strictly increasing (index {k}, soc {s[k]:.4f}: "
                f"{v[k - 1]!r} -> {v[k]!r} V)"
            )
        h = None
        if hysteresis_v is not None:
            h = np.array(hysteresis_v, dtype=np.float64)
            if h.shape != s.shape:
                raise ValueError(f"hysteresis_v has shape {h.shape}, soc has {s.shape}")
            if not np.all(np.isfinite(h)):
                raise ValueError("hysteresis_v must be finite")
            if np.any(h < 0):
                raise ValueError(f"hysteresis_v must be >= 0 (min {h.min():.6g} V)")
        s = np.clip(s, 0.0, 1.0)
        for arr in (s, v) + ((h,) if h is not None else ()):
            arr.setflags(write=False)
        self.soc: np.ndarray = s
        self.ocv_v: np.ndarray = v
        self.hysteresis_v: np.ndarray | None = h
        self.capacity_discharge_ah = None if capacity_discharge_ah is None else float(capacity_discharge_ah)
        self.capacity_charge_ah = None if capacity_charge_ah is None else float(capacity_charge_ah)
        if temperature_c is not None and not math.isfinite(float(temperature_c)):
            raise ValueError(f"temperature_c must be a finite number of degC, got {temperature_c!r}")
        self.temperature_c = None if temperature_c is None else float(temperature_c)
        self._build()

    # ------------------------------------------------------------------ set-up
    def _build(self) -> None:
        s, v = self.soc, self.ocv_v
        secants = np.diff(v) / np.diff(s)
        self._s0, self._s1 = float(s[0]), float(s[-1])
        self._v0, self._v1 = float(v[0]), float(v[-1])
        self._slope_lo = float(secants[0])
        self._slope_hi = float(secants[-1])
        if s.size > 2:
            d = PchipInterpolator(s, v).derivative()(s)
        else:
            d = np.full(2, secants[0])
        d[0], d[-1] = secants[0], secants[-1]
        spline = CubicHermiteSpline(s, v, d)
        grid = np.linspace(self._s0, self._s1, GRID_POINTS)
        gv = spline(grid)
        gv[0], gv[-1] = self._v0, self._v1
        if np.any(np.diff(gv) <= 0):  # rounding guard: the table must be strictly increasing
            gv = _strictly_increasing(gv, 1e-12 * max(1.0, abs(self._v1)))
            gv[-1] = max(gv[-1], self._v1)
            self._v1 = float(gv[-1])
        self._fwd = _UniformTable(self._s0, self._s1, gv)
        on_grid = self._fwd._locate  # the SOC tables share a grid: one locator (a query is located once)
        self._slope = _UniformTable(self._s0, self._s1, np.maximum(spline.derivative()(grid), MIN_SLOPE_V), on_grid)
        # inverse seed table: exact inverse of the forward table sampled at uniform OCVs
        vgrid = np.linspace(self._v0, self._v1, INVERSE_GRID_POINTS)
        self._inv = _UniformTable(self._v0, self._v1, np.interp(vgrid, gv, grid))
        if self.hysteresis_v is not None:
            hp = PchipInterpolator(s, self.hysteresis_v)
            self._hyst = _UniformTable(self._s0, self._s1, np.maximum(hp(grid), 0.0), on_grid)
        else:
            self._hyst = None

    # --------------------------------------------------------------- hot paths
    def ocv(self, soc: Any) -> np.ndarray | float:
        """OCV [V] at ``soc`` (any shape; scalar in, float out); linear beyond the knots."""
        s, scalar = _as_float_array(soc)
        if scalar:
            x = float(s)
            if x < self._s0:
                return self._v0 + self._slope_lo * (x - self._s0)
            if x > self._s1:
                return self._v1 + self._slope_hi * (x - self._s1)
            return self._fwd.scalar(x)
        v = self._fwd(s)
        v += self._slope_lo * np.minimum(s - self._s0, 0.0) + self._slope_hi * np.maximum(s - self._s1, 0.0)
        return _out(v, scalar)

    __call__ = ocv

    def soc_from_ocv(self, ocv_v: Any) -> np.ndarray | float:
        """Inverse of :meth:`ocv`: SOC at ``ocv_v`` [V]; linear beyond the knots (may leave [0, 1]).

        A uniform-OCV seed table gives the forward-table segment; the segment is
        corrected to the one bracketing ``v`` and the linear piece solved exactly,
        so this is the exact inverse of :meth:`ocv` (to rounding).
        """
        v, scalar = _as_float_array(ocv_v)
        if scalar:
            x = float(v)
            if x < self._v0:
                return self._s0 + (x - self._v0) / self._slope_lo
            if x > self._v1:
                return self._s1 + (x - self._v1) / self._slope_hi
            return self._fwd.inverse_scalar(x, self._inv.scalar(x))
        vc = np.clip(v, self._v0, self._v1)
        s = self._fwd.inverse(vc, self._inv(vc))
        s += np.minimum(v - self._v0, 0.0) / self._slope_lo + np.maximum(v - self._v1, 0.0) / self._slope_hi
        return s

    def docv_dsoc(self, soc: Any) -> np.ndarray | float:
        """Slope dOCV/dSOC [V per unit SOC], strictly positive (>= ``MIN_SLOPE_V``)."""
        s, scalar = _as_float_array(soc)
        if scalar:
            x = float(s)
            if x < self._s0:
                return max(self._slope_lo, MIN_SLOPE_V)
            if x > self._s1:
                return max(self._slope_hi, MIN_SLOPE_V)
            return self._slope.scalar(x)
        d = self._slope(s)
        below, above = s < self._s0, s > self._s1
        if any_cell(below) or any_cell(above):
            d = np.where(below, max(self._slope_lo, MIN_SLOPE_V), d)
            d = np.where(above, max(self._slope_hi, MIN_SLOPE_V), d)
        return _out(d, scalar)

    def hysteresis(self, soc: Any) -> np.ndarray | float:
        """Half charge-minus-discharge gap [V] at ``soc`` (>= 0; 0 when the curve has none)."""
        s, scalar = _as_float_array(soc)
        if self._hyst is None:
            return _out(np.zeros(s.shape), scalar)
        if scalar:
            return self._hyst.scalar(float(s))
        return self._hyst(s)

    def ocv_slope_hysteresis(self, soc: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """``(ocv(soc), docv_dsoc(soc), hysteresis(soc))`` of a 1-D float64 ``soc``, the grid located once.

        Each value is what its own method gives, bit for bit (the same operations on the same
        segment index and fraction); the hysteresis is ``None`` when the curve has none. For the
        estimator, which reads all three at one SOC every sample.
        """
        k, f = self._fwd._locate.locate(soc)
        v = self._fwd.at(k, f)
        v += self._slope_lo * np.minimum(soc - self._s0, 0.0) + self._slope_hi * np.maximum(soc - self._s1, 0.0)
        d = self._slope.at(k, f)
        below, above = soc < self._s0, soc > self._s1
        if any_cell(below) or any_cell(above):
            d = np.where(below, max(self._slope_lo, MIN_SLOPE_V), d)
            d = np.where(above, max(self._slope_hi, MIN_SLOPE_V), d)
        return v, d, (None if self._hyst is None else self._hyst.at(k, f))

    @property
    def has_hysteresis(self) -> bool:
        return self.hysteresis_v is not None

    def with_half_gap_cap(self, cap_v: float) -> "OcvCurve":
        """The same table with its half gap capped at ``cap_v``, each branch kept where it is measured best.

        A C/20 gap wider than the cell's hysteresis is a leg's start transient: the
        charge leg starts at empty, the discharge leg at full.  So near empty the
        discharge branch is the measurement and near full the charge branch is.
        Capping ``H`` about the mean would move both branches; here the excess
        ``e = max(H - cap, 0)`` moves the mean toward the measured branch::

            w     = clip((soc - 0.5) / 0.1, -1, 1)      (-1 below 40 % SOC, +1 above 60 %)
            OCV'  = OCV + w e,      H' = min(H, cap)

        so below 40 % SOC ``OCV' - H' = OCV - H`` (the discharge branch, unchanged) and
        above 60 % ``OCV' + H' = OCV + H`` (the charge branch); only the other
        branch comes within ``2 cap`` of it.  The ramp between keeps the mean
        continuous where a table's mid-SOC gap exceeds the cap (none in
        ../shared/data: 15-41 mV at 50 % SOC).  The knots are moved and the
        curve rebuilt; without hysteresis, or with no gap above the cap, the
        table itself is returned.  Measured on the SOC matrix (README): with the
        gap capped about the mean, the estimator's discharge branch sat 35-70 mV
        above the measured one at 5-10 % SOC, where the OCV slope is 3 V per unit,
        and every discharge ended 2-3 % low.
        """
        cap = float(cap_v)
        if not (math.isfinite(cap) and cap >= 0):
            raise ValueError(f"the half-gap cap must be a finite number of volts >= 0, got {cap_v!r}")
        if self.hysteresis_v is None:
            return self
        excess = np.maximum(self.hysteresis_v - cap, 0.0)
        if not np.any(excess > 0):
            return self
        v = self.ocv_v + np.clip((self.soc - 0.5) / 0.1, -1.0, 1.0) * excess
        if np.any(np.diff(v) <= 0):
            v = _strictly_increasing(v, 1e-6)
        return OcvCurve(self.soc, v, np.minimum(self.hysteresis_v, cap),
                        capacity_discharge_ah=self.capacity_discharge_ah,
                        capacity_charge_ah=self.capacity_charge_ah, temperature_c=self.temperature_c)

    def __repr__(self) -> str:
        return (
            f"OcvCurve({self.soc.size} points, soc {self.soc[0]:.3f}..{self.soc[-1]:.3f}, "
            f"ocv {self.ocv_v[0]:.4f}..{self.ocv_v[-1]:.4f} V, "
            f"hysteresis={'yes' if self.has_hysteresis else 'no'}"
            + ("" if self.temperature_c is None else f", {self.temperature_c:g} degC") + ")"
        )

    # ------------------------------------------------------------ from C/20
    @classmethod
    def from_c20(
        cls,
        time_s: np.ndarray,
        current_a: np.ndarray,
        voltage_v: np.ndarray,
        *,
        capacity_ah: float | None = None,
        n_points: int = 201,
        current_threshold_a: float | None = None,
        temperature_c: Any = None,
    ) -> "OcvCurve":
        """Pseudo-OCV from a C/20 test: discharge from full, rest, charge to full.

        1. Segments.  Samples with ``I < -I_th`` form discharge runs, ``I > I_th``
           charge runs (``I_th`` = 20 % of the 90th percentile of ``|I|``, i.e. of
           the C/20 current, unless given).  The discharge branch is the run with
           the largest charge; the charge branch the largest charge run after it,
           or, in a test that starts empty and charges first (no charge run after
           the discharge), the largest one before it, which ends full where the
           discharge starts.
        2. Coulomb counting: trapezoid over the branch's records plus the lead
           ``I_first Delta`` before its first record (logger model of
           :meth:`from_hppc`; ``Delta`` = spacing of the branch's records, at most
           the gap to the previous record, 0 if the branch opens the file)::

               Q_d(t) = -integral_{t_d0}^{t} I dt,   Q_c(t) = integral_{t_c0}^{t} I dt

           ``capacity_discharge_ah = Q_d(end)``, ``capacity_charge_ah = Q_c(end)``.
        3. SOC.  With ``capacity_ah=None`` each branch is normalised by its own
           throughput, so each spans exactly 0..1 (the discharge starts at 1.0 from
           full and ends at 0 at cut-off; the charge branch starts at 0 - the cell
           is empty after a discharge to cut-off - and ends at 1)::

               soc_d = 1 - Q_d / Q_d(end),     soc_c = Q_c / Q_c(end)

           The throughputs differ (Panasonic 18650PF at 25 degC: 3.00 Ah discharge,
           2.62 Ah charge; LG HG2: 2.78 / 2.97 Ah), so a single Ah scale would leave
           one branch short of an end.  With ``capacity_ah=C`` both are counted
           against C instead (``soc_d = 1 - Q_d/C``, ``soc_c = 1 - Q_d(end)/C +
           Q_c/C``) and the curve covers only the SOC range both branches reach.
        4. Both branches are interpolated on a common grid of ``n_points`` SOCs::

               ocv_v        = (v_c + v_d) / 2
               hysteresis_v = max((v_c - v_d) / 2, 0)

           The half gap includes the C/20 ohmic/polarisation drop ``|I| R`` as well
           as the true hysteresis.
        5. Flat spots and noise are removed by the minimal strictly-increasing
           repair ``z_k = max_{j<=k}(y_j - eps j) + eps k`` (``eps`` = 1 uV).
        6. ``temperature_c``: the test's cell temperature, a number or the logged
           samples (their median, NaN ignored) becomes :attr:`temperature_c`.

        Raises:
            ValueError: no discharge or no charge branch after it, a discharge branch
                with less than ``C20_BRANCH_SHARE_MIN`` of the file's discharged
                charge (not a C/20 test: a drive cycle, an HPPC test), bad arrays.
        """
        t, i, v = _check_arrays(time_s, current_a, voltage_v)
        if n_points < 3:
            raise ValueError("n_points must be >= 3")
        if current_threshold_a is None:
            ref = float(np.percentile(np.abs(i), 90))
            if ref <= 0:
                raise ValueError("the current is zero in 90 % of the samples or more: not a C/20 test")
            current_threshold_a = 0.2 * ref
        # a branch paused (a rest inside the C/20 discharge or charge, at its own current on either side) is one
        # branch: its longest run alone, stretched over 0..1, read the LG 25 degC table 105 mV RMS off for a 10 min
        # pause 40 % into the discharge
        runs_d = _join_paused_runs(_runs(i < -current_threshold_a), _runs(i > current_threshold_a), i, t)
        runs_c = _join_paused_runs(_runs(i > current_threshold_a), _runs(i < -current_threshold_a), i, t)
        if not runs_d:
            raise ValueError("no discharge segment (I < -threshold) found in the C/20 data")
        qd = [_branch_charge(t, i, a, b) for a, b in runs_d]
        kd = int(np.argmax([-q[-1] for q in qd]))
        d0, d1 = runs_d[kd]
        later = [(a, b) for a, b in runs_c if a >= d1]
        # a test that starts empty charges first: its charge branch ends full where the discharge starts
        charge_first = not later
        if charge_first:
            later = [(a, b) for a, b in runs_c if b <= d0]
        if not later:
            raise ValueError("no charge segment (I > threshold) before or after the discharge in the C/20 data")
        qc = [_branch_charge(t, i, a, b) for a, b in later]
        kc = int(np.argmax([q[-1] for q in qc]))
        c0, c1 = later[kc]
        q_d = -qd[kd]  # discharged Ah, increasing
        q_c = qc[kc]
        cap_d, cap_c = float(q_d[-1]), float(q_c[-1])
        if cap_d <= 0 or cap_c <= 0:
            raise ValueError("C/20 branch throughput is zero")
        # step 1's check: a C/20 test discharges in one run; a drive cycle's longest run is a sliver of its charge
        total_d = float(np.sum(np.maximum(-i[:-1], 0.0) * np.diff(t))) / 3600.0
        if cap_d < C20_BRANCH_SHARE_MIN * total_d:
            raise ValueError(
                f"not a C/20 test: its longest discharge run removes {cap_d:.3g} Ah of the {total_d:.3g} Ah the "
                "file discharges (a C/20 test is one slow discharge, a rest and one slow charge)")

        if capacity_ah is None:
            soc_d = 1.0 - q_d / cap_d
            soc_c = q_c / cap_c
        else:
            if not capacity_ah > 0:
                raise ValueError(f"capacity_ah must be positive, got {capacity_ah!r}")
            soc_d = 1.0 - q_d / capacity_ah
            soc_c = (1.0 - cap_c / capacity_ah if charge_first else 1.0 - cap_d / capacity_ah) + q_c / capacity_ah
        lo = max(0.0, soc_d.min(), soc_c.min())
        hi = min(1.0, soc_d.max(), soc_c.max())
        if capacity_ah is None:
            lo, hi = 0.0, 1.0
        if hi - lo < 0.5:
            raise ValueError(
                f"the C/20 branches overlap only over soc {lo:.3f}..{hi:.3f} with "
                f"capacity_ah={capacity_ah}"
            )
        grid = np.linspace(lo, hi, n_points)
        on_d = np.abs(i[d0:d1]) > current_threshold_a  # (a pause's relaxing voltage is no point of its branch)
        on_c = np.abs(i[c0:c1]) > current_threshold_a
        v_d = _branch_on_grid(soc_d[on_d][::-1], v[d0:d1][on_d][::-1], grid)
        v_c = _branch_on_grid(soc_c[on_c], v[c0:c1][on_c], grid)
        ocv_v = _strictly_increasing(0.5 * (v_c + v_d), _EPS_V)
        hyst = np.maximum(0.5 * (v_c - v_d), 0.0)
        return cls(grid, ocv_v, hyst, capacity_discharge_ah=cap_d, capacity_charge_ah=cap_c,
                   temperature_c=median_temperature_c(temperature_c))

    # ------------------------------------------------------------- from HPPC
    @classmethod
    def from_hppc(
        cls,
        hppc: Any,
        steps: Any | None = None,
        *,
        capacity_ah: float | None = None,
        current_threshold_a: float | None = None,
        ocv_window_s: float = 10.0,
        temperature_c: Any = None,
    ) -> "OcvCurve":
        """OCV from the rests of an HPPC test (no hysteresis).

        ``hppc`` and ``steps`` are ``(time_s, current_a, voltage_v)`` tuples (or
        objects with those attributes), as logged - do not resample them: the
        logging gaps carry the timing information used below.

        Structure of the test (Panasonic 18650PF files): pulse sets (five 10 s
        discharge pulses with 1200 s rests) at SOCs from full to empty, logged
        densely in ``hppc``; between the sets a slow discharge and a long rest,
        which ``hppc`` skips (a logging gap of ~2000-3800 s) and ``steps`` logs
        sparsely (every 60 s while discharging, 300 s at rest, on its own
        zero-based time axis, sometimes followed by unrelated later tests).

        Logger model (consistent with every Panasonic file): a test step's first
        record comes one logging interval ``Delta`` after the step starts, and
        its last record is at the step's end.  (The rest after a discharge step
        is first logged at end + 300 s; a 10 s pulse is 100 records 0.1 s apart
        spanning 9.9 s; each step start found by the alignment of step 4 is
        ``Delta`` = 60 s before its first record, to 0.01 s.)  So a run of
        same-sign current records (``|I| >= current_threshold_a``; by default
        :func:`hppc_rest_current_a`, a share of the largest pulse, so a cell of any size) carries::

            Q_run = I_first Delta + trapezoid over the run's own records      (Ah after / 3600)

        A plain ``sum I dt`` is wrong both ways: across the hours-long gaps of
        ``steps`` it gives 8.8 Ah for a 2.9 Ah cell, and in ``hppc`` it holds the
        6 C pulse current over the 1 s gap to the next (rest) record.

        1. Blocks.  ``hppc`` is split at gaps ``dt > max(30 s, 20 median dt)``.
           The OCV point of block ``k`` is the mean voltage of its rest samples
           (``|I| < current_threshold_a``) in the last ``ocv_window_s`` before its
           first pulse: the end of the long rest that preceded the pulse set.
        2. Pulse charge: the runs inside each ``hppc`` block, ``Delta`` = median
           spacing of consecutive current records (0.1 s).
        3. Discharge steps: the runs in ``steps`` whose records are ``<= 3 Delta``
           apart, ``Delta`` = median spacing of consecutive current records (60 s).
        4. Alignment.  The offset ``o`` between the two time axes is the one that
           places the most step starts ``t_first - Delta + o`` on an ``hppc`` gap
           start (``hppc`` stops logging when the step begins) or on the end of
           ``hppc`` (the final discharge to cut-off), within 2 s.  Runs inside gap
           ``j`` are charged to gap ``j``, a run starting at the end of ``hppc`` to
           the total; runs elsewhere (later tests in the same file) are ignored.
           A gap without a step gives a ``UserWarning``; more than half of them
           without one is a ``ValueError`` (the steps of another test: one of a
           drive cycle's runs lines up with a gap by chance).
        5. SOC by coulomb counting from full (``soc = 1`` at the first block)::

               soc_k = 1 + Q_k / C,    Q_k = sum of pulse and step charges before block k

           with ``C = capacity_ah`` or, when ``None``, the total charge removed by
           the end of the test (the test runs to the discharge cut-off), reported
           as ``capacity_discharge_ah``.  Points outside ``[0, 1]`` are dropped.
        6. OCV values are made strictly increasing with the repair of
           :meth:`from_c20`.
        7. ``temperature_c`` as in :meth:`from_c20` (a number or the logged samples).

        Without ``steps`` every ampere-second must be in ``hppc``; a warning is
        given when ``hppc`` has logging gaps longer than 600 s that could hide
        discharge steps.

        Raises:
            ValueError: fewer than 2 usable rest points, steps that cannot be
                aligned with the ``hppc`` gaps or that leave most of them empty.
        """
        t, i, v = _check_arrays(*_unpack(hppc, "hppc"))
        if current_threshold_a is None:
            current_threshold_a = hppc_rest_current_a(i)
        gaps, gap_s = _hppc_gaps(t)  # gap between sample g and g+1
        block_starts = np.r_[0, gaps + 1]
        block_ends = np.r_[gaps + 1, t.size]
        # pulse charge per block (step 2)
        p_start, _, p_trap, p_delta = _current_runs(t, i, current_threshold_a, gap_s)
        p_q = (p_trap + i[p_start] * p_delta) / 3600.0
        block_q = np.bincount(np.searchsorted(block_starts, p_start, side="right") - 1,
                              weights=p_q, minlength=block_starts.size)

        # charge removed in each gap (and after the end) by the discharge steps
        gap_q = np.zeros(gaps.size)
        tail_q = 0.0
        if steps is not None:
            gap_q, tail_q = _steps_charge(
                _check_arrays(*_unpack(steps, "steps")),
                gap_start=t[gaps], gap_end=t[gaps + 1], t_end=float(t[-1]),
                threshold=current_threshold_a,
            )
        elif gaps.size and np.max(t[gaps + 1] - t[gaps]) > 600.0:
            warnings.warn(
                f"from_hppc: hppc has {gaps.size} logging gaps (longest {np.max(t[gaps + 1] - t[gaps]):.0f} s) "
                "but no steps were given; discharge during the gaps is not counted",
                UserWarning,
                stacklevel=2,
            )

        q_points, v_points = [], []
        for k, (a, b) in enumerate(zip(block_starts, block_ends)):
            active = np.flatnonzero(np.abs(i[a:b]) >= current_threshold_a)
            stop = a + (active[0] if active.size else b - a)  # first pulse (exclusive)
            if stop == a:
                continue  # block starts with a pulse: no rest voltage
            sel = np.arange(a, stop)
            sel = sel[t[sel] >= t[stop - 1] - ocv_window_s]
            q_before = block_q[:k].sum() + gap_q[:k].sum()
            q_points.append(q_before)
            v_points.append(float(np.mean(v[sel])))
        q_total = block_q.sum() + gap_q.sum() + tail_q
        if capacity_ah is None:
            capacity = -q_total
            if capacity <= 0:
                raise ValueError("from_hppc: the test removed no charge; cannot normalise SOC")
        else:
            if not capacity_ah > 0:
                raise ValueError(f"capacity_ah must be positive, got {capacity_ah!r}")
            capacity = float(capacity_ah)
        soc = 1.0 + np.asarray(q_points) / capacity
        ocv = np.asarray(v_points)
        keep = (soc >= -1e-9) & (soc <= 1 + 1e-9)
        soc, ocv = np.clip(soc[keep], 0.0, 1.0), ocv[keep]
        order = np.argsort(soc, kind="stable")
        soc, ocv = soc[order], ocv[order]
        uniq = np.diff(soc, prepend=-np.inf) > 1e-9  # (np.r_[True, ...] is one too long for no point at all)
        soc, ocv = soc[uniq], ocv[uniq]
        if soc.size < 2:
            raise ValueError(
                f"from_hppc: only {soc.size} usable rest point(s) (a rest before a pulse set) found in "
                f"{block_starts.size} logging block(s): not an HPPC test, or one resampled (pass hppc as logged, "
                "load_recording(..., resample_s=None): resampling fills the gaps that separate the pulse sets)"
            )
        ocv = _strictly_increasing(ocv, _EPS_V)
        return cls(soc, ocv, None, capacity_discharge_ah=capacity, temperature_c=median_temperature_c(temperature_c))

    # ------------------------------------------------------------------- CSV
    def to_csv_text(self) -> str:
        """The table as CSV text: ``soc,ocv_v[,hysteresis_v][,temperature_c][,capacity_ah]`` (header row).

        The curve columns have 8 decimals (round trip to 5e-9).  ``temperature_c``
        (:attr:`temperature_c`) and ``capacity_ah`` (:attr:`capacity_discharge_ah`,
        the table's C/20 discharge throughput) are constant columns, written when
        known (10 significant digits).  The charge-branch capacity is not stored.
        (Files: :func:`bms_estimator.ocv_table.write_ocv_table`.)
        """
        header = ["soc", "ocv_v"] + (["hysteresis_v"] if self.hysteresis_v is not None else [])
        cols = [self.soc, self.ocv_v] + ([self.hysteresis_v] if self.hysteresis_v is not None else [])
        const = [(name, value) for name, value in (("temperature_c", self.temperature_c),
                                                   ("capacity_ah", self.capacity_discharge_ah))
                 if value is not None]
        tail = "".join(f",{value:.10g}" for _, value in const)
        lines = [",".join(header + [name for name, _ in const])]
        for row in zip(*cols):
            lines.append(",".join(f"{x:.8f}" for x in row) + tail)
        return "\n".join(lines) + "\n"

    @classmethod
    def from_csv_text(cls, text: str, source: str = "OCV table") -> "OcvCurve":
        """The table in CSV ``text`` as :meth:`to_csv_text` writes it (extra columns ignored); ``source``
        (the file's name) starts every error and warning.  (Files: :func:`bms_estimator.ocv_table.read_ocv_table`.)

        The optional constant columns ``temperature_c`` and ``capacity_ah`` set
        :attr:`temperature_c` and :attr:`capacity_discharge_ah`; each must hold
        one value on every row.  ``soc`` must be a strictly increasing fraction in [0, 1]; a table that
        does not span ``OCV_SOC_COVERAGE`` (0.1..0.9) is read with a ``UserWarning``.  An ``ocv_v``
        column that is flat or dips by at most ``MAX_OCV_DIP_V`` (5 mV) is
        repaired to strictly increasing with a ``UserWarning``; a larger dip is an
        error.

        Raises:
            ValueError: naming the file and the problem (missing column, empty or
                non-numeric value with its line, NaN, non-monotone soc, ...).
        """
        lines = [(n, ln) for n, ln in enumerate(text.removeprefix("\ufeff").splitlines(), start=1)
                 if ln.strip() and not ln.lstrip().startswith("#")]
        if not lines:
            raise ValueError(f"{source}: empty file (no header row)")
        hdr = lines[0][1]
        names = [c.strip().strip('"').strip() for c in hdr.split(",")]
        missing = [c for c in ("soc", "ocv_v") if c not in names]
        if missing:
            raise ValueError(f"{source}: missing column(s) {', '.join(missing)} (header: {hdr.strip()})")
        wanted = ["soc", "ocv_v"] + (["hysteresis_v"] if "hysteresis_v" in names else [])
        constants = [c for c in _CONSTANT_COLUMNS if c in names]
        wanted += constants
        idx = [names.index(c) for c in wanted]
        rows = []
        for n, ln in lines[1:]:
            fields = ln.split(",")
            if len(fields) < len(names):
                raise ValueError(f"{source}: line {n} has {len(fields)} fields, header has {len(names)}")
            row = []
            for c, j in zip(wanted, idx):
                txt = fields[j].strip()
                try:
                    x = float(txt)
                except ValueError:
                    raise ValueError(f"{source}: line {n}: non-numeric value {txt!r} in column '{c}'") from None
                if not math.isfinite(x):
                    raise ValueError(f"{source}: line {n}: value {txt!r} in column '{c}' is not finite")
                row.append(x)
            rows.append(row)
        if len(rows) < 2:
            raise ValueError(f"{source}: needs at least 2 data rows, found {len(rows)}")
        data = np.asarray(rows)
        const: dict[str, float] = {}
        for col, name in zip(data.T[len(wanted) - len(constants):], constants):
            if np.any(col != col[0]):
                k = int(np.flatnonzero(col != col[0])[0])
                raise ValueError(
                    f"{source}: column '{name}' must hold one value (the table's), but line {lines[1][0]} has "
                    f"{float(col[0]):g} and line {lines[k + 1][0]} has {float(col[k]):g}"
                )
            const[name] = float(col[0])
        if const.get("capacity_ah", 1.0) <= 0:
            raise ValueError(f"{source}: capacity_ah must be positive, got {const['capacity_ah']:g}")
        t_lo, t_hi = CELL_TEMPERATURE_RANGE_C
        if not t_lo <= const.get("temperature_c", 25.0) <= t_hi:  # (a table at 298.15 was filed at 298 degC)
            raise ValueError(f"{source}: temperature_c {const['temperature_c']:g} is not a cell temperature "
                             f"(expected {t_lo:g}..{t_hi:g} degC; is the column in kelvin?)")
        data = data[:, :len(wanted) - len(constants)]
        s, v = data[:, 0], data[:, 1]
        h = data[:, 2] if data.shape[1] > 2 else None
        if s.min() < -1e-9 or s.max() > 1 + 1e-9:
            hint = " (percent? soc must be a fraction)" if s.max() > 1.5 else ""
            raise ValueError(f"{source}: soc must lie in [0, 1], got {s.min():.6g}..{s.max():.6g}{hint}")
        ds = np.diff(s)
        if np.any(ds <= 0):
            k = int(np.flatnonzero(ds <= 0)[0]) + 1
            raise ValueError(
                f"{source}: soc is not strictly increasing at line {lines[k + 1][0]} "
                f"({float(s[k - 1])!r} -> {float(s[k])!r})"
            )
        if h is not None and np.any(h < 0):
            k = int(np.flatnonzero(h < 0)[0])
            raise ValueError(f"{source}: line {lines[k + 1][0]}: hysteresis_v {float(h[k])!r} is negative")
        lo, hi = OCV_RANGE_V
        off = np.flatnonzero((v < lo) | (v > hi))
        if off.size:
            k = int(off[0])
            raise ValueError(f"{source}: line {lines[k + 1][0]}: ocv_v {float(v[k])!r} is not a cell's open-circuit "
                             f"voltage (expected {lo:g}..{hi:g} V; is the column in mV?)")
        if np.any(np.diff(v) <= 0):
            dip = np.maximum.accumulate(v) - v
            k = int(np.argmax(dip))
            if dip[k] > MAX_OCV_DIP_V:
                raise ValueError(
                    f"{source}: ocv_v decreases by {dip[k] * 1e3:.1f} mV at line {lines[k + 1][0]} "
                    f"(soc {s[k]:.4f}); OCV must increase with SOC"
                )
            warnings.warn(
                f"{source}: ocv_v is not strictly increasing (largest dip {dip[k] * 1e3:.2f} mV "
                f"at soc {s[k]:.4f}); repaired to a strictly increasing curve",
                UserWarning,
                stacklevel=2,
            )
            v = _strictly_increasing(v, _EPS_V)
        lo_cover, hi_cover = OCV_SOC_COVERAGE
        if s[0] > lo_cover or s[-1] < hi_cover:
            warnings.warn(
                f"{source}: the table covers soc {s[0]:.3g}..{s[-1]:.3g} only; outside it the OCV is extrapolated "
                f"along its end segments, and an SOC read there is a guess: give a table that spans "
                f"{lo_cover:g}..{hi_cover:g} or more (a C/20 test spans 0..1)",
                UserWarning,
                stacklevel=2,
            )
        return cls(np.clip(s, 0.0, 1.0), v, h, capacity_discharge_ah=const.get("capacity_ah"),
                   temperature_c=const.get("temperature_c"))


# ---------------------------------------------------------------------------
# helpers


class _GridLocator:
    """Segment index and fraction ``(k, f)`` of queries on a uniform grid of ``n`` points over ``[x0, x1]``.

    The tables of one curve share a grid (OCV, slope, hysteresis) and the estimator reads
    them at the same SOCs in one sample, so the last query's answer is kept, keyed by the
    query's bytes (shape and dtype included): an equal query gets the same ``(k, f)``
    without recomputing, bit for bit what it would compute. The answer must not be
    modified by the caller.
    """

    _MEMO_MAX = 4096  # larger queries are not kept (keying them costs more than it saves)

    def __init__(self, x0: float, x1: float, n: int) -> None:
        self.x0 = float(x0)
        self.n = int(n)
        self.inv_h = (self.n - 1) / (float(x1) - self.x0)
        self._memo: tuple | None = None  # (key, k, f), replaced as one object (threads see a whole one)

    def __call__(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        key = (x.shape, x.dtype.str, x.tobytes()) if x.size <= self._MEMO_MAX else None
        memo = self._memo
        if key is not None and memo is not None and memo[0] == key:
            return memo[1], memo[2]
        k, f = self.locate(x)
        if key is not None:
            self._memo = (key, k, f)
        return k, f

    def locate(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(k, f)`` of ``x`` computed (not kept): for a caller that reads every table at ``x`` itself."""
        u = (x - self.x0) * self.inv_h
        k = np.floor(u)
        clip(k, 0, self.n - 2, out=k)
        nan = np.isnan(k)
        if any_cell(nan):
            k[nan] = 0
        f = u - k
        clip(f, 0.0, 1.0, out=f)  # NaN stays NaN
        return k.astype(np.intp), f


class _UniformTable:
    """Piecewise-linear interpolation on a uniform grid by direct indexing (O(1) per query).

    ``np.interp`` binary-searches each query; for 2000 unsorted queries on a
    2001-point table that is ~140 us, direct indexing ~20 us.  Queries outside
    ``[x0, x1]`` get the end values (callers add their own extrapolation); NaN
    propagates.  Tables on the same grid can share one ``locator`` (:class:`_GridLocator`).
    """

    def __init__(self, x0: float, x1: float, y: np.ndarray, locator: _GridLocator | None = None) -> None:
        self.x0 = float(x0)
        self.n = int(y.size)
        self.inv_h = (self.n - 1) / (float(x1) - self.x0)
        self.y = np.ascontiguousarray(y, dtype=np.float64)
        self.dy = np.diff(self.y)
        if locator is not None and (locator.x0, locator.n, locator.inv_h) != (self.x0, self.n, self.inv_h):
            raise ValueError("a shared locator must be on the table's own grid")
        self._locate = locator if locator is not None else _GridLocator(x0, x1, self.n)

    def __call__(self, x: np.ndarray) -> np.ndarray:
        x1 = np.atleast_1d(x)
        k, f = self._locate(x1)
        return (self.y[k] + self.dy[k] * f).reshape(np.shape(x))

    def at(self, k: np.ndarray, f: np.ndarray) -> np.ndarray:
        """The table at segment ``k``, fraction ``f`` (a locator's answer on this table's grid)."""
        return self.y[k] + self.dy[k] * f

    def scalar(self, x: float) -> float:
        u = (x - self.x0) * self.inv_h
        if u != u:  # NaN
            return math.nan
        k = min(max(int(math.floor(u)), 0), self.n - 2) if math.isfinite(u) else (0 if u < 0 else self.n - 2)
        f = min(max(u - k, 0.0), 1.0)
        return float(self.y[k] + self.dy[k] * f)

    def inverse(self, y: np.ndarray, x_seed: np.ndarray) -> np.ndarray:
        """Exact inverse of this (strictly increasing) table for ``y`` inside its range.

        ``x_seed`` is an approximate answer; when its segment does not bracket
        ``y`` (``table[k] <= y <= table[k+1]``; rare) the segment is found by
        ``searchsorted``; then the linear piece is solved.
        """
        y1 = np.atleast_1d(y)
        k, _ = self._locate(np.atleast_1d(x_seed))
        r = y1 - self.y[k]
        dy = self.dy[k]
        off = (r < 0) | (r > dy)
        if any_cell(off):
            k = k.copy()  # the locator's answer is shared: not to be modified
            k[off] = np.clip(np.searchsorted(self.y, y1[off], side="right") - 1, 0, self.n - 2)
            r[off] = y1[off] - self.y[k[off]]
            dy[off] = self.dy[k[off]]
        x = self.x0 + (k + r / dy) / self.inv_h
        return x.reshape(np.shape(y))

    def inverse_scalar(self, y: float, x_seed: float) -> float:
        if y != y:
            return math.nan
        u = (x_seed - self.x0) * self.inv_h
        k = min(max(int(math.floor(u)), 0), self.n - 2)
        tab = self.y
        while k > 0 and y < tab[k]:
            k -= 1
        while k < self.n - 2 and y > tab[k + 1]:
            k += 1
        return float(self.x0 + (k + (y - tab[k]) / self.dy[k]) / self.inv_h)


def median_temperature_c(temperature_c: Any) -> float | None:
    """A test's temperature [degC]: a number as given, or the median of logged samples (NaN ignored).

    ``None`` (or no finite sample) gives ``None``.
    """
    if temperature_c is None:
        return None
    t = np.asarray(temperature_c, dtype=np.float64).ravel()
    t = t[np.isfinite(t)]
    return float(np.median(t)) if t.size else None


def _unpack(rec: Any, name: str) -> tuple[Any, Any, Any]:
    if hasattr(rec, "time_s") and hasattr(rec, "current_a") and hasattr(rec, "voltage_v"):
        return rec.time_s, rec.current_a, rec.voltage_v
    try:
        t, i, v = rec[:3]
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be (time_s, current_a, voltage_v) arrays") from None
    return t, i, v


def _check_arrays(time_s: Any, current_a: Any, voltage_v: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    t = np.asarray(time_s, dtype=np.float64)
    i = np.asarray(current_a, dtype=np.float64)
    v = np.asarray(voltage_v, dtype=np.float64)
    if t.ndim != 1 or t.shape != i.shape or t.shape != v.shape:
        raise ValueError(f"time_s, current_a, voltage_v must be 1-D of equal length, got "
                         f"{t.shape}, {i.shape}, {v.shape}")
    if t.size < 2:
        raise ValueError("need at least 2 samples")
    if not (np.all(np.isfinite(t)) and np.all(np.isfinite(i)) and np.all(np.isfinite(v))):
        raise ValueError("time_s, current_a, voltage_v must be finite")
    if np.any(np.diff(t) < 0):
        raise ValueError("time_s must be non-decreasing")
    return t, i, v


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """Maximal runs of True as half-open index ranges [a, b)."""
    m = np.r_[False, mask, False].astype(np.int8)
    edges = np.flatnonzero(np.diff(m))
    return list(zip(edges[0::2].tolist(), edges[1::2].tolist()))


#: runs of one sign joined across a pause into one C/20 branch when their median currents are within this of the
#: first's (the same C-rate; a drive's or an HPPC test's runs at other currents are not joined) ...
PAUSED_RUN_CURRENT_TOLERANCE = 0.25
#: ... and each lasts this long at least (a C/20 branch's parts last hours, a drive's runs seconds to minutes: the
#: data set's drive cycles and HPPC tests are refused with the figures of their runs as before)
PAUSED_RUN_MIN_S = 600.0


def _join_paused_runs(runs: list[tuple[int, int]], opposite: list[tuple[int, int]], i: np.ndarray,
                      t: np.ndarray) -> list[tuple[int, int]]:
    """``runs`` with each chain of consecutive runs of ``PAUSED_RUN_MIN_S`` or more at the first one's current
    (within ``PAUSED_RUN_CURRENT_TOLERANCE``), separated by rests only (no run of ``opposite`` between them),
    joined into one ``[a, b)`` spanning the rests."""
    starts = np.array([a for a, _ in opposite], dtype=np.int64)
    out: list[tuple[int, int]] = []
    ref = None  # the current of the chain the last run of ``out`` can take more of (None: it takes none)
    for a, b in runs:
        level = float(np.median(np.abs(i[a:b])))
        long_run = float(t[b - 1] - t[a]) >= PAUSED_RUN_MIN_S
        if out and ref is not None and long_run:
            a0, b0 = out[-1]
            between = np.any((starts >= b0) & (starts < a))
            if not between and abs(level - ref) <= PAUSED_RUN_CURRENT_TOLERANCE * ref:
                out[-1] = (a0, b)
                continue
        out.append((a, b))
        ref = level if long_run else None
    return out


def _branch_charge(t: np.ndarray, i: np.ndarray, a: int, b: int) -> np.ndarray:
    """Signed Ah counted from the start of run [a, b) at each of its samples.

    Logger model of :meth:`OcvCurve.from_hppc`: the step started one logging
    interval ``Delta`` (median spacing inside the run) before its first record,
    at most at the previous record, and ends at its last record; trapezoid rule
    in between.  A run that opens the file gets no lead.
    """
    dt = np.diff(t[a:b])
    q = np.empty(b - a)
    if a > 0:
        delta = float(np.median(dt)) if dt.size else float(t[a] - t[a - 1])
        q[0] = i[a] * min(float(t[a] - t[a - 1]), delta)
    else:
        q[0] = 0.0
    if b - a > 1:
        q[1:] = q[0] + np.cumsum(0.5 * (i[a + 1:b] + i[a:b - 1]) * dt)
    return q / 3600.0


def _branch_on_grid(soc: np.ndarray, v: np.ndarray, grid: np.ndarray) -> np.ndarray:
    """Voltage of one branch on the SOC grid (soc increasing; repeats averaged out)."""
    s, inv = np.unique(soc, return_inverse=True)
    vv = np.bincount(inv, weights=v) / np.bincount(inv)
    if s.size < 2:
        raise ValueError("a C/20 branch has fewer than 2 distinct SOC values")
    return np.interp(grid, s, vv)


def _current_runs(
    t: np.ndarray, i: np.ndarray, threshold: float, link_max_dt: float | None
) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Runs of same-sign current ``|I| >= threshold``.

    Consecutive such samples are linked when ``dt <= link_max_dt`` (default
    ``3 delta``), ``delta`` being the median spacing of same-sign current
    sample pairs.  Returns (first index, last index, trapezoid integral over the
    run's own samples [A s], delta).
    """
    nz = np.abs(i) >= threshold
    sign = np.sign(i) * nz
    dt = np.diff(t)
    pair = nz[1:] & nz[:-1] & (sign[1:] == sign[:-1]) & (dt > 0)
    if link_max_dt is not None:
        pair &= dt <= link_max_dt
    delta = float(np.median(dt[pair])) if np.any(pair) else 0.0
    link = pair if link_max_dt is not None else pair & (dt <= 3.0 * delta)
    starts = np.flatnonzero(nz & ~np.r_[False, link])
    ends = np.flatnonzero(nz & ~np.r_[link, False])
    seg = np.r_[0.0, np.cumsum(np.where(link, 0.5 * (i[1:] + i[:-1]) * dt, 0.0))]
    return starts, ends, seg[ends] - seg[starts], delta


def _hppc_gaps(t: np.ndarray) -> tuple[np.ndarray, float]:
    """The logging gaps of an ``hppc`` file (:meth:`OcvCurve.from_hppc`, step 1): indices ``g`` with
    ``t[g+1] - t[g] > max(30 s, 20 median dt)``, and that limit."""
    dt = np.diff(t)
    gap_s = max(30.0, 20.0 * float(np.median(dt[dt > 0])) if np.any(dt > 0) else 30.0)
    return np.flatnonzero(dt > gap_s), gap_s


#: An HPPC test's rest is ``|I|`` below this share of its largest pulse (Panasonic 18650PF: 0.087 A of 17.4 A,
#: 0.03 C; its discharge steps are 0.87 A, its rests log 0 A).  A fixed 0.01 A was C/300 on a 3 Ah cell and
#: C/6000 on a 60 Ah one, whose sensor's offset or noise (scaled with its range) made every rest a current run.
HPPC_REST_FRACTION = 0.005


def hppc_rest_current_a(current_a: np.ndarray) -> float:
    """The current below which an HPPC test's sample is at rest: ``HPPC_REST_FRACTION`` of its largest |I|."""
    peak = float(np.nanmax(np.abs(current_a))) if np.size(current_a) else 0.0
    return HPPC_REST_FRACTION * peak if np.isfinite(peak) and peak > 0 else 0.01


def hppc_gap_charges(hppc: Any, steps: Any, current_threshold_a: float | None = None) -> tuple[np.ndarray, np.ndarray, float]:
    """Where an ``hppc`` log pauses for the discharge steps ``steps`` logs, and how much charge each
    pause removed: ``(gap indices g (between samples g and g+1), charge per gap [Ah, signed], charge
    after the end [Ah])``, by the alignment of :meth:`OcvCurve.from_hppc` (steps 1, 3, 4).  Both as logged."""
    t, i, _ = _check_arrays(*_unpack(hppc, "hppc"))
    if current_threshold_a is None:
        current_threshold_a = hppc_rest_current_a(i)
    gaps, _ = _hppc_gaps(t)
    gap_q, tail_q = _steps_charge(_check_arrays(*_unpack(steps, "steps")), gap_start=t[gaps], gap_end=t[gaps + 1],
                                  t_end=float(t[-1]), threshold=current_threshold_a)
    return gaps, gap_q, tail_q


def _steps_charge(
    steps: tuple[np.ndarray, np.ndarray, np.ndarray],
    *,
    gap_start: np.ndarray,
    gap_end: np.ndarray,
    t_end: float,
    threshold: float,
    tol_s: float = 2.0,
) -> tuple[np.ndarray, float]:
    """Charge [Ah, signed] of the sparse discharge steps falling in each hppc gap and after the end.

    See :meth:`OcvCurve.from_hppc`, steps 3-4.
    """
    ts, is_, _ = steps
    starts, ends, trap, delta = _current_runs(ts, is_, threshold, None)
    if starts.size == 0:
        return np.zeros(gap_start.size), 0.0
    if delta <= 0:
        raise ValueError("from_hppc: steps hold no two consecutive non-zero current samples")
    q = (trap + is_[starts] * delta) / 3600.0
    run_a = ts[starts] - delta  # step start on the steps' axis
    run_b = ts[ends]
    anchors = np.r_[gap_start, t_end]
    offsets = (anchors[:, None] - run_a[None, :]).ravel()
    best_o, best_score = 0.0, -1
    for o in np.unique(np.round(offsets, 3)):
        score = int(np.sum(np.min(np.abs(run_a[:, None] + o - anchors[None, :]), axis=1) <= tol_s))
        if score > best_score:
            best_o, best_score = float(o), score
    if best_score < 1:
        raise ValueError("from_hppc: cannot align the steps with the hppc logging gaps")
    a_m, b_m = run_a + best_o, run_b + best_o
    gap_q = np.zeros(gap_start.size)
    for j in range(gap_start.size):
        inside = (a_m >= gap_start[j] - tol_s) & (b_m <= gap_end[j] + tol_s)
        gap_q[j] = q[inside].sum()
    tail = np.abs(a_m - t_end) <= tol_s
    empty = np.flatnonzero(gap_q == 0)
    if 2 * empty.size > gap_start.size:  # a step falls into a gap by chance: these are not this test's steps
        raise ValueError(
            f"from_hppc: {empty.size} of the {gap_start.size} hppc logging gaps hold no discharge step of the steps "
            "data: not the hppc_steps file of this HPPC test")
    if empty.size:
        warnings.warn(
            f"from_hppc: {empty.size} of {gap_start.size} hppc gaps have no discharge step "
            f"in the steps data (first at t = {gap_start[empty[0]]:.1f} s); their charge is not counted",
            UserWarning,
            stacklevel=3,
        )
    return gap_q, float(q[tail].sum())
