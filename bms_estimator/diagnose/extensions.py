"""The baseline 2-RC model and one fittable extension per candidate cause (batch, offline).

Every model here has the form (current ``i`` positive = charge, 1 s period means)::

    v[k] = OCV(soc_theta[k]) + X_theta[k, :] @ beta + e[k]

with a handful of *nonlinear* parameters ``theta`` (time constants, a hysteresis
rate, activation energies, a current scale, a capacity, a current offset) and
*linear* ones ``beta`` (resistances, hysteresis amplitudes, ``c0``).  For fixed
``theta`` every column of ``X`` is a linear filter of the measured current (an RC
branch is ``R_j`` times the unit-gain, step-mean ZOH response of ``i`` with time
constant ``tau_j``, exactly what :func:`~bms_estimator.core.ecm.simulate_ecm` with
``output="mean"`` computes), so ``beta`` follows by linear least squares and the
fit is an **output-error** (simulation-error) fit, not an equation-error one: the
model is driven by the current only, never by the measured voltage.  ``theta`` is
found by variable projection: a coarse grid over the extension's own nonlinear
parameters (the time constants held at the baseline's), then a bounded
Levenberg-Marquardt over all of ``theta`` with ``beta`` eliminated.

Baseline (``none``, the paper's model): ``X = [i, rc(i, tau1), rc(i, tau2), 1]``,
``beta = (R0, R1, R2, c0)``, constant parameters, ``tau1 in [1, 100] s``,
``tau2 in [10, 500] s`` (the online identifier's admissible range,
:class:`~bms_estimator.core.identifier.IdentifierConfig`), warm-started from the
LIF identification's median parameters (see :mod:`.decide`).  The online LIF
estimator tracks slowly varying parameters; the batch baseline holds them
constant on purpose: a constant model is what each extension is measured
against, so an effect the LIF would silently absorb by drifting its parameters
(temperature, SOC dependence) shows up in the residual.

Extensions are *features* that compose (:class:`Model` takes any set of them, so
two effects can be fitted jointly); ``extra`` is the number of parameters a
feature adds to the baseline's six:

``hysteresis`` (4)
    Plett's one-state hysteresis with instantaneous term
    (:mod:`bms_estimator.core.hysteresis`): ``+ M h + M0 s``, ``h`` relaxing with
    throughput at rate ``gamma`` per unit SOC towards the current's sign from
    ``h0`` (fitted in [-1, 1], starting from +1 for a file that starts full: it
    started after a charge), ``s`` the held sign of the current.
``temperature`` (2)
    Arrhenius resistances driven by the ``temperature_c`` column:
    ``R0(T) = R0 exp(Ea0/Rg (1/T - 1/Tref))`` and the RC branches with ``Ea_rc``
    (ohmic conduction and charge transfer have different activation energies),
    ``Tref`` the mean temperature of the data.  The RC branches keep their
    capacitance, so their time constants scale with their resistances
    (:func:`rc_mean_varying`, exact ZOH per step).
``soc_dependence`` (3 (K-1))
    ``R0``, ``R1``, ``R2`` piecewise linear in SOC on K knots (hat functions
    ``B_m``): ``sum_m (R0_m B_m i + R1_m rc(B_m i) + R2_m rc2(B_m i))``.  Knots at
    the ends of the SOC range the data cover and at 0.1, 0.25, 0.5, 0.75 inside
    it (resistances of Li-ion cells change fastest towards empty), less those
    that would leave less than 12 % of the charge throughput between two knots
    (a resistance is learnt where current flows; a knot whose support fits in
    one held-out block would have no data in that fold's fit).
``current_nonlinearity`` (2)
    Butler-Volmer-like kinetic overpotential in series with the ohmic R0:
    ``R0 i + K I_s asinh(i / I_s)``: the resistance is ``R0 + K`` for small
    currents and falls towards ``R0`` as ``|i|`` grows past ``I_s``.
    (Fitted together with ``temperature``, the term follows R0's Arrhenius factor.)
``direction_asymmetry`` (1)
    ``R0_charge max(i, 0) + R0_discharge min(i, 0)``.
``slow_diffusion`` (2)
    A third RC branch ``R3 rc(i, tau3)``, ``tau3 in [100, 20000] s``: the slow tail
    of solid-state diffusion (a finite-length Warburg element is a series of RC
    branches whose slowest term dominates at drive-cycle time scales).
``current_offset`` (1)
    The current sensor reads ``i + b``: the true SOC is
    ``soc - b t / (3600 Q)``, so ``v = OCV(soc - b t/(3600 Q)) + ...``.
``capacity_error`` (1)
    The true capacity is ``rho Q``: ``soc = soc0 + q(t) / (rho Q)``.

Every feature nests the baseline (``M = 0``, ``Ea = 0``, equal knots,
``K = 0``, ``R0_c = R0_d``, ``R3 = 0``, ``b = 0``, ``rho = 1``).

Size of a feature in a fitted model (:meth:`Model.components`): the voltage the
feature adds alone to the fitted model's 2-RC part (the other features neutral),
less what a re-fitted 2-RC baseline absorbs of it (R0, R1, R2, c0 and both time
constants) - the same definition the generator sizes its hidden effects with.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field

import numpy as np
from scipy.linalg import solve_triangular
from scipy.optimize import lsq_linear
from scipy.signal import lfilter

from ..core.arrhenius import KELVIN, R_GAS
from ..core.hysteresis import hysteresis_trajectory
from ..core.ocv import OcvCurve

__all__ = [
    "Series",
    "Fit",
    "Feature",
    "Model",
    "FEATURES",
    "CAUSES",
    "BASELINE",
    "rc_mean",
    "fit_model",
    "predict",
    "unabsorbed",
]

TAU1_BOUNDS = (1.0, 100.0)
TAU2_BOUNDS = (10.0, 500.0)
TAU3_BOUNDS = (100.0, 20000.0)


@dataclass
class Series:
    """One recording as the models see it: 1 s means, SOC path by coulomb counting.

    ``charge_ah[k]`` is the counted charge at the middle of sample ``k`` (so
    ``soc = soc0 + charge_ah / Q`` is :func:`~bms_estimator.analysis.reference_soc`),
    ``t_mid_s`` the elapsed time there.
    """

    current_a: np.ndarray
    voltage_v: np.ndarray
    ocv: OcvCurve
    capacity_ah: float
    soc0: float = 1.0
    dt_s: float = 1.0
    temperature_c: np.ndarray | None = None
    #: True where the file logged the sample, False in a logging gap the loader filled (current held, voltage
    #: interpolated: :attr:`CellRecording.filled <bms_estimator.data.CellRecording.filled>`); None: all logged
    logged: np.ndarray | None = None
    charge_ah: np.ndarray = field(init=False)
    soc: np.ndarray = field(init=False)
    t_mid_s: np.ndarray = field(init=False)
    _rc_cache: dict = field(init=False, default_factory=dict, repr=False, compare=False)

    def __post_init__(self) -> None:
        self.current_a = np.asarray(self.current_a, dtype=float)
        self.voltage_v = np.asarray(self.voltage_v, dtype=float)
        if self.current_a.shape != self.voltage_v.shape or self.current_a.ndim != 1:
            raise ValueError("current and voltage must be 1-D arrays of equal length")
        if not (np.all(np.isfinite(self.current_a)) and np.all(np.isfinite(self.voltage_v))):
            raise ValueError("current and voltage must be finite")
        if self.temperature_c is not None:
            t = np.asarray(self.temperature_c, dtype=float)
            self.temperature_c = t if t.shape == self.current_a.shape and np.all(np.isfinite(t)) else None
        if self.logged is not None:
            self.logged = np.asarray(self.logged, dtype=bool)
            if self.logged.shape != self.current_a.shape:
                raise ValueError("logged must have one flag per sample")
        q = np.cumsum(self.current_a) * (self.dt_s / 3600.0)
        self.charge_ah = q - self.current_a * (0.5 * self.dt_s / 3600.0)
        self.soc = self.soc0 + self.charge_ah / self.capacity_ah
        self.t_mid_s = (np.arange(self.current_a.size) + 0.5) * self.dt_s

    def __len__(self) -> int:
        return int(self.current_a.size)

    def rc_current(self, tau: float) -> np.ndarray:
        """``rc_mean(current, tau)``, cached: a fit evaluates the same time constants many times."""
        key = float(tau)
        out = self._rc_cache.get(key)
        if out is None:
            if len(self._rc_cache) >= 64:
                self._rc_cache.pop(next(iter(self._rc_cache)))
            out = self._rc_cache[key] = rc_mean(self.current_a, key, self.dt_s)
        return out

    @property
    def duration_s(self) -> float:
        return len(self) * self.dt_s

    @classmethod
    def from_recording(cls, rec, ocv: OcvCurve, capacity_ah: float, initial_soc: float = 1.0) -> "Series":
        """From a :class:`~bms_estimator.data.CellRecording` (or anything with the same arrays)."""
        filled = getattr(rec, "filled", None)
        return cls(rec.current_a, rec.voltage_v, ocv, float(capacity_ah), float(initial_soc), float(rec.dt_s),
                   getattr(rec, "temperature_c", None), None if filled is None else ~np.asarray(filled, dtype=bool))


def rc_mean(u: np.ndarray, tau: float, dt_s: float = 1.0) -> np.ndarray:
    """Unit-gain RC branch driven by ``u`` (columns), from rest, step-mean output.

    ``x[k+1] = p x[k] + (1 - p) u[k]``, ``p = exp(-dt/tau)``;
    ``mean[k] = g x[k] + (1 - g) u[k]``, ``g = tau (1 - p) / dt``.
    ``R rc_mean(i, tau)`` is the branch voltage of :func:`simulate_ecm` with ``output="mean"``.
    """
    p = float(np.exp(-dt_s / tau))
    g = tau * (1.0 - p) / dt_s
    x = lfilter([0.0, 1.0 - p], [1.0, -p], u, axis=0)
    return g * x + (1.0 - g) * u


def _ltv_first_order(logp: np.ndarray, drive: np.ndarray) -> np.ndarray:
    """``x[0] = 0``, ``x[k+1] = p[k] x[k] + drive[k]`` with per-sample poles ``p = exp(logp)``, vectorised.

    ``x[k] = e^{L_k} sum_{l<k} e^{-L_{l+1}} drive[l]`` with ``L_k = sum_{l<k} logp[l]``,
    evaluated in blocks over which ``L`` falls by at most ~300 so nothing overflows.
    ``drive`` may have trailing columns (one filter per column, same poles).
    """
    n = logp.size
    cum = np.concatenate([[0.0], np.cumsum(logp)])
    x = np.empty(drive.shape)
    state = np.zeros(drive.shape[1:])
    start = 0
    while start < n:
        stop = int(np.searchsorted(-(cum[start:n + 1] - cum[start]), 300.0, side="right")) + start
        stop = min(max(stop, start + 1), n)
        rel = cum[start:stop + 1] - cum[start]
        w = np.exp(-rel[1:])
        acc = np.cumsum((w * drive[start:stop].T).T, axis=0)
        acc = np.concatenate([np.zeros((1,) + drive.shape[1:]), acc], axis=0)
        decay = np.exp(rel[:-1])
        x[start:stop] = (decay * (state + acc[:-1]).T).T
        state = np.exp(rel[-1]) * (state + acc[-1])
        start = stop
    return x


def rc_mean_varying(u: np.ndarray, tau_ref: float, factor: np.ndarray, dt_s: float = 1.0) -> np.ndarray:
    """Unit-reference RC branch whose R *and* tau scale with ``factor`` per sample (C constant), step mean.

    The branch voltage of ``R_ref factor[k]`` in parallel with ``C = tau_ref / R_ref``
    driven by ``u`` is ``R_ref`` times this: ``x[k+1] = p_k x[k] + factor_k (1 - p_k) u[k]``,
    ``p_k = exp(-dt / (tau_ref factor_k))``, ``mean_k = g_k x_k + factor_k u_k (1 - g_k)``,
    ``g_k = tau_k (1 - p_k) / dt`` - exact ZOH per step, as :func:`simulate_ecm` with
    per-sample parameters.
    """
    tau = tau_ref * factor
    logp = -dt_s / tau
    p = np.exp(logp)
    g = tau * (1.0 - p) / dt_s
    fu = (factor * (1.0 - p) * u.T).T
    x = _ltv_first_order(logp, fu)
    return (g * x.T).T + ((factor * (1.0 - g)) * u.T).T


@dataclass(frozen=True)
class Nl:
    """A nonlinear parameter: bounds, log or linear search space, grid for the coarse stage."""

    name: str
    lo: float
    hi: float
    log: bool = True
    grid: tuple[float, ...] = ()

    def to_x(self, v: float) -> float:
        v = min(max(v, self.lo), self.hi)
        return float(np.log(v)) if self.log else float(v)

    def from_x(self, x: float) -> float:
        return float(np.exp(x)) if self.log else float(x)

    def bounds_x(self) -> tuple[float, float]:
        return (float(np.log(self.lo)), float(np.log(self.hi))) if self.log else (self.lo, self.hi)

    def centre(self) -> float:
        if self.grid:
            return float(np.exp(np.mean(np.log(self.grid)))) if self.log else float(np.median(self.grid))
        return float(np.sqrt(self.lo * self.hi)) if self.log else 0.5 * (self.lo + self.hi)


TAU_PARAMS = (
    Nl("tau1_s", *TAU1_BOUNDS, grid=(3.0, 10.0, 30.0)),
    Nl("tau2_s", *TAU2_BOUNDS, grid=(60.0, 150.0, 400.0)),
)


# --------------------------------------------------------------------------- features


class Feature:
    """One candidate cause as a model feature (hooks of :meth:`Model.design`; defaults do nothing)."""

    name = ""
    extra = 0
    description = ""
    #: linear parameters the feature owns (prefixes), for its voltage component
    owns: tuple[str, ...] = ()

    def setup(self, s: Series) -> dict:
        return {}

    def nonlinear(self, s: Series, cfg: dict) -> tuple[Nl, ...]:
        return ()

    def applicable(self, s: Series) -> str | None:
        return None

    def neutral_theta(self) -> dict[str, float]:
        """Nonlinear parameters that switch the feature off (beyond zeroing what it owns)."""
        return {}

    def neutral_beta(self, beta: dict[str, float], cfg: dict) -> dict[str, float]:
        return {k: (0.0 if k.startswith(self.owns) else v) for k, v in beta.items()} if self.owns else dict(beta)


class Hysteresis(Feature):
    name = "hysteresis"
    extra = 4
    description = "one-state OCV hysteresis (Plett) with instantaneous term"
    owns = ("m_v", "m0_v")

    def setup(self, s):
        # the state at the file's start is a prior from its history: a file that starts full
        # started after a charge (h0 = +1), one that starts empty after a discharge (-1)
        return {"h0_prior": 1.0 if s.soc0 >= 0.9 else (-1.0 if s.soc0 <= 0.1 else 0.0)}

    def nonlinear(self, s, cfg):
        return (Nl("gamma", 1.0, 3000.0, grid=(3.0, 10.0, 30.0, 100.0, 300.0, 1000.0)),
                Nl("h0", -1.0, 1.0, log=False, grid=(cfg.get("h0_prior", 0.0),)))


class Temperature(Feature):
    name = "temperature"
    extra = 2
    description = "Arrhenius resistances following temperature_c"

    def setup(self, s):
        return {"t_ref_c": float(np.mean(s.temperature_c))}

    def nonlinear(self, s, cfg):
        g = (0.0, 20.0, 40.0, 80.0)
        return (Nl("ea0_kj_mol", 0.0, 150.0, log=False, grid=g), Nl("ea_rc_kj_mol", 0.0, 150.0, log=False, grid=g))

    def applicable(self, s):
        if s.temperature_c is None:
            return "no temperature_c column"
        if np.ptp(s.temperature_c) < 0.5:
            return "temperature varies by less than 0.5 K"
        return None

    def neutral_theta(self):
        return {"ea0_kj_mol": 0.0, "ea_rc_kj_mol": 0.0}

    @staticmethod
    def factor(temp_c: np.ndarray, t_ref_c: float, ea_kj_mol: float) -> np.ndarray:
        x = ea_kj_mol * 1e3 / R_GAS * (1.0 / (temp_c + KELVIN) - 1.0 / (t_ref_c + KELVIN))
        return np.exp(np.clip(x, -50.0, 50.0))


class SocDependence(Feature):
    name = "soc_dependence"
    extra = 12  # with the usual 5 knots; the count for the data is cfg["extra"]
    description = "R0, R1, R2 piecewise linear in SOC"
    inner_knots = (0.1, 0.25, 0.5, 0.75)

    min_segment = 0.12  # share of the charge throughput between two knots (no held-out block holds all of one)
    #: a file whose counted SOC spans less than this holds no SOC dependence to tell from a drift in time: on
    #: 10 min of the LG la92 drive (SOC 0.93..1.00) it was named with a 76 % gain, temperature close behind
    min_span = 0.2

    def applicable(self, s):
        lo, hi = float(np.quantile(s.soc, 0.002)), float(np.quantile(s.soc, 0.998))
        if hi - lo < self.min_span:
            return (f"the counted SOC spans only {lo:.2f}..{hi:.2f} (under {self.min_span:g}): a resistance's SOC "
                    "dependence cannot be told from its drift in time there")
        return None

    def setup(self, s):
        lo, hi = float(np.quantile(s.soc, 0.002)), float(np.quantile(s.soc, 0.998))
        span = hi - lo
        knots = [lo] + [k for k in self.inner_knots if lo + 0.05 * span < k < hi - 0.05 * span] + [hi]
        # drop inner knots until every segment holds enough throughput
        w = np.abs(s.current_a)  # what a resistance is learnt from: samples with current
        w = w / max(float(w.sum()), 1e-12)
        while len(knots) > 2:
            frac = [float(w[(s.soc >= a) & (s.soc < b)].sum()) for a, b in zip(knots[:-1], knots[1:])]
            j = int(np.argmin(frac))
            if frac[j] >= self.min_segment:
                break
            # merge the smallest segment with its smaller neighbour: remove the knot between them
            if j == 0:
                knots.pop(1)
            elif j == len(frac) - 1:
                knots.pop(-2)
            else:
                knots.pop(j if frac[j - 1] < frac[j + 1] else j + 1)
        return {"knots": np.array(knots)}

    @staticmethod
    def basis(soc: np.ndarray, knots: np.ndarray) -> np.ndarray:
        """Hat functions on the knots (rows sum to 1; constant beyond the end knots)."""
        eye = np.eye(knots.size)
        return np.column_stack([np.interp(soc, knots, eye[m]) for m in range(knots.size)])

    def neutral_beta(self, beta, cfg):
        out = dict(beta)
        groups: dict[str, list[str]] = {}
        for k in beta:
            if "@" in k:
                groups.setdefault(k.split("@")[0], []).append(k)
        for keys in groups.values():
            m = float(np.mean([beta[k] for k in keys]))
            for k in keys:
                out[k] = m
        return out


class CurrentNonlinearity(Feature):
    name = "current_nonlinearity"
    extra = 2
    description = "Butler-Volmer-like kinetic overpotential K I_s asinh(i/I_s) beside R0"
    owns = ("k_nl_ohm",)

    def nonlinear(self, s, cfg):
        scale = max(float(np.percentile(np.abs(s.current_a), 99)), 1e-3)
        grid = tuple(scale * f for f in (0.05, 0.15, 0.4, 1.0, 2.5))
        return (Nl("i_s_a", 0.01 * scale, 100.0 * scale, grid=grid),)


class DirectionAsymmetry(Feature):
    name = "direction_asymmetry"
    extra = 1
    description = "R0 differs between charge and discharge"

    def applicable(self, s):
        i = s.current_a
        if np.sum(i > 0.01 * s.capacity_ah) < 30 or np.sum(i < -0.01 * s.capacity_ah) < 30:
            return "the data do not hold both charge and discharge"
        return None

    def neutral_beta(self, beta, cfg):
        out = dict(beta)
        for k in beta:
            if k.startswith("r0_charge"):
                kd = k.replace("r0_charge", "r0_discharge")
                m = 0.5 * (beta[k] + beta[kd])
                out[k] = out[kd] = m
        return out


class SlowDiffusion(Feature):
    name = "slow_diffusion"
    extra = 2
    description = "third, slow RC branch (diffusion)"
    owns = ("r3_ohm",)

    def nonlinear(self, s, cfg):
        return (Nl("tau3_s", *TAU3_BOUNDS, grid=(800.0, 1600.0, 3200.0, 6400.0, 12800.0)),)


class CurrentOffset(Feature):
    name = "current_offset"
    extra = 1
    description = "constant current-sensor offset b (reads i + b)"

    def nonlinear(self, s, cfg):
        q = s.capacity_ah
        return (Nl("offset_a", -0.2 * q, 0.2 * q, log=False,
                   grid=tuple(q * f for f in (-0.03, -0.01, -0.003, 0.0, 0.003, 0.01, 0.03))),)

    def neutral_theta(self):
        return {"offset_a": 0.0}


#: the search range of the capacity_error extension's true / stated capacity
CAPACITY_RATIO_BOUNDS = (0.5, 2.0)


class CapacityError(Feature):
    name = "capacity_error"
    extra = 1
    description = "true capacity differs from the stated one"

    def nonlinear(self, s, cfg):
        return (Nl("capacity_ratio", *CAPACITY_RATIO_BOUNDS, grid=(0.75, 0.85, 0.93, 1.0, 1.07, 1.18, 1.35)),)

    def neutral_theta(self):
        return {"capacity_ratio": 1.0}


FEATURES: dict[str, Feature] = {
    f.name: f
    for f in (
        Hysteresis(), Temperature(), SocDependence(), CurrentNonlinearity(), DirectionAsymmetry(),
        SlowDiffusion(), CurrentOffset(), CapacityError(),
    )
}
CAUSES = tuple(FEATURES)


# --------------------------------------------------------------------------- models


class Model:
    """The baseline plus a set of features (``Model()`` is the baseline, ``Model("hysteresis")`` one extension)."""

    def __init__(self, *features: str):
        for f in features:
            if f not in FEATURES:
                raise ValueError(f"unknown cause {f!r}; choose from {', '.join(CAUSES)}")
        self.features = tuple(f for f in CAUSES if f in features)  # canonical order
        self.name = "+".join(self.features) if self.features else "none"

    def __repr__(self) -> str:
        return f"Model({self.name})"

    def has(self, f: str) -> bool:
        return f in self.features

    def setup(self, s: Series) -> dict:
        cfg: dict = {}
        for f in self.features:
            cfg.update(FEATURES[f].setup(s))
        return cfg

    def nonlinear(self, s: Series, cfg: dict) -> tuple[Nl, ...]:
        out = list(TAU_PARAMS)
        for f in self.features:
            out += FEATURES[f].nonlinear(s, cfg)
        return tuple(out)

    def applicable(self, s: Series) -> str | None:
        for f in self.features:
            why = FEATURES[f].applicable(s)
            if why:
                return f"{f}: {why}"
        return None

    # -- the model ---------------------------------------------------------------
    def soc_path(self, s: Series, th: dict[str, float]) -> np.ndarray:
        if not (self.has("current_offset") or self.has("capacity_error")):
            return s.soc
        q = s.charge_ah
        if self.has("current_offset"):
            q = q - th["offset_a"] * s.t_mid_s / 3600.0
        cap = s.capacity_ah * (th["capacity_ratio"] if self.has("capacity_error") else 1.0)
        return s.soc0 + q / cap

    def design(self, s: Series, th: dict[str, float], cfg: dict) -> tuple[np.ndarray, np.ndarray, list[str]]:
        """``(y, XT, names)``: ``y = v - OCV(soc_theta)`` and the model ``y = XT.T @ beta``.

        The design matrix is returned transposed, one row per parameter (C order):
        stacking rows is cheap and every product the fit needs is a row product.
        """
        i = s.current_a
        dt = s.dt_s
        u0 = i
        f0 = None  # per-sample factor of R0 (temperature), None = constant
        f_rc = None  # per-sample factor of the RC branches' R (and tau: C stays put), None = constant

        def branch(u: np.ndarray, tau: float) -> np.ndarray:
            return rc_mean(u, tau, dt) if f_rc is None else rc_mean_varying(u, tau, f_rc, dt)

        if self.has("temperature"):
            t_ref = cfg["t_ref_c"]
            f0 = Temperature.factor(s.temperature_c, t_ref, th["ea0_kj_mol"])
            u0 = f0 * i
            if th["ea_rc_kj_mol"] != 0.0:
                f_rc = Temperature.factor(s.temperature_c, t_ref, th["ea_rc_kj_mol"])
        if self.has("direction_asymmetry"):
            r0_in = [(np.maximum(u0, 0.0), "r0_charge_ohm"), (np.minimum(u0, 0.0), "r0_discharge_ohm")]
        else:
            r0_in = [(u0, "r0_ohm")]
        cols: list[np.ndarray] = []
        names: list[str] = []
        if self.has("soc_dependence"):
            b = SocDependence.basis(s.soc, cfg["knots"])
            m = b.shape[1]
            for u, name in r0_in:
                cols += list((b * u[:, None]).T)
                names += [f"{name}@{j}" for j in range(m)]
            ub = b * i[:, None]
            for tau_key, name in (("tau1_s", "r1_ohm"), ("tau2_s", "r2_ohm")):
                cols += list(branch(ub, th[tau_key]).T)
                names += [f"{name}@{j}" for j in range(m)]
        else:
            for u, name in r0_in:
                cols.append(u)
                names.append(name)
            if f_rc is None:
                cols += [s.rc_current(th["tau1_s"]), s.rc_current(th["tau2_s"])]
            else:
                cols += [branch(i, th["tau1_s"]), branch(i, th["tau2_s"])]
            names += ["r1_ohm", "r2_ohm"]
        if self.has("current_nonlinearity"):
            i_s = th["i_s_a"]
            nl = i_s * np.arcsinh(i / i_s)
            cols.append(nl if f0 is None else f0 * nl)  # the kinetic term follows R0's temperature too
            names.append("k_nl_ohm")
        if self.has("slow_diffusion"):
            cols.append(s.rc_current(th["tau3_s"]))
            names.append("r3_ohm")
        if self.has("hysteresis"):
            hz, sg, p = hysteresis_trajectory(i, dt, s.capacity_ah, th["gamma"], unit_h0=True)
            cols += [hz + th["h0"] * p, sg]
            names += ["m_v", "m0_v"]
        cols.append(np.ones(len(s)))
        names.append("c0_v")
        y = s.voltage_v - s.ocv.ocv(self.soc_path(s, th))
        return y, np.array(cols), names

    def predict(self, s: Series, fit: "Fit") -> np.ndarray:
        return _predict(self, s, fit.theta, fit.beta, fit.cfg)

    def components(self, s: Series, fit: "Fit", mask: np.ndarray | None = None) -> dict[str, float]:
        """RMS [mV] each feature adds to the baseline's residual in this fit (see the module docstring).

        A feature's component is the voltage it adds alone to the fitted model's 2-RC
        part (every other feature neutral); its size is the RMS of what a re-fitted
        baseline (R0, R1, R2, c0 and both time constants) leaves of it, over ``mask``
        (all samples by default) - the generator's definition of an effect's size.
        """
        def neutral(features) -> tuple[dict, dict]:
            th, beta = dict(fit.theta), dict(fit.beta)
            for f in features:
                th.update(FEATURES[f].neutral_theta())
                beta = FEATURES[f].neutral_beta(beta, fit.cfg)
            return th, beta

        v_ref = _predict(self, s, *neutral(self.features), fit.cfg)  # the fitted model's 2-RC part
        out = {}
        for f in self.features:
            # the feature alone on that 2-RC part (the others neutral): interactions between two
            # features (a temperature-scaled kinetic term) count for neither, as in the generator
            comp = _predict(self, s, *neutral([g for g in self.features if g != f]), fit.cfg) - v_ref
            out[f] = float(1e3 * np.sqrt(np.mean(unabsorbed(comp, s, fit.theta, mask, base_v=v_ref) ** 2)))
        return out


def _predict(model: Model, s: Series, theta: dict, beta: dict, cfg: dict) -> np.ndarray:
    y, xt, names = model.design(s, theta, cfg)
    return s.voltage_v - y + np.array([beta[n] for n in names]) @ xt


def unabsorbed(e: np.ndarray, s: Series, theta: dict[str, float], mask: np.ndarray | None = None, *,
               base_v: np.ndarray | None = None) -> np.ndarray:
    """What a re-fitted 2-RC baseline leaves of an effect ``e`` (over ``mask``).

    The baseline (R0, R1, R2, c0 and both time constants, started at ``theta``'s)
    is fitted to ``base_v + e``, ``base_v`` the effect-free cell's voltage (a 2-RC
    cell on ``s``'s current and SOC path; ``OCV(soc)`` when omitted), and its
    residual returned.
    """
    base = s.ocv.ocv(s.soc) if base_v is None else base_v
    comp = Series(s.current_a, base + e, s.ocv, s.capacity_ah, s.soc0, s.dt_s)
    f = fit_model(BASELINE, comp, mask=mask, start={"tau1_s": theta["tau1_s"], "tau2_s": theta["tau2_s"]},
                  grid=False, max_iter=20)
    r = comp.voltage_v - BASELINE.predict(comp, f)
    return r if mask is None else r[np.asarray(mask, dtype=bool)]


BASELINE = Model()


@dataclass
class Fit:
    """A fitted model: nonlinear ``theta``, linear ``beta`` (by column name), data-derived ``cfg``."""

    cause: str
    theta: dict[str, float]
    beta: dict[str, float]
    cfg: dict
    train_rmse_mv: float
    extra: int = 0
    nfev: int = 0

    def params(self) -> dict:
        out: dict = dict(self.theta)
        out.update(self.beta)
        for k, v in self.cfg.items():
            if isinstance(v, np.ndarray):
                out[k] = [float(x) for x in v]
            elif isinstance(v, (int, float, np.floating)):
                out[k] = float(v)
        return out


# --------------------------------------------------------------------------- fitting


#: a resistance of the models (R0, R1, R2, R3, per SOC knot ``@k``, per direction), which no cell has below zero
RESISTANCE = re.compile(r"^r\d(_charge|_discharge)?_ohm(@\d+)?$")


def _solve(xt: np.ndarray, y: np.ndarray, nonneg: np.ndarray | None = None) -> np.ndarray:
    """Linear least squares ``y ~ xt.T @ beta``: equilibrated normal equations plus one refinement step,
    with ``beta[nonneg] >= 0`` (the resistances) where the free solution breaks it.

    ~100x faster than an SVD of the tall matrix for a dozen columns; the columns
    are scaled to unit norm, a pseudo-inverse of the small Gram matrix handles
    (near-)collinear columns, and one step of iterative refinement recovers the
    accuracy the squared condition number costs.  Bounded: with ``G = L L^T`` (the
    scaled Gram matrix, a ridge of 1e-12 of its trace) and ``h = xs y``,
    ``|xs^T b - y|^2 = |L^T b - L^-1 h|^2 + const``, so the bounded problem is a
    small one (columns x columns), solved by bounded-variable least squares.  Free,
    a resistance went negative to absorb what the model does not hold (R2 -267 mOhm
    at a SOC knot of the Panasonic 0 degC cycle_1 drive) and was reported as the cell's.
    """
    scale = np.sqrt(np.einsum("ij,ij->i", xt, xt))
    scale[scale == 0] = 1.0
    xs = xt / scale[:, None]
    gram = xs @ xs.T
    pinv = np.linalg.pinv(gram, rcond=1e-12, hermitian=True)
    h = xs @ y
    beta = pinv @ h
    beta += pinv @ (xs @ (y - beta @ xs))
    if nonneg is None or not np.any(beta[nonneg] < 0.0):
        return beta / scale
    n = gram.shape[0]
    for ridge in (1e-12, 1e-9, 1e-6):  # (collinear columns: the smallest ridge that factors)
        try:
            chol = np.linalg.cholesky(gram + ridge * np.trace(gram) * np.eye(n))
            break
        except np.linalg.LinAlgError:
            continue
    else:
        return beta / scale
    z = solve_triangular(chol, h, lower=True)
    lo = np.where(nonneg, 0.0, -np.inf)
    bounded = lsq_linear(chol.T, z, bounds=(lo, np.full(n, np.inf)), method="bvls")
    return bounded.x / scale


def _levenberg_marquardt(fun, x0, lo, hi, max_iter: int, ftol: float = 1e-6, xtol: float = 1e-5,
                         step: float = 1e-4) -> tuple[np.ndarray, int]:
    """Bounded Levenberg-Marquardt on a few parameters with forward-difference Jacobians.

    The residual vectors are long (one per sample) and the parameters few (2-6),
    so the work is in ``fun``; this loop only forms ``J^T J`` (d x d) and ``J^T r``
    (scipy's trust-region solvers spend more time than ``fun`` on such shapes).
    Bounds by clipping each trial point; stops when the cost improves by less than
    ``ftol`` (relative) or the step is below ``xtol``, or after ``max_iter`` Jacobians.
    """
    x = np.clip(np.asarray(x0, dtype=float), lo, hi)
    r = fun(x)
    cost = float(r @ r)
    nfev, lam, d = 1, 1e-3, x.size
    for _ in range(max_iter):
        h = step * np.maximum(1.0, np.abs(x))
        jac = np.empty((d, r.size))
        for j in range(d):
            xj = x.copy()
            xj[j] = xj[j] + h[j] if xj[j] + h[j] <= hi[j] else xj[j] - h[j]
            jac[j] = (fun(xj) - r) / (xj[j] - x[j])
        nfev += d
        a = jac @ jac.T
        g = jac @ r
        diag = np.maximum(np.diag(a), 1e-12 * max(np.max(np.diag(a)), 1e-300))
        improved = False
        while True:
            try:
                dx = -np.linalg.solve(a + lam * np.diag(diag), g)
            except np.linalg.LinAlgError:
                dx = -g / (diag * (1.0 + lam))
            x_new = np.clip(x + dx, lo, hi)
            r_new = fun(x_new)
            nfev += 1
            c_new = float(r_new @ r_new)
            if c_new < cost:
                rel = (cost - c_new) / max(cost, 1e-300)
                moved = float(np.max(np.abs(x_new - x)))
                x, r, cost = x_new, r_new, c_new
                lam = max(lam / 5.0, 1e-9)
                improved = True
                if rel < ftol or moved < xtol:
                    return x, nfev
                break
            lam *= 8.0
            if lam > 1e8:
                break
        if not improved:
            break
    return x, nfev


def fit_model(
    model: Model,
    s: Series,
    *,
    mask: np.ndarray | None = None,
    start: dict[str, float] | None = None,
    cfg: dict | None = None,
    grid: bool = True,
    max_iter: int = 12,
) -> Fit:
    """Output-error fit of ``model`` on the samples ``mask`` of ``s`` (variable projection).

    ``start`` holds initial nonlinear parameters (``tau1_s``, ``tau2_s`` and the
    features' own); missing ones start at the best point of their grid
    (``grid=True``, the others held at their start) or at its centre.  Then a
    bounded Levenberg-Marquardt over all nonlinear parameters (log-scaled where
    positive), ``beta`` eliminated by linear least squares at every evaluation.
    """
    cfg = model.setup(s) if cfg is None else cfg
    specs = model.nonlinear(s, cfg)
    rows = None if mask is None or np.all(mask) else np.flatnonzero(mask)
    start = {k: v for k, v in (start or {}).items() if any(sp.name == k for sp in specs)}
    nfev = [0]

    def unpack(x: np.ndarray) -> dict[str, float]:
        return {sp.name: sp.from_x(float(v)) for sp, v in zip(specs, x)}

    def resid(x: np.ndarray) -> np.ndarray:
        y, xt, names = model.design(s, unpack(x), cfg)
        if rows is not None:
            y, xt = y[rows], xt[:, rows]
        nfev[0] += 1
        return 1e3 * (y - _solve(xt, y, _resistances(names)) @ xt)  # mV: a well-scaled cost

    own = [sp for sp in specs if sp.name not in start]
    for sp in own:
        start[sp.name] = sp.centre()
    if grid and own:
        # coarse stage over the parameters without a start, the others held
        grids = [sp.grid or (start[sp.name],) for sp in own]
        best, best_cost = dict(start), np.inf
        for combo in np.array(np.meshgrid(*grids, indexing="ij")).reshape(len(own), -1).T:
            trial = dict(start)
            trial.update({sp.name: float(v) for sp, v in zip(own, combo)})
            r = resid(np.array([sp.to_x(trial[sp.name]) for sp in specs]))
            c = float(r @ r)
            if c < best_cost:
                best, best_cost = trial, c
        start = best
    x0 = np.array([sp.to_x(start[sp.name]) for sp in specs])
    lo = np.array([sp.bounds_x()[0] for sp in specs])
    hi = np.array([sp.bounds_x()[1] for sp in specs])
    x_best, _ = _levenberg_marquardt(resid, x0, lo, hi, max_iter)
    th = unpack(x_best)
    y, xt, names = model.design(s, th, cfg)
    if rows is not None:
        beta = _solve(xt[:, rows], y[rows], _resistances(names))
        r = y[rows] - beta @ xt[:, rows]
    else:
        beta = _solve(xt, y, _resistances(names))
        r = y - beta @ xt
    extra = int(xt.shape[0] + len(specs) - 6)
    return Fit(model.name, th, dict(zip(names, (float(b) for b in beta))), cfg,
               float(1e3 * np.sqrt(np.mean(r * r))), extra, nfev[0])


def _resistances(names: list[str]) -> np.ndarray:
    """Which of the linear columns are resistances (held at or above zero by :func:`_solve`)."""
    return np.array([RESISTANCE.match(n) is not None for n in names], dtype=bool)


def predict(model: Model, s: Series, fit: Fit) -> np.ndarray:
    """Simulated terminal voltage of a fitted model over ``s`` (from rest at the file's start)."""
    return model.predict(s, fit)
