"""State of power: the largest constant current (and power) over a horizon, per cell and for the pack.

Model-based SOP (Plett, "High-performance battery-pack power estimation using a
dynamic cell model", IEEE TVT 53(5), 2004), on the identified 2-RC model, current
``I`` positive = charge.  Held constant for ``D`` seconds from now, the ECM
(:mod:`bms_estimator.core.ecm`, exact for constant current) predicts::

    v(D, I) = OCV(s + c I) + b + sum_j [x_j p_j + R_j (1 - p_j) I] + R0 I,
              p_j = exp(-D / tau_j),   c = D / (3600 Q)

where ``x_j`` are the RC voltages now and ``b`` all that the model holds constant
over the horizon (the OCV bias c0, the hysteresis, a slow diffusion voltage).  ``b``
is not modelled separately: the prediction is anchored on the voltage ``v`` measured
now at the current ``i`` (``v = OCV(s) + b + sum_j x_j + R0 i``), so whatever the
model does not explain stays in the prediction as measured::

    v(D, I) = v_base + [OCV(s + c I) - OCV(s)] + R_D I
    v_base  = v - R0 i - sum_j x_j (1 - p_j)          (the voltage after D s at I = 0, OCV aside)
    R_D     = R0 + sum_j R_j (1 - p_j)                 (the D-second resistance)

Limits, magnitudes in A (>= 0).  The discharge limit ``I_dis`` solves
``v(D, -I_dis) = v_min``, the charge limit ``I_chg`` solves ``v(D, I_chg) = v_max``;
``v(D, I)`` is strictly increasing in ``I`` (OCV increasing, ``R_D > 0``), so each
root is unique.  It is found by safeguarded Newton from Plett's linearised root
(``OCV(s + c I) ~ OCV(s) + OCV'(s) c I``, his closed form) with ``newton_steps``
Newton steps on the OCV curve itself, clipped to ``[0, I_cap]``; a final overshoot
``g > 0`` is stepped back by ``g / R_D`` (the slope of ``g`` is at least ``R_D``), so the
predicted voltage at the limit never passes the bound.  Then, as in Plett's method:

    SOC:         I_dis <= (s - soc_min) 3600 Q / D,   I_chg <= (soc_max - s) 3600 Q / D
    design:      I_dis <= I_dis,max d_dis(T),          I_chg <= I_chg,max d_chg(T)

with ``d(T)`` the temperature derating, piecewise linear in the cell temperature
over ``derate_temperatures_c`` (held beyond its ends; 0 = no current).  A cell
already past a voltage bound has a zero limit in that direction.  The power
limits are ``P = |I| v(D, I)`` at the limit currents.

Pack (cells in series, ``n_parallel`` strings of equal cells in parallel): every
cell carries the pack current / n_parallel, so the pack current limit is the
weakest cell's times ``n_parallel``, and the pack power is that current times the
sum of every cell's predicted voltage at it (the series count times the mean).

Model-error margin.  The n-step error of the model (n = D / Ts) is what the ECM does not
explain changing over the horizon: with ``b_k = v_k - OCV(s_k) - R0 i_k - sum_j x_j[k]``
(x_j the RC voltages tracked under the actual current), the prediction made at ``k - n``
for the current that then flowed misses ``v_k`` by ``e_k = b_k - b_{k-n}``.
:class:`~bms_estimator.core.sox.SoxEstimator` keeps ``rms_D`` (an exponential average of
``e^2`` over ``margin_tau_s``) and the limits are solved for the bounds moved inward by
``margin_sigmas * rms_D``, so a cell whose model has been missing by 30 mV over 10 s gets
90 mV of headroom, one whose model fits gets almost none.

Baseline: the HPPC static-resistance method (FreedomCAR/USABC HPPC manual) assumes
a cell at rest and an unchanged OCV::

    I_dis = (OCV(s) - v_min) / R_D,    I_chg = (v_max - OCV(s)) / R_D

with the same design limits and derating.  It ignores the RC voltages already
built up (optimistic after a discharge pulse, pessimistic after a charge) and the
OCV's fall over the horizon.

Everything is vectorised over cells (and horizons); no I/O.  Limits are never
negative and never NaN: a cell whose inputs or model are not finite gets 0.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from typing import Annotated, Callable

import numpy as np
from annotated_types import Ge, Gt

from .bounds import check_bounds

__all__ = ["SopConfig", "SopResult", "derate", "predict_voltage", "sop_limits", "sop_and_pack_limits", "pack_limits"]

OcvFn = Callable[[np.ndarray], np.ndarray]


#: the cell whose ratings the defaults of ``i_discharge_max_a`` / ``i_charge_max_a`` are (an 18650, the LG
#: HG2: 20 A / 6 A); a cell more than 2 times that size or less than half of it is told they are not its own
DEFAULT_RATINGS_CELL_AH = 3.0


def default_ratings_note(capacity_ah: float, defaulted: list[str], where: str) -> str | None:
    """What to say when the defaults of the current ratings (``defaulted``: the names left at them) are not
    the size of a cell of ``capacity_ah`` (None when they are, or none is defaulted)."""
    ratio = float(capacity_ah) / DEFAULT_RATINGS_CELL_AH
    if not defaulted or 0.5 <= ratio <= 2.0:
        return None
    d = SopConfig()
    return (f"{' and '.join(defaulted)} not given: the defaults {d.i_discharge_max_a:g} A / {d.i_charge_max_a:g} A are "
            f"a {DEFAULT_RATINGS_CELL_AH:g} Ah 18650's ratings, {d.i_discharge_max_a / capacity_ah:.2g} C / "
            f"{d.i_charge_max_a / capacity_ah:.2g} C of {where} {capacity_ah:g}: give the cell's")


@dataclass(frozen=True)
class SopConfig:
    """Cell limits and derating (defaults: an 18650 NCA/NMC cell's datasheet figures)."""

    horizons_s: tuple[Annotated[float, Gt(0)], ...] = (2.0, 10.0, 30.0)
    v_min: Annotated[float, Gt(0)] = 2.5  # V, cell discharge cut-off
    v_max: Annotated[float, Gt(0)] = 4.2  # V, cell charge cut-off
    i_discharge_max_a: Annotated[float, Ge(0)] = 20.0  # A, the cell's continuous discharge rating
    i_charge_max_a: Annotated[float, Ge(0)] = 6.0  # A, the cell's charge rating
    soc_min: Annotated[float, Ge(0)] = 0.0
    soc_max: Annotated[float, Gt(0)] = 1.0
    n_parallel: Annotated[int, Ge(1)] = 1  # cells in parallel per series element
    newton_steps: Annotated[int, Ge(0)] = 1  # refinements of the linearised root on the OCV curve
    # model-error margin (core.sox): the limits keep the prediction this many RMS horizon errors
    # of the recent past inside the bounds (0 = none); the RMS is averaged over margin_tau_s
    margin_sigmas: Annotated[float, Ge(0)] = 3.0
    margin_tau_s: Annotated[float, Gt(0)] = 600.0
    # derating: factor on the design current limits, linear between these temperatures (degC)
    derate_temperatures_c: tuple[float, ...] = (-20.0, 0.0, 10.0, 45.0, 60.0)
    discharge_derate: tuple[Annotated[float, Ge(0)], ...] = (0.3, 0.6, 1.0, 1.0, 0.0)
    charge_derate: tuple[Annotated[float, Ge(0)], ...] = (0.0, 0.1, 0.5, 1.0, 0.0)

    def __post_init__(self) -> None:
        if not self.horizons_s or any(not (np.isfinite(h) and h > 0) for h in self.horizons_s):
            raise ValueError(f"horizons_s must be positive numbers of seconds, got {list(self.horizons_s)}")
        if not 0 < self.v_min < self.v_max:
            raise ValueError(f"need 0 < v_min < v_max, got v_min={self.v_min}, v_max={self.v_max}")
        if not 0 <= self.soc_min < self.soc_max <= 1:
            raise ValueError(f"need 0 <= soc_min < soc_max <= 1, got {self.soc_min}, {self.soc_max}")
        t = np.asarray(self.derate_temperatures_c, dtype=float)
        if t.size < 1 or np.any(np.diff(t) <= 0) or not np.all(np.isfinite(t)):
            raise ValueError(f"derate_temperatures_c must be increasing, got {list(self.derate_temperatures_c)}")
        for name in ("discharge_derate", "charge_derate"):
            d = np.asarray(getattr(self, name), dtype=float)
            if d.shape != t.shape or np.any(d < 0) or np.any(d > 1) or not np.all(np.isfinite(d)):
                raise ValueError(f"{name} must have one factor in [0, 1] per derate temperature "
                                 f"({t.size}), got {list(getattr(self, name))}")
        check_bounds(self)


@dataclass(frozen=True)
class SopResult:
    """Limits per horizon and cell, shape ``(n_horizons, n_cells)``; magnitudes, A and W."""

    horizons_s: np.ndarray
    discharge_a: np.ndarray
    charge_a: np.ndarray
    discharge_w: np.ndarray
    charge_w: np.ndarray
    #: the model method's prediction basis per horizon (core.sop_residual learns from it):
    #: v_base (H, N), the identified R_D (H, N), OCV(s) (N,); None for the HPPC method
    basis: tuple | None = None


def derate(temperature_c: np.ndarray, temperatures_c, factors) -> np.ndarray:
    """Derating factor at each temperature (linear, held beyond the ends; NaN -> 0)."""
    t = np.asarray(temperature_c, dtype=float)
    d = np.interp(t, np.asarray(temperatures_c, float), np.asarray(factors, float))
    fin = np.isfinite(t)
    return d if fin.all() else np.where(fin, d, 0.0)


def _horizon_terms(r0, r_rc, tau_rc, x_rc, horizons_s):
    """(R_D, sum_j x_j (1 - p_j)) with shape (H, N): r_rc, tau_rc, x_rc are (N, m)."""
    d = np.asarray(horizons_s, dtype=float)[:, None, None]
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        q = 1.0 - np.exp(-d / tau_rc[None])  # (H, N, m)
    r_d = r0[None] + np.einsum("hnm,nm->hn", q, r_rc)  # (a sum over the short last axis is 4x slower)
    decay = np.einsum("hnm,nm->hn", q, x_rc)
    return r_d, decay


def predict_voltage(current_a, horizon_s, *, voltage_v, current_now_a, soc, capacity_ah, ocv: OcvFn,
                    r0_ohm, r_ohm, tau_s, x_v, dr_ohm=None) -> np.ndarray:
    """``v(D, I)`` of the module docstring for a constant current ``I`` (per cell) over ``D`` s.

    ``dr_ohm`` (per cell, optional): the learnt correction of ``R_D`` (core.sop_residual),
    used as ``max(R_D + dR, R_D / 2)``."""
    r0 = np.asarray(r0_ohm, dtype=float)
    r_d, decay = _horizon_terms(r0, np.asarray(r_ohm, float), np.asarray(tau_s, float), np.asarray(x_v, float),
                                [float(horizon_s)])
    i = np.asarray(current_a, dtype=float)
    s = np.asarray(soc, dtype=float)
    c = float(horizon_s) / (3600.0 * np.asarray(capacity_ah, dtype=float))
    base = np.asarray(voltage_v, float) - r0 * np.asarray(current_now_a, float) - decay[0]
    r_d = r_d[0] if dr_ohm is None else _corrected(r_d[0], np.asarray(dr_ohm, dtype=float))
    return base + (ocv(s + c * i) - ocv(s)) + r_d * i


def _corrected(r_d: np.ndarray, dr: np.ndarray) -> np.ndarray:
    """``max(R_D + dR, R_D / 2)``: the learnt correction, floored so that v(D, I) stays increasing."""
    return np.maximum(r_d + np.where(np.isfinite(dr), dr, 0.0), 0.5 * r_d)


def _solve(g0, r_d, s, c, sign, cap, ocv: OcvFn, ocv_slope, ocv_s, slope_s, steps: int):
    """The root ``I`` in ``[0, cap]`` of ``g(I) = g0 + sign (OCV(s + sign c I) - OCV(s)) + R_D I``, every row at once.

    ``g0 = sign (base - target)``; rows are (direction, horizon) pairs, columns cells.
    ``g`` is increasing with ``g' >= R_D``.  Start: Plett's linearised root
    ``-g(0) / (R_D + c OCV'(s))``; then ``steps`` Newton steps; then, if ``g(I) > 0``
    (an overshoot), ``I -= g(I) / R_D``, which by ``g' >= R_D`` makes ``g(I) <= 0``: the
    limit never lets the predicted voltage past the bound.  The result is the larger of that
    and the largest iterate seen with ``g <= 0`` (every such ``I`` is safe, ``g`` being
    increasing): where the OCV table ends (SOC clamped, slope 0) Newton can overshoot far, and
    with a small ``R_D`` the step back alone fell to 0 A from a full cell (found by Hypothesis).  Last the cap, ``min(I, cap)``
    (``g`` stays <= 0 below a safe ``I``).  The root is found without the cap, so a lower
    cap (a colder cell's derating) can only lower the limit: with the iterates clipped to
    the cap, the unconverged Newton step landed elsewhere and a colder cell's 30 s limit
    came out 0.1 % higher than a warmer one's.  A row already past its bound
    (``g0 >= 0``) gets 0.  ``ocv_slope`` gives (OCV, slope) at one array in one call.
    Runs inside the caller's ``np.errstate`` (a division by a zero R_D gives inf, capped).
    """
    sc = sign * c
    x = -g0 / (r_d + c * slope_s)
    np.maximum(x, 0.0, out=x)
    safe = None  # the largest iterate seen with g <= 0 (None: none yet, i.e. 0)
    for _ in range(steps):
        o, d = ocv_slope(s + sc * x)
        gx = g0 + sign * (o - ocv_s) + r_d * x
        # x >= 0 here, so max(0, x) = x where g <= 0 on the first pass
        safe = np.where(gx <= 0.0, x, 0.0) if safe is None else np.where(gx <= 0.0, np.maximum(safe, x), safe)
        x = x - gx / (r_d + c * d)
        np.maximum(x, 0.0, out=x)
    gx = g0 + sign * (ocv(s + sc * x) - ocv_s) + r_d * x
    x = np.where(gx > 0.0, np.maximum(x - gx / r_d, 0.0), x)
    if safe is not None:
        np.maximum(x, safe, out=x)
    np.minimum(x, cap, out=x)
    return np.where(g0 >= 0.0, 0.0, x)


@lru_cache(maxsize=32)
def _rows(cfg: SopConfig) -> tuple:
    """Constants of the stacked solve: horizons (H,), sign (2H, 1), bound (2H, 1), horizons
    (2H, 1, 1), discharge rows (2H, 1) bool, the derating tables as arrays.  The H discharge
    rows (sign -1, v_min) first, then the H charge rows (+1, v_max)."""
    hz = np.asarray(cfg.horizons_s, dtype=float)
    nh = hz.size
    sign = np.repeat([-1.0, 1.0], nh)[:, None]
    target = np.repeat([cfg.v_min, cfg.v_max], nh)[:, None]
    tables = (np.asarray(cfg.derate_temperatures_c, float), np.asarray(cfg.discharge_derate, float),
              np.asarray(cfg.charge_derate, float))
    return hz, sign, target, np.concatenate([hz, hz])[:, None, None], sign < 0.0, tables


_ROWS_LAST: list = [None]  # (config, _rows(config)) of the last call
_DESIGN_MEMO: list = [None]  # (config, temperatures, limits) of the last call


def _design_limits(t: np.ndarray, cfg: SopConfig, dis, t_tab, dis_tab, chg_tab) -> np.ndarray:
    """(2H, N) derated design current limits; the last call's kept while the temperatures are equal
    (per sample they mostly are: CAN temperatures are quantised and slow)."""
    memo = _DESIGN_MEMO[0]
    if memo is not None and memo[0] is cfg and memo[1].shape == t.shape and np.array_equal(memo[1], t):
        return memo[2]
    design = np.where(dis, cfg.i_discharge_max_a * derate(t, t_tab, dis_tab), cfg.i_charge_max_a * derate(t, t_tab, chg_tab))
    design.setflags(write=False)
    _DESIGN_MEMO[0] = (cfg, t.copy(), design)
    return design


def _per_cell(a, n: int) -> np.ndarray:
    a = np.asarray(a, dtype=float)
    return a if a.shape == (n,) else np.broadcast_to(a, (n,))


def sop_limits(*, voltage_v, current_now_a, soc, capacity_ah, temperature_c, ocv: OcvFn, docv_dsoc: OcvFn,
               r0_ohm, r_ohm, tau_s, x_v, config: SopConfig = SopConfig(), method: str = "model",
               v_margin=None, ocv_slope=None, dr_ohm=None) -> SopResult:
    """Discharge and charge current and power limits per horizon and cell (module docstring).

    ``v_margin`` (V, ``(H, N)`` or broadcastable, >= 0): the model's own error margin; the
    limits keep the predicted voltage within ``[v_min + margin, v_max - margin]``.

    Args are per cell (``(N,)``; ``r_ohm``, ``tau_s``, ``x_v`` are ``(N, m)``); ``ocv`` and
    ``docv_dsoc`` map an SOC array of shape ``(K, N)`` to volts (at each cell's temperature);
    ``ocv_slope`` (optional) gives both at once (e.g.
    :meth:`~bms_estimator.core.ocv_surface.OcvAtTemperatures.ocv_slope`).
    ``method`` = ``"model"`` (Plett's, the default) or ``"hppc"`` (the static-resistance baseline).
    ``dr_ohm`` (``(2H, N)``: discharge horizons, then charge; optional, model method): the learnt
    correction of each row's ``R_D`` (core.sop_residual), used as ``max(R_D + dR, R_D / 2)``.
    """
    return _limits(dr_ohm=dr_ohm, voltage_v=voltage_v, current_now_a=current_now_a, soc=soc, capacity_ah=capacity_ah,
                   temperature_c=temperature_c, ocv=ocv, docv_dsoc=docv_dsoc, r0_ohm=r0_ohm, r_ohm=r_ohm,
                   tau_s=tau_s, x_v=x_v, config=config, method=method, v_margin=v_margin, ocv_slope=ocv_slope)[0]


def sop_and_pack_limits(*, n_parallel: int = 1, valid=None, groups=None,
                        **kwargs) -> tuple[SopResult, dict[str, np.ndarray]]:
    """:func:`sop_limits` (model method) and :func:`pack_limits` of its result in one pass.

    The same numbers as the two calls (tests/core/test_sop_fast.py), with the OCV
    evaluated at the cells' limits (for the power) and at the pack's limit (for the pack
    power) in one stacked call: per sample this is the service's SOP.

    ``groups`` (a :class:`~bms_estimator.core.groups.CellGroups`, optional): the cells are
    independent packs side by side; each pack's limits are then those of its own cells
    (weakest cell, power sum and "no valid cell" per group), ``(H, G)`` arrays, each column
    bit for bit the pack's alone (tests/core/test_sox_groups.py).
    """
    return _limits(pack=(int(n_parallel), valid, groups), **kwargs)


def _limits(*, voltage_v, current_now_a, soc, capacity_ah, temperature_c, ocv: OcvFn, docv_dsoc: OcvFn,
            r0_ohm, r_ohm, tau_s, x_v, config: SopConfig = SopConfig(), method: str = "model",
            v_margin=None, ocv_slope=None, pack=None, dr_ohm=None, ocv_slope_s=None):
    """The limits of all horizons and both directions as one ``(2H, N)`` solve (rows: :func:`_rows`).

    ``ocv_slope_s``: ``ocv_slope(soc)``, when the caller has it already."""
    if method not in ("model", "hppc"):
        raise ValueError(f"method must be 'model' or 'hppc', got {method!r}")
    if pack is not None and method != "model":
        raise ValueError("pack limits are the model method's")
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):  # one context for the whole solve
        return _limits_body(voltage_v, current_now_a, soc, capacity_ah, temperature_c, ocv, docv_dsoc, r0_ohm, r_ohm,
                            tau_s, x_v, config, method, v_margin, ocv_slope, pack, dr_ohm, ocv_slope_s)


def _limits_body(voltage_v, current_now_a, soc, capacity_ah, temperature_c, ocv, docv_dsoc, r0_ohm, r_ohm, tau_s,
                 x_v, config, method, v_margin, ocv_slope, pack, dr_ohm, ocv_slope_s=None):
    cfg = config
    v = np.asarray(voltage_v, dtype=float)
    n = v.shape[0]
    i_now, s, q, r0 = _per_cell(current_now_a, n), _per_cell(soc, n), _per_cell(capacity_ah, n), _per_cell(r0_ohm, n)
    r_rc = np.asarray(r_ohm, float).reshape(n, -1)
    tau_rc = np.asarray(tau_s, float).reshape(n, -1)
    x_rc = np.asarray(x_v, float)
    if x_rc.shape != r_rc.shape:
        x_rc = np.broadcast_to(x_rc, r_rc.shape)
    m_rc = r_rc.shape[1]
    # finite (a NaN or inf anywhere makes the sum non-finite) and positive; the per-cell test of
    # the RC columns (a reduction over the short axis) only when some entry fails
    tot = v + i_now
    tot += s
    tot += q
    tot += r0
    for j in range(m_rc):  # whole columns: cheaper than a reduction over the short pair axis
        tot += r_rc[:, j]
        tot += tau_rc[:, j]
        tot += x_rc[:, j]
    ok = np.isfinite(tot)
    ok &= np.minimum(q, r0) > 0
    if not ((r_rc >= 0).all() and (tau_rc > 0).all()):
        ok &= ((r_rc >= 0) & (tau_rc > 0)).all(axis=1)
    all_ok = bool(ok.all())
    if not all_ok:  # a cell that cannot be predicted gets no current: harmless numbers, zeroed at the end
        v, s, q, r0, i_now = (np.where(ok, a, d) for a, d in ((v, cfg.v_min), (s, 0.0), (q, 1.0), (r0, 1.0),
                                                               (i_now, 0.0)))
        okc = ok[:, None]
        r_rc, tau_rc, x_rc = np.where(okc, r_rc, 0.0), np.where(okc, tau_rc, 1.0), np.where(okc, x_rc, 0.0)
        ocv_slope_s = None  # evaluated at the replaced SOC below
    memo = _ROWS_LAST[0]  # the last config's rows by identity: hashing the frozen config costs more
    if memo is None or memo[0] is not cfg:
        memo = _ROWS_LAST[0] = (cfg, _rows(cfg))
    hz, sign, target, hz3, dis, (t_tab, dis_tab, chg_tab) = memo[1]
    nh = hz.size
    if ocv_slope is None:
        def ocv_slope(z):
            return ocv(z), docv_dsoc(z)
    # per RC pair j (a Python loop over the 2 pairs: whole-row operations beat a reduction over
    # the short pair axis): q_j = 1 - p_j per row, R_D and the RC voltages' change over D
    neg_hz2 = -hz3[:, :, 0]
    r_d, decay = r0, 0.0
    for j in range(m_rc):
        qj = np.exp(neg_hz2 / tau_rc[:, j])  # (2H, N): p_j, then q_j = 1 - p_j
        np.subtract(1.0, qj, out=qj)
        r_d = r_d + r_rc[:, j] * qj
        decay = decay + x_rc[:, j] * qj
    c = hz3[:, :, 0] / (3600.0 * q)  # (2H, N): SOC per A over the horizon
    # (N,): one evaluation serves every row (given by the caller when it has it)
    ocv_s, slope_s = ocv_slope(s) if ocv_slope_s is None else ocv_slope_s
    ocv_s, slope_s = np.asarray(ocv_s, dtype=float), np.asarray(slope_s, dtype=float)
    basis = None
    if method == "model":
        base = (v - r0 * i_now) - decay
        c_use = c
        basis = (base[:nh], r_d[:nh], ocv_s)  # the identified model's, before any correction
        if dr_ohm is not None:
            r_d = _corrected(r_d, np.asarray(dr_ohm, dtype=float))
    else:
        base = np.broadcast_to(ocv_s, c.shape)  # at rest, and the OCV held
        c_use = np.zeros_like(c)
    design = _design_limits(_per_cell(temperature_c, n), cfg, dis, t_tab, dis_tab, chg_tab)
    room = np.where(dis, s - cfg.soc_min, cfg.soc_max - s)
    np.maximum(room, 0.0, out=room)
    room /= c
    cap = np.minimum(design, room)
    if v_margin is not None:
        m = np.asarray(v_margin, dtype=float)
        m = np.where(m > 0.0, m, 0.0)  # NaN -> 0
        if m.shape != (nh, n):
            m = np.broadcast_to(m, (nh, n))
        target = target - sign * np.concatenate([m, m])  # moved inward
    g0 = sign * (base - target)
    x = _solve(g0, r_d, s, c_use, sign, cap, ocv, ocv_slope, ocv_s, slope_s, cfg.newton_steps)
    lim = x if all_ok else np.where(ok, x, 0.0)
    fin = np.isfinite(lim)
    if fin.all():  # _solve's result is >= 0 or NaN
        np.maximum(lim, 0.0, out=lim)
    else:
        lim = np.where(fin, np.maximum(lim, 0.0), 0.0)
    sc = sign * c_use
    # the predicted voltage at each limit (a zero limit: at zero current) and, for the pack,
    # every cell's at the weakest cell's limit: one OCV call on both stacked
    if pack is not None:
        n_par, valid, groups = pack
        use = np.ones(n, dtype=bool) if valid is None else np.asarray(valid, dtype=bool)
        use_all = bool(use.all())
        if groups is not None:  # per pack: its weakest valid cell, 0 where it has none
            i_pack = groups.reduce(np.min, lim if use_all else np.where(use, lim, np.inf))
            if not use_all:
                i_pack = np.where(groups.reduce(np.any, use), i_pack, 0.0)
        elif not use_all and not use.any():
            i_pack = np.zeros(2 * nh)
        else:  # the weakest cell's limit (a cell that cannot be predicted has 0)
            i_pack = lim.min(axis=1) if use_all else lim[:, use].min(axis=1)
        if not all_ok:
            use = use & ok
            use_all = False
        # (2H, 1) signed cell current; per pack (2H, N), each cell at its own pack's
        i2 = sign * (i_pack[:, None] if groups is None else i_pack[:, groups.of])
        z = np.empty((4 * nh, n))
        np.multiply(sc, lim, out=z[:2 * nh])
        z[:2 * nh] += s
        np.multiply(c_use, i2, out=z[2 * nh:])
        z[2 * nh:] += s
        o = ocv(z)
        o_lim, o_pack = o[:2 * nh], o[2 * nh:]
    else:
        o_lim = ocv(s + sc * lim)
    gl = o_lim - ocv_s
    gl *= sign
    gl += g0
    gl += r_d * lim
    np.minimum(gl, 0.0, out=gl)
    gl *= sign
    v_at = target + gl
    v_at = np.where(lim > 0.0, v_at, base)
    p = lim * v_at
    np.maximum(p, 0.0, out=p)  # NaN stays NaN
    if not np.isfinite(p).all():
        p = np.where(np.isfinite(v_at), p, 0.0)
    res = SopResult(hz, lim[:nh], lim[nh:], p[:nh], p[nh:], basis)
    if pack is None:
        return res, None
    v_pack = o_pack - ocv_s
    v_pack += base
    v_pack += r_d * i2
    if groups is not None:  # each pack's sum as its own (module docstring of core.groups)
        p_pack = groups.reduce(np.sum, np.where(use & np.isfinite(v_pack), v_pack, 0.0))
    else:
        p_pack = v_pack.sum(axis=1)
        if not (use_all and np.isfinite(p_pack).all()):
            p_pack = np.sum(np.where(use & np.isfinite(v_pack), v_pack, 0.0), axis=1)
    p_pack = i_pack * n_par * p_pack
    p_pack = np.maximum(p_pack, 0.0)
    return res, {"discharge_a": i_pack[:nh] * n_par, "charge_a": i_pack[nh:] * n_par,
                 "discharge_w": p_pack[:nh], "charge_w": p_pack[nh:]}


def pack_limits(result: SopResult, *, voltage_v, current_now_a, soc, capacity_ah, ocv: OcvFn,
                r0_ohm, r_ohm, tau_s, x_v, n_parallel: int = 1, valid=None) -> dict[str, np.ndarray]:
    """Pack current and power limits per horizon (module docstring), shape ``(H,)``.

    The pack current is the weakest cell's limit times ``n_parallel``; the power is that
    current times the sum of every cell's predicted voltage at its share of it.
    ``valid`` (N,) bool restricts the weakest-cell search (all cells when None); no valid
    cell gives 0.
    """
    n = result.discharge_a.shape[1]
    nh = len(result.horizons_s)
    use = np.ones(n, dtype=bool) if valid is None else np.asarray(valid, dtype=bool)
    if not use.any():
        z = np.zeros(nh)
        return {"discharge_a": z, "charge_a": z.copy(), "discharge_w": z.copy(), "charge_w": z.copy()}
    i_dis = np.min(result.discharge_a[:, use], axis=1)  # (H,) per cell of the string
    i_chg = np.min(result.charge_a[:, use], axis=1)
    r0 = np.asarray(r0_ohm, dtype=float)
    r_d, decay = _horizon_terms(r0, np.asarray(r_ohm, float), np.asarray(tau_s, float), np.asarray(x_v, float),
                                result.horizons_s)
    base = (np.asarray(voltage_v, float) - r0 * np.asarray(current_now_a, float))[None] - decay
    s = np.asarray(soc, dtype=float)
    c = result.horizons_s[:, None] / (3600.0 * np.asarray(capacity_ah, dtype=float)[None])
    i2 = np.concatenate([-i_dis, i_chg])[:, None]  # (2H, 1) signed cell current
    base2, r_d2, c2 = np.concatenate([base, base]), np.concatenate([r_d, r_d]), np.concatenate([c, c])
    s2 = np.broadcast_to(s, base2.shape)
    with np.errstate(invalid="ignore"):
        v = base2 + ocv(s2 + c2 * i2) - ocv(s2) + r_d2 * i2
        p = np.abs(i2[:, 0]) * n_parallel * np.sum(np.where(use & np.isfinite(v), v, 0.0), axis=1)
    p = np.maximum(p, 0.0)
    return {"discharge_a": i_dis * n_parallel, "charge_a": i_chg * n_parallel, "discharge_w": p[:nh],
            "charge_w": p[nh:]}
