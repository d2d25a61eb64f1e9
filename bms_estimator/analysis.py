"""Offline runs of the online estimators over recorded data (arrays in, arrays out).

Used by ``fit``, ``compare``, ``soc``, ``diagnose``, ``encode-log`` and the demo; no file I/O here.

How a recording is simulated (the paper's Section IV-A):

* The SOC path of a file is coulomb counting from its start SOC (the data's drive
  cycles start full) with the *effective* capacity of the training file: the
  output-error capacity (:func:`output_error_capacity`), i.e. the capacity whose
  identified model simulates the training file best, found in one vectorised pass
  over candidate SOC paths.
* Identification runs online over the training file with ``v_o = v - OCV(soc)``
  and, since that SOC is given, a prior c0 = 0 (``KNOWN_SOC_C0_PRIOR_WEIGHT``).
* Training simulation: the model is simulated with the online parameter
  trajectory (R0, RC pairs and c0 at each second), from rest.
* Validation simulation: the parameters are looked up by SOC in a table built
  from the training run (median per 2 % SOC bin over identified samples,
  interpolated), c0 included, so what the training run learnt about the cell at
  each SOC carries over; nothing is learnt on the validation file.  Where both
  files log the cell temperature the table holds the training temperature of
  each bin too, and the looked-up resistances are brought from it to the
  validation file's temperature at each sample by Arrhenius
  (:mod:`bms_estimator.core.arrhenius`, ``B = RESISTANCE_ACTIVATION_K``, the
  time constants kept): an aggressive cycle heats the cell by 2-5 K more than a
  gentle one, which lowers its resistances by 5-15 %.
* One-step-ahead (OSA) error: the ZOH-discretised model of the previous
  second predicts the voltage from the measured past (same predictor for both
  methods, so CT and DT are comparable).
* Metrics cover the 20-90 % SOC part of each file by default (``soc_window``),
  and the full range is reported too.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .core.arrhenius import RESISTANCE_ACTIVATION_K, resistances_at
from .core.ecm import EcmParams, simulate_ecm
from .core.identifier import IdentifierConfig
from .core.identifier_methods import make_identifier
from .core.lif_bv import kinetic_input
from .core.lif_ct import kinetic_excess, thermal_voltage
from .core.ocv_surface import Ocv
from .core.params import dt_theta_from_physical
from .core.soc import SocConfig, SocEstimator
from .scoring import counted_soc, soc_on_branch

# weight of the prior c0 = 0 when the SOC path is given (fit, compare): per sample, relative
# to one data sample; c0 is then an OCV-model error, not an SOC error, and the prior keeps
# it from trading off against the slow RC branch (c0 + R2 * mean current) on drive cycles
KNOWN_SOC_C0_PRIOR_WEIGHT = 0.1

# The CT method for identification along a known SOC path (fit, compare, diagnose): recursive IV
# measures better than LS there (below DT on more of the same-ambient pairs of ../shared/data, see
# README). The SOC estimator keeps its own default (IdentifierConfig.method), measured on SOC.
IDENTIFICATION_METHOD = "lif-iv"
# what compare runs by default: the CT default first (its model gives the capacity), the other CT, DT
DEFAULT_METHODS = (IDENTIFICATION_METHOD, "lif", "arx")

PARAM_KEYS = ("r0_ohm", "r1_ohm", "c1_f", "r2_ohm", "c2_f", "c0_v", "tau1_s", "tau2_s")

__all__ = [
    "IdentificationRun",
    "SocRun",
    "run_identification",
    "run_identification_paths",
    "output_error_capacity",
    "run_soc",
    "simulate_with_params",
    "one_step_ahead",
    "soc_lookup_table",
    "lookup_params",
    "rmse_mv",
    "IDENTIFICATION_METHOD",
    "DEFAULT_METHODS",
    "compare_methods",
    "train_methods",
    "validate_methods",
    "reference_soc",
    "reference_capacity",
]


@dataclass
class IdentificationRun:
    time_s: np.ndarray
    soc: np.ndarray
    params: dict[str, np.ndarray]  # trajectories, shape (n,)
    identified: np.ndarray  # bool (n,)
    rejections: int
    method: str


@dataclass
class SocRun:
    time_s: np.ndarray
    soc: np.ndarray  # NaN before the start
    capacity_ah: np.ndarray
    params: dict[str, np.ndarray]
    corrections: int
    rejections: int
    soc_sigma: np.ndarray | None = None  # the EKF's 1-sigma SOC uncertainty (NaN for the c0 method)
    # at the end, -1 / +1: the capacity estimate at its low / high bound (the stated capacity is wrong for the
    # cell: SocEstimator.capacity_at_bound), 0 inside
    capacity_at_bound: int = 0
    # at the end, the c0 method's voltage-line capacity (SocEstimator.capacity_voltage_ah; NaN: none yet, or ekf)
    capacity_voltage_ah: float = float("nan")


#: coulomb counting from a known start (the data's drive cycles start full), read at mid-sample
reference_soc = counted_soc


def _record(traj: dict[str, np.ndarray], k: int, params: dict[str, np.ndarray]) -> None:
    """Store cell 0's parameters at sample k of the trajectories."""
    for key in PARAM_KEYS:
        traj[key][k] = params[key][0]


def run_identification(
    current_a: np.ndarray,
    voltage_v: np.ndarray,
    soc: np.ndarray,
    ocv: Ocv,
    capacity_ah: float,
    dt_s: float = 1.0,
    config: IdentifierConfig = IdentifierConfig(),
) -> IdentificationRun:
    """Online identification along a known SOC path (no SOC compensation)."""
    return run_identification_paths(current_a, voltage_v, np.asarray(soc)[:, None], ocv, capacity_ah,
                                    dt_s, config)[0]


def run_identification_paths(
    current_a: np.ndarray,
    voltage_v: np.ndarray,
    soc_paths: np.ndarray,
    ocv: Ocv,
    capacity_ah: float,
    dt_s: float = 1.0,
    config: IdentifierConfig = IdentifierConfig(),
) -> list[IdentificationRun]:
    """Online identification of one recording along m SOC paths ``(n, m)`` at once.

    The paths are m cells of one vectorised identifier, so m candidate SOC
    paths (candidate capacities, say) cost about as much as one.
    """
    soc_paths = np.asarray(soc_paths, dtype=float)
    n, m = soc_paths.shape
    ident = make_identifier(m, dt_s, capacity_ah, config)
    v_o = np.asarray(voltage_v, dtype=float)[:, None] - ocv.ocv(soc_paths)
    # PARAM_KEYS, and a model extension's (lif-iv-bv: KINETIC_KEYS, lif-iv-ct: CT_KEYS)
    keys = tuple(ident.param_dict())
    traj = {k: np.empty((n, m)) for k in keys}
    identified = np.zeros((n, m), dtype=bool)
    i = np.asarray(current_a, dtype=float)
    for k in range(n):
        ident.update(i[k], v_o[k])
        p = ident.param_dict()
        for key in keys:
            traj[key][k] = p[key]
        identified[k] = ident.identified
    t = np.arange(n) * dt_s
    return [
        IdentificationRun(t, soc_paths[:, j], {key: traj[key][:, j].copy() for key in keys},
                          identified[:, j].copy(), int(ident.rejections[j]), config.method)
        for j in range(m)
    ]


def output_error_capacity(
    current_a: np.ndarray,
    voltage_v: np.ndarray,
    ocv: Ocv,
    stated_ah: float,
    initial_soc: float = 1.0,
    dt_s: float = 1.0,
    config: IdentifierConfig = IdentifierConfig(),
    *,
    relative: tuple[float, float] = (0.8, 1.1),
    step: float = 0.02,
    soc_window: tuple[float, float] = (0.2, 0.9),
) -> tuple[float, dict[str, np.ndarray]]:
    """The capacity that makes the identified model simulate the recording best.

    Capacity is a parameter of the model like R0 (the gain of the SOC
    integrator): each candidate Q on a grid of ``relative`` x the stated
    capacity gives an SOC path by coulomb counting from ``initial_soc``; the
    online identifier runs along every path at once (one vectorised pass) and
    the free-run simulation RMSE of its parameter trajectory, over the samples
    inside ``soc_window`` on the stated capacity's path, is the output error of
    that Q.  A parabola through the best grid point and its neighbours refines
    the minimum.  Returns (Q, profile) with the profile's ``capacity_ah`` and
    ``sim_rmse_mv``.
    """
    i = np.asarray(current_a, dtype=float)
    v = np.asarray(voltage_v, dtype=float)
    rel = np.arange(relative[0], relative[1] + 0.5 * step, step)
    q = stated_ah * rel
    paths = np.stack([reference_soc(i, dt_s, qj, initial_soc) for qj in q], axis=1)
    runs = run_identification_paths(i, v, paths, ocv, stated_ah, dt_s, config)
    s_stated = reference_soc(i, dt_s, stated_ah, initial_soc)
    inside = (s_stated >= soc_window[0]) & (s_stated <= soc_window[1])
    if inside.sum() < 100:
        inside = np.ones_like(inside)
    err = np.array([rmse_mv(simulate_with_params(i, r.soc, ocv, r.params, dt_s), v, inside) for r in runs])
    err = np.where(np.isfinite(err), err, np.inf)
    k = int(np.argmin(err))
    q_best = q[k]
    if 0 < k < len(q) - 1 and np.all(np.isfinite(err[k - 1:k + 2])):
        e0, e1, e2 = err[k - 1:k + 2]
        curv = e0 - 2 * e1 + e2
        if curv > 0:
            q_best = q[k] + 0.5 * (e0 - e2) / curv * (q[1] - q[0])
    return float(q_best), {"capacity_ah": q, "sim_rmse_mv": err}


def run_soc(
    current_a: np.ndarray,
    voltage_v: np.ndarray,
    ocv: Ocv,
    capacity_ah: float,
    initial_soc: float | None,
    dt_s: float = 1.0,
    config: SocConfig = SocConfig(),
    *,
    temperature_c: np.ndarray | None = None,
    start_index: int = 0,
    rest_s: np.ndarray | None = None,
    fed: np.ndarray | None = None,
) -> SocRun:
    """The online SOC estimator over a recording (one cell).

    It starts at sample ``start_index`` with ``initial_soc`` (``None``: read from
    the OCV at that sample, as after a rest); samples before it are NaN.
    ``temperature_c`` (per sample) reads the OCV at the cell temperature when
    ``ocv`` holds several tables.  ``rest_s`` (per sample): seconds without samples
    before sample ``k`` (a recording with holes, fed contiguously), rested over first
    (``SocEstimator.rest``: the cell parked).  ``fed`` (per sample; None: all): the
    samples the estimator is fed; the others (a file's logging gaps,
    :func:`bms_estimator.gaps.rest_plan`) are skipped and hold the state of the last
    fed sample, as the service publishes nothing new while it has no samples.  A start
    on a sample not fed begins at the next fed one.
    """
    n = len(current_a)
    k0 = int(start_index)
    if not 0 <= k0 < n:
        raise ValueError(f"start sample {k0} is outside the recording (0..{n - 1})")
    if fed is not None and np.shape(fed) != (n,):
        raise ValueError(f"fed has shape {np.shape(fed)}, the recording {n} samples")
    est = SocEstimator(1, ocv, capacity_ah, dt_s, initial_soc=initial_soc, config=config)
    soc = np.full(n, np.nan)
    sigma = np.full(n, np.nan)
    cap = np.full(n, np.nan)
    traj = {k: np.full(n, np.nan) for k in PARAM_KEYS}
    v1 = np.empty(1)
    t1 = None if temperature_c is None else np.empty(1)
    begun = False
    for k in range(k0, n):
        if fed is not None and not fed[k]:
            if begun:  # a logging gap: the state of the last fed sample held
                for x in (soc, sigma, cap, *traj.values()):
                    x[k] = x[k - 1]
            continue
        if begun and rest_s is not None and rest_s[k] > 0:
            est.rest(float(rest_s[k]))
        begun = True
        v1[0] = voltage_v[k]
        if t1 is not None:
            t1[0] = temperature_c[k]
        est.update(current_a[k], v1, temperature_c=t1)
        soc[k] = est.soc[0]
        sigma[k] = est.soc_sigma[0]
        cap[k] = est.capacity_ah[0]
        _record(traj, k, est.params)
    return SocRun(np.arange(n) * dt_s, soc, cap, traj, int(est.corrections[0]), int(est.identifier.rejections[0]),
                  sigma, int(est.capacity_at_bound[0]), float(est.capacity_voltage_ah[0]))


def _ecm_params(p: dict[str, np.ndarray]) -> EcmParams:
    r = np.stack([p["r1_ohm"], p["r2_ohm"]], axis=-1)
    tau = np.stack([p["tau1_s"], p["tau2_s"]], axis=-1)
    return EcmParams(np.asarray(p["r0_ohm"]), r, tau, np.asarray(p["c0_v"]))


def _kinetic_excess(current_a: np.ndarray, params: dict[str, np.ndarray]) -> np.ndarray:
    """The charge-transfer branch's kinetic excess w (V) along a parameter trajectory (core/lif_ct.py)."""
    return kinetic_excess(np.asarray(current_a, dtype=float), params["r1_ohm"], params["ct_fraction"],
                          params["ct_vt_v"])


def _through_branches(x: np.ndarray, r1, r2, params: dict[str, np.ndarray], dt_s: float) -> np.ndarray:
    """Free-run response (period means, from rest) of the RC branches with resistances r1, r2 and the
    model's time constants to an extra input x: how a model extension's input enters the simulation."""
    part = {"r0_ohm": 0.0, "r1_ohm": r1, "r2_ohm": r2, "c0_v": 0.0,
            "tau1_s": params["tau1_s"], "tau2_s": params["tau2_s"]}
    return simulate_ecm(x, dt_s, _ecm_params(part), output="mean").voltage_v


def _osa_through_branches(x: np.ndarray, r1, r2, params: dict[str, np.ndarray], dt_s: float) -> np.ndarray:
    """The one-step-ahead contribution (samples 2..n-1) of an extra input x through the same branches."""
    t = np.broadcast_to(dt_theta_from_physical(0.0, r1, params["tau1_s"], r2, params["tau2_s"], dt_s=dt_s),
                        (len(x), 6))[1:-1]
    return t[:, 2] * x[2:] + t[:, 3] * x[1:-1] + t[:, 4] * x[:-2]


def simulate_with_params(
    current_a: np.ndarray, soc: np.ndarray, ocv: Ocv, params: dict[str, np.ndarray], dt_s: float = 1.0
) -> np.ndarray:
    """Free-run voltage simulation with (possibly time-varying) parameters, from rest.

    With a charge-transfer fast branch (``ct_vt_v``, ``ct_fraction`` in ``params``,
    :mod:`bms_estimator.core.lif_ct`) the fast branch carries the kinetic excess
    ``w(i; R1)`` besides ``R1 i`` (simulated as an input through that branch with unit gain).
    With a kinetic term (``k1_ohm``, ``k2_ohm`` in ``params``, :mod:`bms_estimator.core.lif_bv`) the
    same RC branches carry ``K_j u`` besides ``R_j i``; the model is linear in its gains, so
    that part is simulated with the input u and gains K (split into their positive and
    negative parts, since an RC branch takes no negative resistance).
    """
    v = simulate_ecm(current_a, dt_s, _ecm_params(params), ocv.ocv, soc=soc, output="mean").voltage_v
    if "ct_vt_v" in params:  # a charge-transfer fast branch (core/lif_ct.py): its kinetic excess w through it
        unit = np.ones_like(np.asarray(params["tau1_s"], dtype=float))
        v = v + _through_branches(_kinetic_excess(current_a, params), unit, 0.0 * unit, params, dt_s)
    if "k1_ohm" not in params:
        return v
    u = kinetic_input(np.asarray(current_a, dtype=float), params["i0_a"])
    for sign in (1.0, -1.0):
        k1, k2 = (np.maximum(sign * np.asarray(params[key]), 0.0) for key in ("k1_ohm", "k2_ohm"))
        v = v + sign * _through_branches(u, k1, k2, params, dt_s)
    return v


def one_step_ahead(
    current_a: np.ndarray, voltage_v: np.ndarray, soc: np.ndarray, ocv: Ocv,
    params: dict[str, np.ndarray], dt_s: float = 1.0,
) -> np.ndarray:
    """OSA prediction v_hat[k] from the model of sample k-1 and the measured past (NaN for k < 2)."""
    i = np.asarray(current_a, dtype=float)
    v_o = np.asarray(voltage_v) - ocv.ocv(soc)
    th = dt_theta_from_physical(
        params["r0_ohm"], params["r1_ohm"], params["tau1_s"], params["r2_ohm"], params["tau2_s"],
        params["c0_v"], dt_s=dt_s,
    )
    th = np.broadcast_to(th, (len(i), 6))
    pred = np.full(len(i), np.nan)
    t = th[1:-1]  # model of sample k-1 predicts k, k = 2..n-1
    pred[2:] = (
        t[:, 0] * v_o[1:-1] + t[:, 1] * v_o[:-2] + t[:, 2] * i[2:] + t[:, 3] * i[1:-1] + t[:, 4] * i[:-2] + t[:, 5]
    )
    if "ct_vt_v" in params:  # the kinetic excess w through the fast branch (core/lif_ct.py)
        pred[2:] += _osa_through_branches(_kinetic_excess(i, params), 1.0, 0.0, params, dt_s)
    if "k1_ohm" in params:  # the kinetic input u through the same poles (core/lif_bv.py)
        u = kinetic_input(i, params["i0_a"])
        pred[2:] += _osa_through_branches(u, params["k1_ohm"], params["k2_ohm"], params, dt_s)
    return pred + ocv.ocv(soc)


def soc_lookup_table(run: IdentificationRun, bin_width: float = 0.02,
                     temperature_c: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """Median parameters per SOC bin over the identified samples of a run.

    With the run's cell temperature (per sample) the table holds each bin's median
    temperature too (``temperature_c``: where the parameters were identified).
    """
    sel = run.identified & np.isfinite(run.soc)
    edges = np.arange(0.0, 1.0 + bin_width, bin_width)
    series = dict(run.params)
    if temperature_c is not None:
        t = np.asarray(temperature_c, dtype=float)
        if t.shape != run.soc.shape:
            raise ValueError(f"temperature has {t.size} samples, the run {run.soc.size}")
        series["temperature_c"] = t
    keys = tuple(series)
    centers, rows = [], {k: [] for k in keys}
    for lo, hi in zip(edges[:-1], edges[1:]):
        m = sel & (run.soc >= lo) & (run.soc < hi)
        if m.sum() < 5:
            continue
        centers.append(0.5 * (lo + hi))
        for k in keys:
            x = series[k][m]
            if k == "temperature_c":  # a logged temperature may have gaps
                x = x[np.isfinite(x)] if np.isfinite(x).any() else np.array([np.nan])
            rows[k].append(float(np.median(x)))
    if not centers:
        # nothing identified: the last parameters are all there is
        centers = [0.5]
        for k in keys:
            rows[k].append(float(series[k][-1]))
    table = {k: np.asarray(v) for k, v in rows.items()}
    table["soc"] = np.asarray(centers)
    return table


def lookup_params(table: dict[str, np.ndarray], soc: np.ndarray) -> dict[str, np.ndarray]:
    """Parameters along an SOC path from a lookup table (held constant beyond its ends)."""
    out = {k: np.interp(soc, table["soc"], table[k]) for k in table if k not in ("soc", "tau1_s", "tau2_s")}
    out["tau1_s"] = out["r1_ohm"] * out["c1_f"]
    out["tau2_s"] = out["r2_ohm"] * out["c2_f"]
    return out


def rmse_mv(a: np.ndarray, b: np.ndarray, mask: np.ndarray | None = None) -> float:
    d = np.asarray(a) - np.asarray(b)
    m = np.isfinite(d)
    if mask is not None:
        m &= mask
    if not m.any():
        return float("nan")
    return float(1e3 * np.sqrt(np.mean(d[m] ** 2)))


@dataclass
class FileResult:
    name: str
    soc: np.ndarray
    voltage_v: np.ndarray
    simulated_v: dict[str, np.ndarray] = field(default_factory=dict)
    osa_v: dict[str, np.ndarray] = field(default_factory=dict)
    params: dict[str, dict[str, np.ndarray]] = field(default_factory=dict)


@dataclass
class Comparison:
    capacity_ah: float
    metrics: dict  # {"train": {"lif": {...}, "arx": {...}}, "validate": {...}, "full_range": {...}}
    train: FileResult
    validate: FileResult
    runs: dict[str, IdentificationRun]


def _metrics(res: FileResult, method: str, window: tuple[float, float]) -> tuple[dict, dict]:
    inside = (res.soc >= window[0]) & (res.soc <= window[1])
    m_win = {
        "sim_rmse_mv": rmse_mv(res.simulated_v[method], res.voltage_v, inside),
        "osa_rmse_mv": rmse_mv(res.osa_v[method], res.voltage_v, inside),
    }
    m_full = {
        "sim_rmse_mv": rmse_mv(res.simulated_v[method], res.voltage_v),
        "osa_rmse_mv": rmse_mv(res.osa_v[method], res.voltage_v),
    }
    return m_win, m_full


@dataclass
class Training:
    """What the identifiers learnt on a training file (its SOC path from the effective capacity)."""

    capacity_ah: float  # effective (output-error) capacity
    profile: dict[str, np.ndarray]
    source: str
    result: FileResult
    runs: dict[str, IdentificationRun]
    tables: dict[str, dict[str, np.ndarray]]  # per method: parameters by SOC


def train_methods(
    train: tuple[np.ndarray, np.ndarray],
    ocv: Ocv,
    capacity_ah: float,
    *,
    dt_s: float = 1.0,
    initial_soc: float = 1.0,
    soc_window: tuple[float, float] = (0.2, 0.9),
    config: SocConfig = SocConfig(),
    methods: tuple[str, ...] = DEFAULT_METHODS,
    name: str = "train",
    c0_prior_weight: float = KNOWN_SOC_C0_PRIOR_WEIGHT,
    temperature_c: np.ndarray | None = None,
) -> Training:
    """The training half of :func:`compare_methods` (one training file, any number of validations).

    ``temperature_c`` (the training file's cell temperature per sample, optional) goes into
    the SOC tables, for :func:`validate_methods`' temperature correction.
    """
    i_tr, v_tr = (np.asarray(x, dtype=float) for x in train)
    ident_cfg = config.identifier.with_(c0_prior_weight=c0_prior_weight)
    t_median = float(np.nanmedian(temperature_c)) if temperature_c is not None and np.isfinite(temperature_c).any() \
        else float("nan")
    if -100.0 < t_median < 200.0:  # (a logged cell temperature, not a broken column)
        # lif-iv-ct: the charge-transfer branch's V_T = 2RT/F at the training file's median cell temperature
        ident_cfg = ident_cfg.with_(ct_temperature_c=t_median)
    q_eff, profile = output_error_capacity(i_tr, v_tr, ocv, capacity_ah, initial_soc, dt_s,
                                           ident_cfg.with_(method=methods[0]), soc_window=soc_window)
    soc_tr = reference_soc(i_tr, dt_s, q_eff, initial_soc)
    res = FileResult(name, soc_tr, v_tr)
    runs, tables = {}, {}
    for method in methods:
        run = run_identification(i_tr, v_tr, soc_tr, ocv, capacity_ah, dt_s, ident_cfg.with_(method=method))
        runs[method] = run
        res.params[method] = run.params
        res.simulated_v[method] = simulate_with_params(i_tr, soc_tr, ocv, run.params, dt_s)
        res.osa_v[method] = one_step_ahead(i_tr, v_tr, soc_tr, ocv, run.params, dt_s)
        tables[method] = soc_lookup_table(run, temperature_c=temperature_c)
    return Training(q_eff, profile, f"output error of the {methods[0]} model on the training file", res, runs,
                    tables)


def validate_methods(
    training: Training, validate: tuple[np.ndarray, np.ndarray], ocv: Ocv, *, dt_s: float = 1.0,
    initial_soc: float = 1.0, name: str = "validate", temperature_c: np.ndarray | None = None,
    activation_k: float = RESISTANCE_ACTIVATION_K,
) -> FileResult:
    """Simulate a validation file with each method's training parameters looked up by SOC (nothing learnt).

    With the validation file's cell temperature (``temperature_c``) and a training table that
    holds its own, the resistances are brought to the validation temperature at each sample
    (:func:`~bms_estimator.core.arrhenius.resistances_at`, ``activation_k``; 0 = no correction).
    """
    i_va, v_va = (np.asarray(x, dtype=float) for x in validate)
    soc_va = reference_soc(i_va, dt_s, training.capacity_ah, initial_soc)
    if temperature_c is not None and np.shape(temperature_c) != i_va.shape:
        raise ValueError(f"validation temperature has {np.size(temperature_c)} samples, the file {i_va.size}")
    res = FileResult(name, soc_va, v_va)
    for method, table in training.tables.items():
        p_va = lookup_params(table, soc_va)
        if temperature_c is not None and "temperature_c" in p_va and activation_k > 0:
            p_va = resistances_at(p_va, temperature_c, p_va["temperature_c"], activation_k)
        if temperature_c is not None and "ct_vt_v" in p_va:  # V_T at the validation file's cell temperature
            t = np.asarray(temperature_c, dtype=float)
            p_va["ct_vt_v"] = np.where(np.isfinite(t), thermal_voltage(np.where(np.isfinite(t), t, 25.0)),
                                       p_va["ct_vt_v"])
        res.params[method] = p_va
        res.simulated_v[method] = simulate_with_params(i_va, soc_va, ocv, p_va, dt_s)
        res.osa_v[method] = one_step_ahead(i_va, v_va, soc_va, ocv, p_va, dt_s)
    return res


def compare_methods(
    train: tuple[np.ndarray, np.ndarray],
    validate: tuple[np.ndarray, np.ndarray],
    ocv: Ocv,
    capacity_ah: float,
    *,
    dt_s: float = 1.0,
    initial_soc: float = 1.0,
    soc_window: tuple[float, float] = (0.2, 0.9),
    config: SocConfig = SocConfig(),
    methods: tuple[str, ...] = ("lif", "arx"),
    names: tuple[str, str] = ("train", "validate"),
    c0_prior_weight: float = KNOWN_SOC_C0_PRIOR_WEIGHT,
    temperatures_c: tuple[np.ndarray | None, np.ndarray | None] = (None, None),
    activation_k: float = RESISTANCE_ACTIVATION_K,
) -> Comparison:
    """The paper's Section IV-A on any pair of recordings (current, voltage at dt_s).

    The SOC of both files is coulomb counting from ``initial_soc`` with the
    training file's output-error capacity (:func:`output_error_capacity`, of
    the first method's model);
    since that SOC is given, the identifiers carry a prior c0 = 0 of weight
    ``c0_prior_weight`` (0 = the paper's plain estimate).  ``temperatures_c``: the cell
    temperature of each file (per sample, or None), for the validation simulation's
    Arrhenius correction (:func:`validate_methods`).
    """
    tr = train_methods(train, ocv, capacity_ah, dt_s=dt_s, initial_soc=initial_soc, soc_window=soc_window,
                       config=config, methods=methods, name=names[0], c0_prior_weight=c0_prior_weight,
                       temperature_c=temperatures_c[0])
    res_va = validate_methods(tr, validate, ocv, dt_s=dt_s, initial_soc=initial_soc, name=names[1],
                              temperature_c=temperatures_c[1], activation_k=activation_k)
    res_tr = tr.result
    q_rest, rest_source = reference_capacity(np.asarray(train[0], dtype=float), np.asarray(train[1], dtype=float),
                                             dt_s, ocv, capacity_ah, initial_soc)
    metrics = comparison_metrics(tr, res_va, soc_window)
    if not rest_source.startswith("stated"):
        metrics["capacity_ah_end_rest"] = q_rest
    metrics["c0_prior_weight"] = c0_prior_weight
    return Comparison(tr.capacity_ah, metrics, res_tr, res_va, tr.runs)


def comparison_metrics(training: Training, validation: FileResult, soc_window: tuple[float, float]) -> dict:
    """RMSE figures of every method on the training and a validation file (see :class:`Comparison`)."""
    metrics: dict = {"train": {}, "validate": {}, "full_range": {"train": {}, "validate": {}}}
    for method in training.runs:
        for key, res in (("train", training.result), ("validate", validation)):
            win, full = _metrics(res, method, soc_window)
            metrics[key][method] = win
            metrics["full_range"][key][method] = full
        metrics["train"][method]["rejections"] = training.runs[method].rejections
    metrics["capacity_ah_estimated"] = training.capacity_ah
    metrics["capacity_source"] = training.source
    metrics["capacity_profile"] = {k: [float(x) for x in v] for k, v in training.profile.items()}
    metrics["soc_window"] = list(soc_window)
    return metrics


def reference_capacity(
    current_a: np.ndarray,
    voltage_v: np.ndarray,
    dt_s: float,
    ocv: Ocv,
    stated_ah: float,
    soc0: float = 1.0,
    *,
    rest_s: float = 600.0,
    relaxed_v: float = 0.002,
) -> tuple[float, str]:
    """Capacity for the reference SOC of a recording that starts at a known SOC.

    When the file ends at a relaxed rest (the last ``rest_s`` below C/50 and the
    voltage moving less than ``relaxed_v`` over the last minute, like the LG
    files' final 600 s rest; the Panasonic files' 300 s rests still recover
    2-5 mV a minute and would read 2.88-2.92 Ah) the end SOC is read from the OCV and the capacity
    is the net charge over the SOC travelled: that is measured, not stated.
    Otherwise the stated capacity is all there is.

    The rest voltage is read on the hysteresis branch the cell came from: after
    a net discharge the relaxed voltage sits about H(soc) below the mean curve
    (the discharge branch, as measured at C/20), after a net charge above it.
    Read on the mean curve, an LG drive cycle's end would sit at 4 % SOC instead
    of 7.7 % and its capacity would come out 2.70 instead of 2.81 Ah (its C/20
    discharge gives 2.78 Ah).
    """
    i = np.asarray(current_a, dtype=float)
    n_rest = int(round(rest_s / dt_s))
    net_ah = float(np.sum(i) * dt_s / 3600.0)
    n_last = max(2, int(round(60.0 / dt_s)))
    v = np.asarray(voltage_v, dtype=float)
    # a rest of rest_s (a sample or two of it may carry residual current)
    at_rest = len(i) > n_rest and np.mean(np.abs(i[-n_rest:]) < stated_ah / 50.0) >= 0.99
    # only a relaxed rest tells the OCV: a voltage still rising after a deep discharge
    # (the Panasonic files' 300 s rests) would put the end SOC too low
    relaxed = at_rest and abs(v[-1] - v[-n_last]) < relaxed_v
    if at_rest and not relaxed:
        return float(stated_ah), "stated (end-of-test rest not relaxed)"
    if relaxed:
        soc_end, _ = soc_on_branch(float(voltage_v[-1]), ocv, side=np.sign(net_ah))
        travelled = soc_end - soc0
        if abs(net_ah) > 0.2 * stated_ah and travelled * net_ah > 0:
            q = net_ah / travelled
            if 0.5 * stated_ah < q < 1.5 * stated_ah:
                return q, "end-of-test rest (OCV)"
    return float(stated_ah), "stated"


def soc_errors(
    soc: np.ndarray, soc_ref: np.ndarray, time_s: np.ndarray, after_s: float = 3600.0
) -> dict[str, float]:
    """SOC error figures in percent (the paper's Fig. 10 numbers)."""
    err = 100.0 * (np.asarray(soc) - np.asarray(soc_ref))
    late = np.asarray(time_s) >= after_s
    out = {"soc_rmse_pct": float(np.sqrt(np.mean(err**2)))}
    if late.any():
        out["soc_rmse_pct_after_3600s"] = float(np.sqrt(np.mean(err[late] ** 2)))
        out["soc_max_abs_error_pct_after_3600s"] = float(np.max(np.abs(err[late])))
    else:
        out["soc_rmse_pct_after_3600s"] = float("nan")
        out["soc_max_abs_error_pct_after_3600s"] = float("nan")
    return out
