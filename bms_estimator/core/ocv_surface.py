"""Open-circuit voltage as a function of SOC and cell temperature: OCV(soc, T) from tables at several T.

Conventions as in :mod:`bms_estimator.core.ocv`: ``soc`` a fraction, voltages in V,
temperatures in degC.  Each table is an :class:`~bms_estimator.core.ocv.OcvCurve`
measured at one temperature ``T_j`` (``T_0 < T_1 < ... < T_{m-1}``).

1. Interpolation, linear in T at equal SOC, held at the end tables outside
   ``[T_0, T_{m-1}]``::

       j = max{i <= m-2 : T_i <= T}   (0 below T_0)
       w = clip((T - T_j) / (T_{j+1} - T_j), 0, 1)
       OCV(s, T) = (1 - w) OCV_j(s) + w OCV_{j+1}(s)

   ``T`` = ``None`` or NaN reads ``default_temperature_c`` (25 degC unless given).
   With one table the temperature is ignored and every call goes straight to
   that :class:`OcvCurve` (its speed unchanged).
2. Monotone at any T.  For fixed ``w`` the blend is a convex combination of
   strictly increasing functions of ``s``, so it is strictly increasing: the
   inverse exists and is unique at every temperature.  SOC means the same
   thing at every T: the fraction of each table's own C/20 throughput.
3. Fast evaluation.  Every table is sampled once on one uniform SOC grid
   ``s_k = S_0 + k h`` (``GRID_POINTS`` = 2001 points over the union of the
   tables' SOC ranges; beyond its own knots a table is its linear extension) and
   the rows are stacked into a flat array ``Y`` of ``m G`` values.  A query needs
   the row ``j``, weight ``w`` (``np.searchsorted`` on the m temperatures), the
   grid cell ``k = floor((s - S_0)/h)`` and its fraction ``f``; then four
   gathers::

       OCV = (1 - w) (Y[jG+k] + dY[jG+k] f) + w (Y[(j+1)G+k] + dY[(j+1)G+k] f)

   This is exactly the piecewise-linear table of the blended curve, so at a
   table's own temperature (``w`` = 0 or 1) it equals that table's
   :meth:`OcvCurve.ocv` (to rounding when the grids coincide, which they do for
   tables over the same SOC range).  Beyond the grid the blend continues
   linearly with the blended end slopes ``(1-w) m_j + w m_{j+1}``.
4. Inverse.  ``soc_from_ocv(v, T)`` is the exact inverse of that blended table:
   a vectorised bisection over grid cells (``ceil(log2(G-1))`` = 11 steps, two
   gathers each, no Python loop over cells) finds ``k`` with
   ``B_k <= v < B_{k+1}`` (``B_k = (1-w) Y_{j,k} + w Y_{j+1,k}``) and the linear
   piece is solved, so ``soc_from_ocv(ocv(s, T), T) = s`` to rounding; linear
   beyond the ends.
5. Slope.  ``docv_dsoc`` blends the tables' slope tables the same way (the
   derivative of a blend is the blend of the derivatives); each row is
   ``>= MIN_SLOPE_V``, so the blend is too.
6. Hysteresis.  ``hysteresis(soc, T)`` is interpolated the same way, but only
   between the tables that have a hysteresis column (a table without one, e.g.
   from HPPC rests, says nothing about the hysteresis, so it is not read as
   H = 0); held beyond them; one such table is used at every T; none gives 0.
7. Capacity.  ``capacity_ah(T)`` interpolates (linear, clamped) the tables' C/20
   discharge capacities ``capacity_discharge_ah`` over the tables that know
   theirs (NaN when none does); ``relative_capacity(T)`` divides it by the
   capacity of the known table nearest 25 degC (1.0 where unknown).

8. Speed.  Measured with ``timeit`` (best of 15 x 200) on 2000 cells at random
   temperatures -20..45 degC, the three LG HG2 C/20 tables (-10, -0.5, 23.9
   degC), on 2 cores shared with other jobs (load average 7-8, so the absolute
   figures are about 2x an idle machine's; OcvCurve's own docstring figures
   are idle ones).  Against one :class:`OcvCurve` in the same run:

   =============================  ==========  ============
   call                           OcvSurface  OcvCurve
   =============================  ==========  ============
   ``ocv`` (same T as last call)  70-86 us    64 us
   ``ocv`` (new T each call)      113-128 us
   ``docv_dsoc``                  87 us       56 us
   ``hysteresis``                 85 us       49 us
   ``soc_from_ocv``               640-770 us  217-227 us
   ``ocv`` scalar                 7 us        1.9 us
   ``soc_from_ocv`` scalar        34-55 us
   =============================  ==========  ============

   The temperature location (``j``, ``w``) of an array is kept for the next
   call with equal temperatures, as the estimator's calls in one step are;
   with one table every call is the OcvCurve's own.

9. One cell.  The blend is only meaningful between tables of one cell.  Every
   pair of neighbouring tables (the pairs blended, ``T_j`` and ``T_{j+1}``, ``dT``
   apart) is compared at equal SOC over 10-90 % (81 points, mean curves)::

       d = RMS_s (OCV_j(s) - OCV_{j+1}(s))      flagged (:attr:`OcvSurface.mixed_cells`) when
       d > min(ONE_CELL_RMS_V + ONE_CELL_RMS_PER_K_V dT, ONE_CELL_RMS_MAX_V)
         = min(15 mV + 1 mV/K x dT, 45 mV)

   Measured on every table the shared data gives (LG HG2 C/20 at 23.9, -0.5 and
   -10.0 degC; Panasonic 18650PF C/20 at 25.2 and HPPC rests at 25.8, 10.8, 0.6
   and -9.7 degC; each built with ``bms-estimator ocv``), over all 13
   pairs of one cell (any two of them can be neighbours in a set): d = 3.7-40.9 mV,
   0.39-1.49 mV/K for the pairs >= 9.5 K apart (9.1 mV for the Panasonic C/20 and
   HPPC tables 0.6 K apart: the two methods, 15 mV/K), at most 0.91 x the limit
   (Panasonic 25.8 / -9.7 degC HPPC, 40.9 mV against 45; 0.85 x below 30 K apart).
   The 15 pairs of the two cells: d = 46.3-76.3 mV whatever dT (0.3-35.8 K),
   1.79-3.6 x the limit up to 21 K apart, at least 1.27 x up to 26 K and 1.14 x
   beyond (LG 23.9 degC against Panasonic -9.7 degC, 51.1 mV against 45).  The two
   meet near 35 K apart (one cell's tables differ more the further apart they are,
   two cells' do not): the 45 mV cap sits between them there.  The C/20 capacity is no criterion:
   one cell's tables differ by 1.3-26 % (0.14-0.92 %/K; 10 %/K for the C/20 and
   HPPC tables 0.6 K apart), two cells' by 1.8-17 %.  Nor is equal charge instead
   of equal SOC (the LG tables agree to 5-14 mV there, but the Panasonic C/20
   against HPPC tables differ by 36-64 mV).  Flagged, not refused: a
   blend of two cells is a wrong OCV at every temperature between them, so the
   edges warn, naming both files and the figure; but the margins rest on two cells
   only (one cell's pairs come within 9 % of the limit 35 K apart), and a cell whose
   tables move more with temperature (colder than -10 degC, another chemistry) must
   still run.
"""

from __future__ import annotations

import math
from typing import Any, Sequence

import numpy as np

from .ocv import GRID_POINTS, MIN_SLOPE_V, OcvCurve, _as_float_array, _strictly_increasing

__all__ = ["Ocv", "OcvSurface", "OcvAtTemperatures", "ONE_CELL_RMS_MAX_V", "ONE_CELL_RMS_PER_K_V",
           "ONE_CELL_RMS_V",
           "REFERENCE_TEMPERATURE_C", "STATED_CAPACITY_RATIO_MAX", "one_cell_mismatch", "stated_capacity_ratio",
           "table_capacities_ah"]

#: Neighbouring tables of one cell differ by at most this RMS OCV at equal SOC over 10-90 % [V], plus
#: ``ONE_CELL_RMS_PER_K_V`` per kelvin between them (module docstring, item 9: the measured margins)
ONE_CELL_RMS_V = 0.015
ONE_CELL_RMS_PER_K_V = 0.001
ONE_CELL_RMS_MAX_V = 0.045  # and never more than this
_ONE_CELL_SOC = np.linspace(0.1, 0.9, 81)


def one_cell_mismatch(curves: Sequence[OcvCurve], temperatures_c: Sequence[float]) -> tuple[int, float, float] | None:
    """The first neighbouring pair (index ``k`` of the lower of ``k``, ``k + 1`` in the order given, which
    must be by temperature) whose RMS OCV difference at equal SOC over 10-90 % exceeds
    ``min(ONE_CELL_RMS_V + ONE_CELL_RMS_PER_K_V dT, ONE_CELL_RMS_MAX_V)``: ``(k, rms_v, limit_v)``; None when
    every pair is within."""
    for k in range(len(curves) - 1):
        d = np.asarray(curves[k].ocv(_ONE_CELL_SOC)) - np.asarray(curves[k + 1].ocv(_ONE_CELL_SOC))
        rms = float(np.sqrt(np.mean(d * d)))
        limit = min(ONE_CELL_RMS_V + ONE_CELL_RMS_PER_K_V * abs(temperatures_c[k + 1] - temperatures_c[k]),
                    ONE_CELL_RMS_MAX_V)
        if rms > limit:
            return k, rms, limit
    return None

#: A stated capacity more than this many times away from the OCV tables' C/20 capacity is not the
#: capacity of the cell the tables were measured on (a pack's or a module's, mA h, another cell's table)
STATED_CAPACITY_RATIO_MAX = 2.0


def table_capacities_ah(ocv: Any) -> list[float]:
    """The C/20 capacities the OCV table(s) carry (``capacity_ah`` column): one per table of an
    :class:`OcvSurface`, the one of an :class:`~bms_estimator.core.ocv.OcvCurve`; empty when none does."""
    curves = getattr(ocv, "curves", None) or [ocv]
    out = [getattr(c, "capacity_discharge_ah", None) for c in curves]
    return [float(q) for q in out if q is not None and math.isfinite(q) and q > 0]


def stated_capacity_ratio(stated_ah: float, ocv: Any) -> float | None:
    """``stated / median table capacity`` when it is outside ``[1 / STATED_CAPACITY_RATIO_MAX,
    STATED_CAPACITY_RATIO_MAX]`` (the stated capacity is not the tables' cell's), else None (within, or
    the tables carry no capacity)."""
    tables = table_capacities_ah(ocv)
    if not tables:
        return None
    ratio = float(stated_ah) / float(np.median(tables))
    return None if 1.0 / STATED_CAPACITY_RATIO_MAX <= ratio <= STATED_CAPACITY_RATIO_MAX else ratio

#: ``relative_capacity`` is relative to the capacity of the table nearest this temperature [degC].
REFERENCE_TEMPERATURE_C = 25.0


class _Blend:
    """Tables sampled on one uniform SOC grid, stacked, blended linearly in temperature.

    ``rows``: (m, G) values on the grid ``linspace(s0, s1, G)``; ``temps``: (m,)
    strictly increasing, m >= 2; ``lo``/``hi``: per-row constants (slopes or
    values) used beyond the grid's ends.  Row ``j`` of a query is carried as its
    flat offset ``jg = j G``.
    """

    def __init__(self, temps: np.ndarray, s0: float, s1: float, rows: np.ndarray,
                 lo: np.ndarray, hi: np.ndarray) -> None:
        self.temps = np.ascontiguousarray(temps, dtype=np.float64)
        self.m, self.g = rows.shape
        self.inv_dt = 1.0 / np.diff(self.temps)
        self.s0, self.s1 = float(s0), float(s1)
        self.inv_h = (self.g - 1) / (self.s1 - self.s0)
        self.rows = rows
        self.y = np.ascontiguousarray(rows.ravel())
        dy = np.zeros_like(rows)
        dy[:, :-1] = np.diff(rows, axis=1)
        self.dy = dy.ravel()
        self.lo, self.hi = lo, hi
        self._cache: tuple[np.ndarray, Any, np.ndarray] | None = None

    def locate_t(self, t: np.ndarray | float) -> tuple[Any, Any]:
        """Row offset ``jg = j G`` (``j`` = 0..m-2) and weight ``w`` in [0, 1] for a non-NaN ``t``.

        ``j`` counts the interior temperatures ``<= t`` (= ``searchsorted(temps, t,
        'right') - 1`` clipped to 0..m-2).  An array's answer is kept for the next
        call with equal values: the estimator asks ocv, slope, hysteresis and
        inverse at the same temperatures in one step.
        """
        if np.ndim(t) == 0:
            t = float(t)
            j = min(max(int(np.searchsorted(self.temps, t, side="right")) - 1, 0), self.m - 2)
            w = min(max((t - self.temps[j]) * self.inv_dt[j], 0.0), 1.0) if math.isfinite(t) else float(t > 0)
            return j * self.g, w
        cache = self._cache
        if cache is not None and cache[0].shape == t.shape and np.array_equal(cache[0], t):
            return cache[1], cache[2]
        if self.m == 2:
            j: Any = 0
            w = (t - self.temps[0]) * self.inv_dt[0]
        else:
            j = (t >= self.temps[1]).astype(np.intp)
            for tk in self.temps[2:-1]:
                j += t >= tk
            w = (t - self.temps.take(j)) * self.inv_dt.take(j)
        np.maximum(w, 0.0, out=w)
        np.minimum(w, 1.0, out=w)
        jg = j * self.g
        self._cache = (t.copy(), jg, w)
        return jg, w

    def __call__(self, s: np.ndarray, jg: Any, w: Any) -> tuple[np.ndarray, bool]:
        """(Blended table at ``s`` (1-D), True when every ``s`` is inside the grid).

        Outside the grid (or NaN) the end value is returned; the caller adds its
        extension.
        """
        a, f, inside = self.locate_s(s, jg)
        return self.at(a, f, w), inside

    def locate_s(self, s: np.ndarray, jg: Any) -> tuple[np.ndarray, np.ndarray, bool]:
        """(flat index ``jG + k`` of row j, fraction ``f``, all inside) for any-shaped ``s``
        whose last axis matches ``jg``'s (or scalar ``jg``): the part of :meth:`__call__` two
        tables on this grid (OCV and slope) can share."""
        u = s * self.inv_h if self.s0 == 0.0 else (s - self.s0) * self.inv_h  # s - 0.0 is s
        inside = bool(u.min() >= 0.0 and u.max() <= self.g - 1)  # False for NaN too
        if not inside:
            u = np.fmin(np.fmax(u, 0.0), self.g - 1.0)  # NaN -> 0 (a safe index)
        k = u.astype(np.intp)
        np.minimum(k, self.g - 2, out=k)
        f = u - k
        k += jg
        return k, f, inside

    def at(self, a: np.ndarray, f: np.ndarray, w: Any, a1: np.ndarray | None = None) -> np.ndarray:
        """The blended table at the location :meth:`locate_s` gave (the end values outside).

        ``a1``: ``a + G`` (the next temperature's row), when the caller has it already."""
        v = self.y.take(a)
        v += self.dy.take(a) * f
        if a1 is None:
            a1 = a + self.g
        v1 = self.y.take(a1)
        v1 += self.dy.take(a1) * f
        v1 -= v
        v1 *= w
        v += v1
        return v

    def scalar(self, x: float, jg: int, w: float) -> tuple[float, int]:
        """One query (Python floats): (blended table value, -1/0/+1 for below/inside/above the grid)."""
        u = (x - self.s0) * self.inv_h
        side = -1 if u < 0 else (1 if u > self.g - 1 else 0)
        u = min(max(u, 0.0), self.g - 1.0)
        k = min(int(u), self.g - 2)
        f = u - k
        y, dy = self.y, self.dy
        a, b = jg + k, jg + k + self.g
        v0 = float(y[a] + dy[a] * f)
        return v0 + w * (float(y[b] + dy[b] * f) - v0), side

    def ends(self, jg: Any, w: Any) -> tuple[Any, Any]:
        """Blended ``lo`` and ``hi`` constants."""
        j = jg // self.g
        lo, hi = self.lo, self.hi
        return lo[j] + w * (lo[j + 1] - lo[j]), hi[j] + w * (hi[j + 1] - hi[j])



class OcvSurface:
    """OCV(soc, T), its inverse, slope and hysteresis from OCV tables measured at several temperatures.

    The math is in the module docstring.  All methods are vectorised: ``soc``
    (or ``ocv_v``) and ``temperature_c`` broadcast against each other (any shape;
    scalars in give a float out, like :class:`OcvCurve`).

    Speed: module docstring, item 8.

    Args:
        curves: one or more tables.
        temperatures_c: the temperature of each table [degC]; ``None`` takes each
            curve's own ``temperature_c``.  Needed for every table when there are
            several; ignored (may be unknown) with one.
        default_temperature_c: the temperature read when a call gives ``None``
            or NaN.
        names: a label per table (its file), for the messages.
        check_one_cell: flag neighbouring tables that are not of one cell
            (module docstring, item 9); off only for tables derived from a
            checked surface.

    Raises:
        ValueError: no table, a table without a temperature when there are
            several, two tables at the same temperature, non-finite values.
    """

    def __init__(
        self,
        curves: Sequence[OcvCurve],
        temperatures_c: Sequence[float] | None = None,
        *,
        default_temperature_c: float = REFERENCE_TEMPERATURE_C,
        names: Sequence[str] | None = None,
        check_one_cell: bool = True,
    ) -> None:
        curves = list(curves)
        mixed_cells = None
        if not curves:
            raise ValueError("an OCV surface needs at least one OCV table")
        for c in curves:
            if not isinstance(c, OcvCurve):
                raise TypeError(f"OcvSurface takes OcvCurve tables, got {type(c).__name__}")
        if temperatures_c is None:
            temps = [c.temperature_c for c in curves]
        else:
            temps = [None if t is None else float(t) for t in temperatures_c]
            if len(temps) != len(curves):
                raise ValueError(f"{len(curves)} OCV tables but {len(temps)} temperatures")
        if not math.isfinite(float(default_temperature_c)):
            raise ValueError(f"default_temperature_c must be finite, got {default_temperature_c!r}")
        self.default_temperature_c = float(default_temperature_c)
        if len(curves) > 1:
            for k, t in enumerate(temps):
                if t is None or not math.isfinite(t):
                    raise ValueError(
                        f"OCV table {k + 1} of {len(curves)} has no temperature ({t!r}); with several tables "
                        "each needs the temperature it was measured at"
                    )
            order = np.argsort(temps, kind="stable")
            curves = [curves[k] for k in order]
            temps = [temps[k] for k in order]
            same = np.flatnonzero(np.diff(temps) == 0)
            if same.size:
                raise ValueError(
                    f"two OCV tables at the same temperature {temps[same[0]]:g} degC; give one table per "
                    "temperature (merge or drop one)"
                )
            bad = one_cell_mismatch(curves, temps) if check_one_cell else None
            if bad is not None:
                k, rms, limit = bad
                label = [f"{names[j]} ({temps[i]:g} degC)" if names is not None else f"the table at {temps[i]:g} degC"
                         for i, j in ((k, order[k]), (k + 1, order[k + 1]))]
                mixed_cells = (
                    f"{label[0]} and {label[1]} differ by {rms * 1e3:.0f} mV RMS at equal SOC (10-90 %), more "
                    f"than one cell's tables {temps[k + 1] - temps[k]:.1f} K apart do ({limit * 1e3:.0f} mV: "
                    f"{ONE_CELL_RMS_V * 1e3:g} mV + {ONE_CELL_RMS_PER_K_V * 1e3:g} mV/K, at most "
                    f"{ONE_CELL_RMS_MAX_V * 1e3:g} mV): are they tables of one cell? The OCV between them is "
                    "their blend; give the OCV tables of the cell being estimated only"
                )
        #: None, or why the neighbouring tables look like two cells' (module docstring, item 9): the
        #: edges (the CLI's ``--ocv``, the service's ``pack.ocv_csv``) warn with it
        self.mixed_cells: str | None = mixed_cells
        self.curves: tuple[OcvCurve, ...] = tuple(curves)
        t_arr = np.array([math.nan if t is None else t for t in temps], dtype=np.float64)
        t_arr.setflags(write=False)
        self._temps = t_arr
        self._single = curves[0] if len(curves) == 1 else None
        self._build()

    def _build(self) -> None:
        curves = self.curves
        hyst = [k for k, c in enumerate(curves) if c.has_hysteresis]
        self._hyst_single = curves[hyst[0]] if len(hyst) == 1 else None
        known = [(self._temps[k], c.capacity_discharge_ah) for k, c in enumerate(curves)
                 if c.capacity_discharge_ah is not None]
        self._cap_t = np.array([t for t, _ in known])
        self._cap = np.array([q for _, q in known])
        if known:
            ref = int(np.argmin(np.abs(np.nan_to_num(self._cap_t, nan=REFERENCE_TEMPERATURE_C)
                                       - REFERENCE_TEMPERATURE_C)))
            self._cap_ref = float(self._cap[ref])
        if self._single is not None:
            return
        s0 = min(float(c.soc[0]) for c in curves)
        s1 = max(float(c.soc[-1]) for c in curves)
        grid = np.linspace(s0, s1, GRID_POINTS)
        below, above = s0 - 1.0, s1 + 1.0
        rows = np.empty((len(curves), GRID_POINTS))
        for k, c in enumerate(curves):
            r = np.asarray(c.ocv(grid))
            if np.any(np.diff(r) <= 0):  # rounding guard, as in OcvCurve
                r = _strictly_increasing(r, 1e-12 * max(1.0, abs(r[-1])))
            rows[k] = r
        # beyond the grid each table is linear: its slope there from two points on its extension
        lo = np.array([c.ocv(s0) - c.ocv(below) for c in curves])
        hi = np.array([c.ocv(above) - c.ocv(s1) for c in curves])
        self._ocv = _Blend(self._temps, s0, s1, rows, lo, hi)
        slope_rows = np.array([np.maximum(c.docv_dsoc(grid), MIN_SLOPE_V) for c in curves])
        self._slope = _Blend(self._temps, s0, s1, slope_rows,
                             np.array([c.docv_dsoc(below) for c in curves]),
                             np.array([c.docv_dsoc(above) for c in curves]))
        self._hyst = None
        if len(hyst) > 1:
            h_rows = np.array([curves[k].hysteresis(grid) for k in hyst])
            zero = np.zeros(len(hyst))
            self._hyst = _Blend(self._temps[hyst], s0, s1, h_rows, zero, zero)
        # the inverse's search tables: row j and row j+1 - row j, padded to a power of two
        self._pad = 1 << math.ceil(math.log2(GRID_POINTS))
        base = np.full((len(curves) - 1, self._pad), 1e300)
        diff = np.zeros_like(base)
        base[:, :GRID_POINTS] = rows[:-1]
        diff[:, :GRID_POINTS] = rows[1:] - rows[:-1]
        self._pad_base, self._pad_diff = base.ravel(), diff.ravel()

    # ------------------------------------------------------------ constructors
    @classmethod
    def from_tables(
        cls,
        curves: Sequence[OcvCurve],
        names: Sequence[str],
        temperatures_c: Sequence[float] | None = None,
        *,
        default_temperature_c: float = REFERENCE_TEMPERATURE_C,
    ) -> "OcvSurface":
        """One surface of ``curves`` (one per table, named by ``names``: the files), each at its own
        :attr:`OcvCurve.temperature_c`.  (Files: :func:`bms_estimator.ocv_table.read_ocv_tables`.)

        ``temperatures_c`` (one per table) overrides the tables' own.

        Raises:
            ValueError: naming the table: no ``temperature_c`` while there are several tables,
                two tables at the same temperature.  Neighbouring tables that are not of one cell
                (module docstring, item 9) are not an error: :attr:`mixed_cells` names both,
                their temperatures and the figure.
        """
        curves, names = list(curves), [str(n) for n in names]
        if not curves:
            raise ValueError("no OCV table given")
        if len(names) != len(curves):
            raise ValueError(f"{len(curves)} OCV tables but {len(names)} names")
        if temperatures_c is not None:
            temps = [float(t) for t in temperatures_c]
            if len(temps) != len(curves):
                raise ValueError(f"{len(curves)} OCV tables but {len(temps)} temperatures")
        else:
            temps = [c.temperature_c for c in curves]
        if len(curves) > 1:
            for name, t in zip(names, temps):
                if t is None:
                    raise ValueError(
                        f"{name}: has no temperature_c column; give --temperature-c when you build it with "
                        "`bms-estimator ocv` (with several OCV tables each needs its temperature)"
                    )
            seen: dict[float, str] = {}
            for name, t in zip(names, temps):
                if t in seen:
                    raise ValueError(f"{seen[t]} and {name} are both at {t:g} degC; give one OCV table per temperature")
                seen[t] = name
        return cls(curves, temps if len(curves) > 1 or temperatures_c is not None else None,
                   default_temperature_c=default_temperature_c, names=names)

    # ------------------------------------------------------------- properties
    @property
    def temperatures_c(self) -> np.ndarray:
        """The tables' temperatures [degC], increasing (NaN for a single table of unknown temperature)."""
        return self._temps

    @property
    def has_hysteresis(self) -> bool:
        """True when any table has a hysteresis column."""
        return any(c.has_hysteresis for c in self.curves)

    def with_half_gap_cap(self, cap_v: float) -> "OcvSurface":
        """Every table's half gap capped at ``cap_v`` (:meth:`OcvCurve.with_half_gap_cap`), the rest the same."""
        curves = [c.with_half_gap_cap(cap_v) for c in self.curves]
        if all(a is b for a, b in zip(curves, self.curves)):
            return self
        capped = OcvSurface(curves, None if self._single is not None else list(self._temps),
                            default_temperature_c=self.default_temperature_c, check_one_cell=False)  # checked once
        capped.mixed_cells = self.mixed_cells
        return capped

    def __repr__(self) -> str:
        temps = ", ".join("?" if math.isnan(t) else f"{t:g}" for t in self._temps)
        return (f"OcvSurface({len(self.curves)} table(s) at {temps} degC, "
                f"hysteresis={'yes' if self.has_hysteresis else 'no'})")

    # -------------------------------------------------------------- hot paths
    def _temperature(self, temperature_c: Any) -> np.ndarray | float:
        if temperature_c is None:
            return self.default_temperature_c
        t = np.asarray(temperature_c, dtype=np.float64)
        if t.ndim == 0:
            t = float(t)
            return self.default_temperature_c if t != t else t
        nan = np.isnan(t)
        return np.where(nan, self.default_temperature_c, t) if nan.any() else t

    def _prepare(self, x: Any, temperature_c: Any, blend: _Blend) -> tuple[np.ndarray, tuple, Any, Any, bool]:
        """(x as 1-D, output shape, jg, w, scalar) with x and the temperature broadcast together."""
        xa, scalar = _as_float_array(x)
        t = self._temperature(temperature_c)
        if not isinstance(t, float) and t.shape != xa.shape:
            xa, t = np.broadcast_arrays(xa, t)
            scalar = False
            t = t.ravel()
        elif not isinstance(t, float):
            t = t.ravel()
        jg, w = blend.locate_t(t)
        return xa.ravel(), xa.shape, jg, w, scalar

    @staticmethod
    def _out(v: np.ndarray, shape: tuple, scalar: bool) -> np.ndarray | float:
        return float(v[0]) if scalar else v.reshape(shape)

    def _scalar(self, x: Any, temperature_c: Any, blend: _Blend) -> tuple[float, int, int, float] | None:
        """(value, side, jg, w) for a finite scalar query at a scalar temperature, else None."""
        if not (isinstance(x, (float, int)) and math.isfinite(x)
                and (temperature_c is None or isinstance(temperature_c, (float, int)))):
            return None
        jg, w = blend.locate_t(self._temperature(temperature_c))
        value, side = blend.scalar(float(x), jg, w)
        return value, side, jg, w

    def ocv(self, soc: Any, temperature_c: Any = None) -> np.ndarray | float:
        """OCV [V] at ``soc`` and ``temperature_c`` [degC]; linear in SOC beyond the tables."""
        if self._single is not None:
            return self._single.ocv(soc)
        b = self._ocv
        one = self._scalar(soc, temperature_c, b)
        if one is not None:
            v, side, jg, w = one
            if side:
                lo, hi = b.ends(jg, w)
                v += lo * min(soc - b.s0, 0.0) + hi * max(soc - b.s1, 0.0)
            return v
        s, shape, jg, w, scalar = self._prepare(soc, temperature_c, b)
        v, inside = b(s, jg, w)
        if not inside:  # linear extension with the blended end slopes (NaN propagates)
            lo, hi = b.ends(jg, w)
            v += lo * np.minimum(s - b.s0, 0.0) + hi * np.maximum(s - b.s1, 0.0)
        return self._out(v, shape, scalar)

    __call__ = ocv

    def docv_dsoc(self, soc: Any, temperature_c: Any = None) -> np.ndarray | float:
        """Slope dOCV/dSOC [V per unit SOC] at ``soc`` and ``temperature_c``, >= ``MIN_SLOPE_V``."""
        if self._single is not None:
            return self._single.docv_dsoc(soc)
        b = self._slope
        one = self._scalar(soc, temperature_c, b)
        if one is not None:
            d, side, jg, w = one
            return float(b.ends(jg, w)[0 if side < 0 else 1]) if side else d
        s, shape, jg, w, scalar = self._prepare(soc, temperature_c, b)
        d, inside = b(s, jg, w)
        if not inside:
            lo, hi = b.ends(jg, w)
            d = np.where(s < b.s0, lo, np.where(s > b.s1, hi, d))
            d[np.isnan(s)] = math.nan
        return self._out(d, shape, scalar)

    def hysteresis(self, soc: Any, temperature_c: Any = None) -> np.ndarray | float:
        """Half charge-minus-discharge gap [V] (>= 0) from the tables that have one; 0 when none has."""
        if self._single is not None:
            return self._single.hysteresis(soc)
        b = self._hyst
        if b is None:
            if self._hyst_single is not None:
                return self._hyst_single.hysteresis(soc)
            s, scalar = _as_float_array(soc)
            z = np.zeros(np.broadcast_shapes(s.shape, np.shape(temperature_c)))
            return float(z) if z.ndim == 0 else z
        one = self._scalar(soc, temperature_c, b)
        if one is not None:
            return one[0]
        s, shape, jg, w, scalar = self._prepare(soc, temperature_c, b)
        h, inside = b(s, jg, w)  # held at the ends
        if not inside:
            h[np.isnan(s)] = math.nan
        return self._out(h, shape, scalar)

    def soc_from_ocv(self, ocv_v: Any, temperature_c: Any = None) -> np.ndarray | float:
        """Inverse of :meth:`ocv` at ``temperature_c``: SOC at ``ocv_v`` [V]; linear beyond the tables."""
        if self._single is not None:
            return self._single.soc_from_ocv(ocv_v)
        b = self._ocv
        v, shape, jg, w, scalar = self._prepare(ocv_v, temperature_c, b)
        lo_slope, hi_slope = b.ends(jg, w)
        if scalar and np.ndim(w) == 0:  # one value: search the blended row
            j = jg // b.g
            row = b.rows[j] + w * (b.rows[j + 1] - b.rows[j])
            v_lo, v_hi = row[0], row[-1]
            vc = np.fmin(np.fmax(v, v_lo), v_hi)
            k = np.minimum(np.searchsorted(row, vc, side="right") - 1, b.g - 2)
            bk, bk1 = row[k], row[k + 1]
        else:
            bk, bk1, k, vc, v_lo, v_hi = self._bisect(v, jg, w)
        s = b.s0 + (k + (vc - bk) / (bk1 - bk)) / b.inv_h
        s += np.minimum(v - v_lo, 0.0) / lo_slope + np.maximum(v - v_hi, 0.0) / hi_slope
        return self._out(s, shape, scalar)

    def _bisect(self, v: np.ndarray, jg: Any, w: np.ndarray) -> tuple[np.ndarray, ...]:
        """Grid cell ``k`` of the blended table holding ``v`` (clipped to the table: ``vc``), and its ends.

        Branch-free binary search on rows padded to ``P = 2^steps`` (pad: a huge
        OCV, never below ``vc``): ``a`` starts at the row's first point and moves
        up by ``P/2, P/4, ..., 1`` wherever the blended value there is ``<= vc``.
        """
        b = self._ocv
        g, p = b.g, self._pad
        base, diff = self._pad_base, self._pad_diff
        j = jg // g
        start = j * p
        v_lo = base.take(start) + w * diff.take(start)
        v_hi = base.take(start + (g - 1)) + w * diff.take(start + (g - 1))
        vc = np.fmin(np.fmax(v, v_lo), v_hi)  # NaN -> an end (a safe search); NaN comes back from v
        a = np.zeros(v.shape, dtype=np.intp) + start
        step = p >> 1
        while step:
            cand = a + step
            bm = diff.take(cand)
            bm *= w
            bm += base.take(cand)
            np.copyto(a, cand, where=bm <= vc)
            step >>= 1
        k = np.minimum(a - start, g - 2)
        a = k + start
        bk = base.take(a) + w * diff.take(a)
        a += 1
        bk1 = base.take(a) + w * diff.take(a)
        return bk, bk1, k, vc, v_lo, v_hi

    # --------------------------------------------------------------- capacity
    def capacity_ah(self, temperature_c: Any = None) -> np.ndarray | float:
        """The tables' C/20 discharge capacity [Ah] at ``temperature_c``: linear in T, clamped; NaN if unknown."""
        t = self._temperature(temperature_c)
        if self._cap.size == 0:
            return math.nan if np.ndim(t) == 0 else np.full(np.shape(t), math.nan)
        if self._cap.size == 1:
            return float(self._cap[0]) if np.ndim(t) == 0 else np.full(np.shape(t), self._cap[0])
        q = np.interp(t, self._cap_t, self._cap)
        return float(q) if np.ndim(q) == 0 else q

    def relative_capacity(self, temperature_c: Any = None) -> np.ndarray | float:
        """``capacity_ah(T)`` over the capacity of the known table nearest 25 degC (1.0 where unknown)."""
        q = self.capacity_ah(temperature_c)
        if self._cap.size == 0:
            return 1.0 if np.ndim(q) == 0 else np.ones(np.shape(q))
        return q / self._cap_ref


#: What an estimator reads the OCV from: one table (at every temperature), or several by temperature.  Both
#: answer ``ocv``, ``docv_dsoc``, ``soc_from_ocv`` and ``hysteresis``; the surface's take the cells' temperatures.
Ocv = OcvCurve | OcvSurface


class OcvAtTemperatures:
    """``OCV(s, T_n)`` and ``dOCV/dSOC(s, T_n)`` with the cells' temperatures ``T_n`` fixed.

    The queries are arrays whose last axis is the cells (``(..., N)``, ``N`` = the
    temperatures' length).  The temperature location (``j``, ``w``, item 1 of the module
    docstring) is found once here, and :meth:`ocv_slope` locates the SOC on the grid once
    for both tables (they share it).  Values are those of :meth:`OcvSurface.ocv` and
    :meth:`OcvSurface.docv_dsoc` at the same points (same arithmetic); a per-sample SOP
    (core.sop) asks 4 such calls per step, so the per-call overhead matters.
    """

    def __init__(self, surface: OcvSurface | OcvCurve, temperature_c: Any) -> None:
        self.surface = surface
        self._single = surface if isinstance(surface, OcvCurve) else surface._single  # T ignored
        if self._single is not None:
            return
        t = surface._temperature(temperature_c)
        t = np.atleast_1d(np.asarray(t, dtype=np.float64))
        b = surface._ocv
        self._jg, self._w = b.locate_t(t.copy() if t.ndim == 1 else t.ravel())
        self._ends_ocv = b.ends(self._jg, self._w)
        self._ends_slope = surface._slope.ends(self._jg, self._w)

    def ocv(self, soc: Any) -> np.ndarray:
        if self._single is not None:
            return np.asarray(self._single.ocv(soc))
        s = np.asarray(soc, dtype=np.float64)
        b = self.surface._ocv
        a, f, inside = b.locate_s(s, self._jg)
        v = b.at(a, f, self._w)
        if not inside:
            lo, hi = self._ends_ocv
            v += lo * np.minimum(s - b.s0, 0.0) + hi * np.maximum(s - b.s1, 0.0)
        return v

    __call__ = ocv

    def slope(self, soc: Any) -> np.ndarray:
        return self.ocv_slope(soc)[1]

    def ocv_slope(self, soc: Any) -> tuple[np.ndarray, np.ndarray]:
        """(OCV, dOCV/dSOC) at ``soc``, the grid location shared."""
        if self._single is not None:
            return np.asarray(self._single.ocv(soc)), np.asarray(self._single.docv_dsoc(soc))
        s = np.asarray(soc, dtype=np.float64)
        b, bs = self.surface._ocv, self.surface._slope
        a, f, inside = b.locate_s(s, self._jg)
        a1 = a + b.g  # the same grid: the next temperature's row, for both tables
        v = b.at(a, f, self._w, a1)
        d = bs.at(a, f, self._w, a1)
        if not inside:
            lo, hi = self._ends_ocv
            v += lo * np.minimum(s - b.s0, 0.0) + hi * np.maximum(s - b.s1, 0.0)
            lo, hi = self._ends_slope
            d = np.where(s < bs.s0, lo, np.where(s > bs.s1, hi, d))
            d[np.isnan(s)] = math.nan
        return v, d
