"""Seeded synthetic cells on real current profiles with hidden model errors of a given size.

:func:`generate` simulates a cell whose 2-RC base parameters are drawn around the
values the LIF identifies on the measured cells (R0 15-35 mOhm, R1 6-16 mOhm,
tau1 5-25 s, R2 10-40 mOhm, tau2 100-400 s, c0 within +-5 mV), drives it with a
real current profile (the shipped samples, or any file of ../shared/data) and
adds one or more *hidden effects*, each a physical mechanism the 2-RC model does
not have:

==========================  ===================================================================
``hysteresis``              Plett one-state hysteresis, gamma 10-200 per unit SOC, M0/M 0-0.5,
                            h0 = +1 (the drive cycles start after a full charge)
``temperature``             Arrhenius R0 (Ea0) and RC branches (Ea_rc, larger), tau = R C with C
                            fixed, driven by the temperature column
``soc_dependence``          R0, R1, R2 rising towards empty (``exp(-soc/w)``, w 0.05-0.2) plus a
                            mild linear trend, tau = R C with C fixed
``current_nonlinearity``    a Butler-Volmer kinetic term in series with the ohmic R0:
                            ``R0 i + a R0 I_s asinh(i / I_s)``, I_s 0.3-1.5 C (the small-current
                            resistance is ``(1 + a) R0``, falling towards ``R0`` at large ``|i|``)
``direction_asymmetry``     ``R0 +- delta/2`` on charge / discharge, random sign
``slow_diffusion``          a third RC (tau3 1000-4000 s) or a finite-length Warburg element
                            (5-term Foster series, tau_w 2000-8000 s), random choice
``current_offset``          the sensor reads ``i + b`` (random sign); the cell sees ``i``
``capacity_error``          the stated capacity is off by a factor (random sign)
==========================  ===================================================================

Size.  ``size_mv`` is the RMS the effect adds to the residual of the baseline:
the noise-free voltage of the cell with the effect is fitted by the diagnosis'
own 2-RC baseline (R0, R1, R2, c0 and both time constants re-fitted, on the
*measured* current with the *stated* capacity), and the amplitude is solved
(secant on the RMS of that fit's residual) so that the residual has ``size_mv``
RMS: what the baseline cannot absorb, however it bends its parameters.  ``size_mode="raw"`` sizes ``e`` itself
instead.  Both RMS figures are returned in ``truth``.  Several effects
(``causes={"hysteresis": 5, "temperature": 3}``) are each sized alone, then
simulated together.

Noise: 1 mV white on the voltage, 10 mA white on the current, 0.05 K on the
temperature (defaults).  The stated capacity is chosen so that the profile ends at
4-12 % SOC.  Temperature: the profile's own column when passed, else a lumped
thermal model (ambient 0-35 degC drifting by 1-4 K over hours, self-heating
``i^2 R`` through a thermal resistance of 3-8 K/W and capacity of 40-90 J/K).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.signal import lfilter

from .. import samples
from ..core.arrhenius import KELVIN, R_GAS
from ..core.hysteresis import hysteresis_trajectory
from ..core.ocv import OcvCurve
from ..data import CellRecording, load_recording, save_recording, shared_data_dir
from ..ocv_table import read_ocv_table, write_ocv_table
from .extensions import Series, rc_mean, unabsorbed

__all__ = ["GeneratedCell", "generate", "load_profile", "profile_names", "EFFECTS"]

EFFECTS = (
    "hysteresis", "temperature", "soc_dependence", "current_nonlinearity", "direction_asymmetry",
    "slow_diffusion", "current_offset", "capacity_error",
)


@dataclass
class GeneratedCell:
    """A synthetic recording plus the truth behind it."""

    time_s: np.ndarray
    current_a: np.ndarray  # measured (noise, offset)
    voltage_v: np.ndarray
    temperature_c: np.ndarray
    capacity_ah: float  # the stated capacity (what a user would pass to diagnose)
    initial_soc: float
    ocv: OcvCurve
    causes: dict[str, float]
    truth: dict = field(default_factory=dict)
    dt_s: float = 1.0

    def series(self) -> Series:
        return Series(self.current_a, self.voltage_v, self.ocv, self.capacity_ah, self.initial_soc, self.dt_s,
                      self.temperature_c)

    def recording(self):
        """As a :class:`~bms_estimator.data.CellRecording` (e.g. for ``save_recording``)."""
        return CellRecording(self.time_s, self.current_a, self.voltage_v, self.temperature_c, "generated")

    def save(self, folder) -> dict[str, Path]:
        """Write ``data.csv``, ``ocv.csv`` and ``truth.json`` into ``folder`` (what the CLI reads)::

            bms-estimator diagnose data.csv --ocv ocv.csv --capacity-ah <truth.json: capacity_ah>
        """
        folder = Path(folder)
        folder.mkdir(parents=True, exist_ok=True)
        out = {"data": save_recording(self.recording(), folder / "data.csv"),
               "ocv": write_ocv_table(self.ocv, folder / "ocv.csv")}
        truth = {"causes": self.causes, "dominant": self.dominant, "capacity_ah": self.capacity_ah,
                 "initial_soc": self.initial_soc, **self.truth}
        (folder / "truth.json").write_text(json.dumps(truth, indent=1, default=float) + "\n")
        out["truth"] = folder / "truth.json"
        return out

    @property
    def dominant(self) -> str:
        """The cause with the largest size (``none`` when clean)."""
        return max(self.causes, key=self.causes.get) if self.causes else "none"


# ------------------------------------------------------------------ profiles


def profile_names(include_shared: bool = True) -> list[str]:
    """Names accepted by :func:`load_profile`: shipped samples, and ../shared/data drive cycles when present."""
    names = [f"{cell}/25degC/{c}" for cell, (_, cycles) in samples.CELLS.items() for c in cycles]
    if include_shared:
        root = shared_data_dir()
        if root is not None:
            for p in sorted(Path(root).glob("*/*/*.csv*")):
                if not any(x in p.name for x in ("c20", "hppc")):
                    n = f"{p.parent.parent.name}/{p.parent.name}/{p.name.split('.')[0]}"
                    if n not in names:
                        names.append(n)
    return names


def load_profile(name: str):
    """``(current_a, temperature_c, cell, ocv)`` of a profile ``cell/ambient/test``.

    Shipped samples are used when they exist (no ../shared needed), else the
    shared data set.  The OCV is the cell's shipped 25 degC table.
    """
    cell, ambient, test = name.split("/")
    ocv = read_ocv_table(samples.ocv_table(cell))
    try:
        if ambient != "25degC":
            raise FileNotFoundError
        path = samples.drive_cycle(cell, test)
    except FileNotFoundError:
        root = shared_data_dir()
        if root is None:
            raise FileNotFoundError(f"profile {name!r} needs ../shared/data (not found)") from None
        path = Path(root) / cell / ambient / f"{test}.csv.gz"
    rec = load_recording(path)
    return rec.current_a, rec.temperature_c, cell, ocv


# ------------------------------------------------------------------ simulation


def _rc_varying(i: np.ndarray, r: np.ndarray, tau: np.ndarray, dt: float) -> np.ndarray:
    """Step-mean voltage of one RC branch with per-sample R and tau (C may vary too), exact ZOH per step."""
    p = np.exp(-dt / tau)
    gain = r * (1.0 - p) * i
    x = np.empty(i.size)
    xv = 0.0
    pl, gl = p.tolist(), gain.tolist()
    for k in range(i.size):
        x[k] = xv
        xv = pl[k] * xv + gl[k]
    g = tau * (1.0 - p) / dt
    return x * g + r * i * (1.0 - g)


def _warburg_terms(r_w: float, tau_w: float, n: int = 5) -> tuple[np.ndarray, np.ndarray]:
    """Foster RC series of a finite-length Warburg element ``R_w tanh(sqrt(s tau))/sqrt(s tau)``.

    ``R_k = 8 R_w / ((2k-1)^2 pi^2)``, ``tau_k = 4 tau_w / ((2k-1)^2 pi^2)``; the
    truncated tail's resistance is added to the last term so ``sum R_k = R_w``.
    """
    k = np.arange(1, n + 1)
    d = (2 * k - 1) ** 2 * np.pi**2
    r = 8.0 * r_w / d
    r[-1] += r_w - r.sum()
    return r, 4.0 * tau_w / d


@dataclass
class _Spec:
    """Everything that defines the true cell (neutral values = the clean 2-RC cell)."""

    r0: float
    r: tuple[float, float]
    tau: tuple[float, float]
    c0: float
    capacity_true: float
    soc0: float
    # effects
    hyst: tuple[float, float, float, float] = (0.0, 0.0, 30.0, 1.0)  # M, M0, gamma, h0
    ea: tuple[float, float] = (0.0, 0.0)  # kJ/mol: R0, RC branches
    soc_dep: tuple = ()  # (amp, w, a0, a1, a2, c0, c1, c2)
    nonlin: tuple[float, float] = (0.0, 1.0)  # a, I_s
    asym: float = 0.0  # delta R0 (charge - discharge)
    slow: tuple = ()  # (R's, tau's)
    offset_a: float = 0.0


def _simulate(i_true: np.ndarray, temp_c: np.ndarray, ocv: OcvCurve, spec: _Spec, dt: float) -> np.ndarray:
    """Noise-free terminal voltage of the true cell."""
    n = i_true.size
    s = Series(i_true, np.zeros(n), ocv, spec.capacity_true, spec.soc0, dt)
    soc = s.soc
    f0 = np.ones(n)
    f_rc = [np.ones(n), np.ones(n)]
    t_ref = float(np.mean(temp_c))
    if spec.ea[0] or spec.ea[1]:
        inv = 1.0 / (temp_c + KELVIN) - 1.0 / (t_ref + KELVIN)
        f0 = f0 * np.exp(spec.ea[0] * 1e3 / R_GAS * inv)
        f_rc = [f * np.exp(spec.ea[1] * 1e3 / R_GAS * inv) for f in f_rc]
    if spec.soc_dep:
        amp, w, a0, a1, a2, c0, c1, c2 = spec.soc_dep
        shape = np.exp(-np.clip(soc, 0.0, 1.0) / w)
        trend = np.clip(soc, 0.0, 1.0) - 0.5
        f0 = f0 * (1.0 + amp * (a0 * shape + c0 * trend))
        f_rc = [f_rc[0] * (1.0 + amp * (a1 * shape + c1 * trend)), f_rc[1] * (1.0 + amp * (a2 * shape + c2 * trend))]
    r0 = spec.r0 * f0
    v = ocv.ocv(soc) + spec.c0
    i_pos, i_neg = np.maximum(i_true, 0.0), np.minimum(i_true, 0.0)
    v = v + (r0 + 0.5 * spec.asym) * i_pos + (r0 - 0.5 * spec.asym) * i_neg
    a, i_s = spec.nonlin
    if a:
        v = v + a * r0 * i_s * np.arcsinh(i_true / i_s)
    for j in range(2):
        if np.all(f_rc[j] == 1.0):
            v = v + spec.r[j] * rc_mean(i_true, spec.tau[j], dt)
        else:
            rj = spec.r[j] * f_rc[j]
            v = v + _rc_varying(i_true, rj, spec.tau[j] * f_rc[j], dt)  # C fixed: tau scales with R
    if spec.slow:
        for rk, tk in zip(*spec.slow):
            v = v + rk * rc_mean(i_true, tk, dt)
    m, m0, gamma, h0 = spec.hyst
    if m or m0:
        h, sg = hysteresis_trajectory(i_true, dt, spec.capacity_true, gamma, h0=h0)
        v = v + m * h + m0 * sg
    return v


def _model_view(i_meas: np.ndarray, ocv: OcvCurve, spec: _Spec, q_stated: float, dt: float) -> np.ndarray:
    """The base 2-RC model on the measured current with the stated capacity (what 'no effect' predicts)."""
    s = Series(i_meas, np.zeros(i_meas.size), ocv, q_stated, spec.soc0, dt)
    return (ocv.ocv(s.soc) + spec.c0 + spec.r0 * i_meas + spec.r[0] * rc_mean(i_meas, spec.tau[0], dt)
            + spec.r[1] * rc_mean(i_meas, spec.tau[1], dt))


def _unabsorbed(e: np.ndarray, i: np.ndarray, spec: _Spec, dt: float, ocv: OcvCurve, q_stated: float) -> np.ndarray:
    """The part of ``e`` a re-fitted 2-RC baseline cannot absorb (:func:`.extensions.unabsorbed`).

    The fit is the diagnosis' own baseline fit (R0, R1, R2, c0 and both time
    constants, started at the true ones) on the measured current with the stated
    capacity.
    """
    s = Series(i, np.zeros(i.size), ocv, q_stated, spec.soc0, dt)
    return unabsorbed(e, s, {"tau1_s": spec.tau[0], "tau2_s": spec.tau[1]},
                      base_v=_model_view(i, ocv, spec, q_stated, dt))


def _rms_mv(x: np.ndarray) -> float:
    return float(1e3 * np.sqrt(np.mean(x * x)))


class _Effect:
    """One hidden effect: random shape from the seed, amplitude ``alpha`` solved for the size."""

    def __init__(self, cause: str, rng: np.random.Generator, i: np.ndarray, q: float, temp_c: np.ndarray):
        self.cause = cause
        self.sign = float(rng.choice([-1.0, 1.0]))
        self.info: dict = {}
        if cause == "hysteresis":
            self.gamma = float(np.exp(rng.uniform(np.log(10.0), np.log(200.0))))
            self.ratio = float(rng.uniform(0.0, 0.5))
        elif cause == "temperature":
            self.ea0 = float(rng.uniform(10.0, 35.0))
            self.ea_rc = float(rng.uniform(35.0, 70.0))
        elif cause == "soc_dependence":
            self.w = float(rng.uniform(0.05, 0.2))
            self.a = rng.uniform(0.5, 1.5, 3)
            self.c = rng.uniform(-0.4, 0.4, 3)
        elif cause == "current_nonlinearity":
            self.i_s = float(rng.uniform(0.3, 1.5) * q)
        elif cause == "slow_diffusion":
            self.kind = str(rng.choice(["rc", "warburg"]))
            self.tau = float(np.exp(rng.uniform(np.log(1000.0), np.log(4000.0)))) if self.kind == "rc" else \
                float(np.exp(rng.uniform(np.log(2000.0), np.log(8000.0))))

    def apply(self, spec: _Spec, alpha: float, q_stated: float) -> tuple[_Spec, float]:
        """(spec with the effect at amplitude alpha, stated capacity)."""
        alpha = float(alpha)
        c = self.cause
        d = dict(spec.__dict__)
        if c == "hysteresis":
            d["hyst"] = (alpha * 1e-3, alpha * 1e-3 * self.ratio, self.gamma, 1.0)
            self.info = {"m_v": alpha * 1e-3, "m0_v": alpha * 1e-3 * self.ratio, "gamma": self.gamma, "h0": 1.0}
        elif c == "temperature":
            d["ea"] = (alpha * self.ea0, alpha * self.ea_rc)
            self.info = {"ea0_kj_mol": alpha * self.ea0, "ea_rc_kj_mol": alpha * self.ea_rc}
        elif c == "soc_dependence":
            d["soc_dep"] = (alpha, self.w, *self.a, *self.c)
            self.info = {"amplitude": alpha, "w": self.w, "a": self.a.tolist(), "c": self.c.tolist()}
        elif c == "current_nonlinearity":
            d["nonlin"] = (alpha, self.i_s)
            self.info = {"a": alpha, "i_s_a": self.i_s}
        elif c == "direction_asymmetry":
            d["asym"] = self.sign * alpha * 1e-3
            self.info = {"delta_r0_ohm": d["asym"]}
        elif c == "slow_diffusion":
            r = alpha * 1e-3
            d["slow"] = ((np.array([r]), np.array([self.tau])) if self.kind == "rc" else _warburg_terms(r, self.tau))
            self.info = {"kind": self.kind, "r_ohm": r, "tau_s": self.tau}
        elif c == "current_offset":
            d["offset_a"] = self.sign * alpha * 1e-3
            self.info = {"offset_a": d["offset_a"]}
        elif c == "capacity_error":
            ratio = (1.0 + alpha * 1e-3) ** self.sign
            q_stated = q_stated * ratio
            self.info = {"stated_over_true": ratio}
        else:
            raise ValueError(f"unknown cause {c!r}; choose from {', '.join(EFFECTS)}")
        return _Spec(**d), q_stated


def _measure(i_true, temp, ocv, spec, q_stated, dt) -> tuple[np.ndarray, np.ndarray]:
    i_meas = i_true + spec.offset_a
    e = _simulate(i_true, temp, ocv, spec, dt) - _model_view(i_meas, ocv, spec, q_stated, dt)
    return e, i_meas


def _solve_alpha(effect: _Effect, i_true, temp, ocv, base: _Spec, q_stated, dt, size_mv, mode) -> tuple[float, dict]:
    """Amplitude giving ``size_mv`` (secant in log-log on the monotone size(alpha))."""

    def size(alpha: float) -> tuple[float, float]:
        spec, qs = effect.apply(base, alpha, q_stated)
        e, i_meas = _measure(i_true, temp, ocv, spec, qs, dt)
        return _rms_mv(e), _rms_mv(_unabsorbed(e, i_meas, spec, dt, ocv, qs))

    pick = (lambda r: r[1]) if mode == "residual" else (lambda r: r[0])
    a0, f0 = 1.0, pick(size(1.0))
    if not f0 > 1e-6:
        raise ValueError(f"the {effect.cause} effect is invisible on this profile (e.g. no charge current)")
    a1 = a0 * size_mv / f0
    f1 = pick(size(a1))
    for _ in range(8):
        if abs(f1 - size_mv) < 0.005 * size_mv or f1 <= 0:
            break
        slope = (np.log(f1) - np.log(f0)) / (np.log(a1) - np.log(a0)) if a1 != a0 else 1.0
        slope = slope if np.isfinite(slope) and slope > 0.2 else 1.0
        a0, f0 = a1, f1
        a1 = a1 * (size_mv / f1) ** (1.0 / slope)
        f1 = pick(size(a1))
    raw, resid = size(a1)
    spec, qs = effect.apply(base, a1, q_stated)
    why = _unphysical(spec, qs, base, q_stated)
    if why:
        raise ValueError(f"{effect.cause} of {size_mv:g} mV on this profile needs {why}")
    return a1, {"raw_rms_mv": raw, "residual_rms_mv": resid, **effect.info}


def _unphysical(spec: _Spec, q_stated: float, base: _Spec, q0: float) -> str | None:
    """Why an effect's amplitude is beyond what a cell could show (``None`` when it is fine)."""
    if abs(spec.asym) >= 2.0 * spec.r0:
        return f"a charge/discharge R0 difference of {spec.asym * 1e3:.1f} mOhm (R0 {spec.r0 * 1e3:.1f} mOhm)"
    if max(spec.ea) > 150.0:
        return f"an activation energy of {max(spec.ea):.0f} kJ/mol"
    if not 0.5 <= q_stated / q0 <= 2.0:
        return f"a capacity error of a factor {q_stated / q0:.2f}"
    if abs(spec.offset_a) > 0.2 * q0:
        return f"a current offset of {spec.offset_a:.2f} A"
    if spec.hyst[0] > 0.2:
        return f"a hysteresis of {spec.hyst[0] * 1e3:.0f} mV"
    return None


def _thermal(i: np.ndarray, r_tot: float, rng: np.random.Generator, dt: float) -> tuple[np.ndarray, dict]:
    """Cell temperature: ambient with a slow drift plus lumped self-heating ``i^2 R``."""
    n = i.size
    ambient = float(rng.uniform(0.0, 35.0))
    r_th = float(rng.uniform(3.0, 8.0))
    c_th = float(rng.uniform(40.0, 90.0))
    tau = r_th * c_th
    p = np.exp(-dt / tau)
    heat = i * i * r_tot * r_th  # steady-state rise of each step
    rise = lfilter([0.0, 1.0 - p], [1.0, -p], heat)
    # the surroundings drift too (a vehicle's environment, a chamber's control): two slow sines
    t_h = np.arange(n) * dt / 3600.0
    drift_k = float(rng.uniform(1.0, 4.0))
    periods = rng.uniform(1.5, 5.0, 2)
    phases = rng.uniform(0.0, 2 * np.pi, 2)
    drift = 0.5 * drift_k * sum(np.sin(2 * np.pi * t_h / pp + ph) for pp, ph in zip(periods, phases))
    return ambient + drift + rise, {"ambient_c": ambient, "r_th_k_w": r_th, "c_th_j_k": c_th, "drift_k": drift_k}


def generate(
    profile_current: np.ndarray,
    dt_s: float = 1.0,
    cause: str | dict[str, float] | None = "none",
    size_mv: float = 3.0,
    seed: int = 0,
    *,
    temperature: np.ndarray | None = None,
    ocv: OcvCurve | None = None,
    capacity_ah: float | None = None,
    initial_soc: float = 1.0,
    noise_v: float = 1e-3,
    noise_a: float = 0.01,
    size_mode: str = "residual",
) -> GeneratedCell:
    """A synthetic recording on ``profile_current`` with hidden effect(s).

    Args:
        profile_current: the true current [A] (positive = charge), e.g. ``load_profile(...)[0]``.
        cause: ``"none"``, one cause, or ``{cause: size_mv, ...}`` for several at once.
        size_mv: size of a single cause (RMS it adds to the baseline's residual, see the module doc).
        seed: everything random (base parameters, effect shapes, noise) follows from it.
        temperature: cell temperature [degC] per sample; synthetic (self-heating) when omitted.
        ocv: the OCV curve (default: the Panasonic sample table).
        capacity_ah: the true capacity; default so that the profile ends at 4-12 % SOC.
        size_mode: ``"residual"`` (default) or ``"raw"`` (RMS of the effect itself).
    """
    rng = np.random.default_rng(seed)
    i_true = np.asarray(profile_current, dtype=float)
    n = i_true.size
    if ocv is None:
        ocv = read_ocv_table(samples.ocv_table("panasonic-18650pf"))
    if cause is None or cause == "none":
        causes: dict[str, float] = {}
    elif isinstance(cause, str):
        causes = {cause: float(size_mv)}
    else:
        causes = {str(k): float(v) for k, v in cause.items()}
    for c in causes:
        if c not in EFFECTS:
            raise ValueError(f"unknown cause {c!r}; choose from {', '.join(EFFECTS)}")
    base_rng = np.random.default_rng(rng.integers(2**32))
    spec = _Spec(
        r0=float(base_rng.uniform(0.015, 0.035)),
        r=(float(base_rng.uniform(0.006, 0.016)), float(base_rng.uniform(0.010, 0.040))),
        tau=(float(base_rng.uniform(5.0, 25.0)), float(base_rng.uniform(100.0, 400.0))),
        c0=float(base_rng.uniform(-0.005, 0.005)),
        capacity_true=1.0,
        soc0=float(initial_soc),
    )
    depth = float(np.max(-np.cumsum(i_true) * dt_s / 3600.0))  # deepest discharge [Ah]
    if capacity_ah is None:
        if depth < 0.05 or initial_soc < 0.3:
            raise ValueError("pass capacity_ah: the profile does not discharge a cell from a high SOC")
        capacity_ah = depth / (initial_soc - float(base_rng.uniform(0.04, 0.12)))
    spec = _Spec(**{**spec.__dict__, "capacity_true": float(capacity_ah)})
    q_stated = float(capacity_ah)
    therm = {}
    if temperature is None:
        temp, therm = _thermal(i_true, spec.r0 + sum(spec.r), base_rng, dt_s)
    else:
        temp = np.asarray(temperature, dtype=float)
        if temp.shape != i_true.shape or not np.all(np.isfinite(temp)):
            raise ValueError("temperature must be finite and match the profile's length")
    effects = {c: _Effect(c, np.random.default_rng(rng.integers(2**32)), i_true, q_stated, temp) for c in causes}
    truth: dict = {"base": {"r0_ohm": spec.r0, "r1_ohm": spec.r[0], "tau1_s": spec.tau[0], "r2_ohm": spec.r[1],
                            "tau2_s": spec.tau[1], "c0_v": spec.c0, "capacity_ah": spec.capacity_true},
                   "thermal": therm, "effects": {}, "size_mode": size_mode}
    full = spec
    for c, size in causes.items():
        alpha, info = _solve_alpha(effects[c], i_true, temp, ocv, spec, q_stated, dt_s, size, size_mode)
        truth["effects"][c] = info
        full, q_stated = effects[c].apply(full, alpha, q_stated)
    i_meas = i_true + full.offset_a
    v = _simulate(i_true, temp, ocv, full, dt_s)
    e_all = v - _model_view(i_meas, ocv, full, q_stated, dt_s)
    truth["total_raw_rms_mv"] = _rms_mv(e_all)
    truth["total_residual_rms_mv"] = _rms_mv(_unabsorbed(e_all, i_meas, full, dt_s, ocv, q_stated))
    noise_rng = np.random.default_rng(rng.integers(2**32))
    v_meas = v + noise_v * noise_rng.standard_normal(n)
    i_out = i_meas + noise_a * noise_rng.standard_normal(n)
    t_out = temp + 0.05 * noise_rng.standard_normal(n)
    return GeneratedCell(np.arange(n) * dt_s, i_out, v_meas, t_out, q_stated, float(initial_soc), ocv, causes,
                         truth, dt_s)
