"""What does the 2-RC model get wrong on this recording?  Baseline, candidates, decision.

Procedure (:func:`diagnose`):

1. **SOC path.**  Coulomb counting from ``initial_soc`` with the *stated* capacity
   (``capacity_error`` and ``current_offset`` test exactly that assumption).
2. **Baseline.**  The LIF identifier runs online over the file (the paper's
   method, :func:`~bms_estimator.analysis.run_identification`); its median
   parameters over the identified samples start a batch output-error fit of the
   constant 2-RC model (:mod:`.extensions`), which also tries a coarse grid of
   time constants and keeps the better start.  Residual = measured minus
   simulated voltage.
3. **Candidates.**  Each extension (:data:`~.extensions.CAUSES`) is fitted the
   same way, warm-started from the baseline's time constants.
4. **Out-of-sample score.**  ``folds`` (4) folds of interleaved time blocks
   (:func:`fold_blocks`: blocks of ``duration / 25`` clipped to 300-1800 s, block
   ``b >= 1`` in fold ``(b - 1) mod 4``, the first block always trained on): every
   model is refitted on the other folds, the whole file is simulated from its
   start with those parameters, and the held-out fold is scored; the held-out
   parts together give one out-of-sample prediction per model.  (Contiguous
   quarters would make each held-out part a different SOC range and every SOC-
   or time-dependent effect an extrapolation.)  With ``validate`` the models
   fitted on all of DATA are scored on the whole other file, split into the same
   kind of folds for the statistics.
5. **Significance.**  For candidate ``c`` with ``k`` extra parameters and
   out-of-sample mean squares ``MSE_0`` (reference: the baseline) and ``MSE_c``:

   * ``gain_pct = 100 (1 - RMSE_c / RMSE_0)``;
   * ``explained_mv = sqrt(MSE_0 - MSE_c)``, the RMS of what the extension explains;
   * ``score = ln(MSE_0 / MSE_c) - 2 k / n_eff``: an AIC-like penalty per extra
     parameter on the out-of-sample log-likelihood ratio, with the *effective*
     sample count ``n_eff = n / tau_int`` of the candidate's remaining residual
     (``tau_int`` its integrated autocorrelation time, Sokal's window): a
     residual that is still coloured carries less information per sample, so
     each parameter must buy more;
   * ``t_stat``: per fold ``f`` the held-out log gain ``d_f = ln(MSE_0,f / MSE_c,f)``;
     ``t = mean(d) / (std(d) / sqrt(K))`` - the gain must hold in every fold
     (each fold's blocks are spread over the file, so an effect that lives in
     one part of it is in every fold; the log makes folds with more or less of
     it comparable).

   Significant: ``score > 0``, ``t_stat >= t_min`` (2) and ``explained_mv >=
   noise_fraction * noise_mv`` (0.5): an effect below half the white-noise RMS is
   not worth a model extension even when it is statistically detectable.
   ``noise_mv`` is the white-noise level of the baseline residual,
   ``1.4826 MAD(diff r) / sqrt 2`` (robust to the residual's slow systematic part
   and to its steps).  No threshold depends on the effects' sizes: they follow
   from the noise level, the number of samples and the residual's correlation.
6. **Decision.**  No significant candidate: ``none``.  Otherwise let ``A`` be the
   significant candidate with the largest score.  One flexible extension can
   absorb part of another effect (SOC-dependent resistances times a mostly
   one-signed current mimic any slow drift; a hysteresis state relaxing from
   its start mimics a slow RC), so when two effects are present the single
   gains need not rank them by size.  Hence a *pair stage*: every pair
   ``A + X`` is fitted jointly on all of DATA, then every ``B + X`` for the best
   partner ``B`` (a swap, in case ``A`` itself was the absorber); the pair with
   the best in-sample penalised fit (same score, in-sample; a twin of ``A`` -
   a candidate predicting what ``A`` predicts - may replace ``A`` in it when it
   fits better next to the partner) is cross-validated
   against the best single among ``A`` and its own two members with the same
   three tests.  When it is significant, each
   of its two features gets a size: the RMS its voltage contributes to the joint
   fit, projected off the baseline's columns (what a 2-RC refit cannot absorb -
   the generator's own definition of an effect's size).  The cause is the pair's
   larger feature (``secondary`` the other); otherwise ``A``.
7. **Ties.**  Significant candidates that the named one does not beat block by
   block (``t < t_min`` on ``ln(MSE_other,b / MSE_named,b)`` over the held-out
   blocks) are listed as ``ties``: the data cannot tell them apart.  (The pair
   stage does not pair ``A`` with a candidate whose out-of-sample prediction is
   ``A``'s to within a quarter of what ``A`` explains: the two would only trade
   off against each other.)  The usual tie is ``current_offset`` /
   ``capacity_error``: both drift the coulomb count, one with time and one with
   throughput, which differ only where the file rests or changes pace.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field, replace
from typing import Annotated

import numpy as np
from annotated_types import Ge, Gt

from ..analysis import run_identification, simulate_with_params
from ..core.bounds import check_bounds
from ..core.identifier import IdentifierConfig
from ._blas import single_blas_thread
from .extensions import BASELINE, CAPACITY_RATIO_BOUNDS, CAUSES, FEATURES, RESISTANCE, Fit, Model, Series, fit_model

__all__ = ["DiagnoseConfig", "Candidate", "Diagnosis", "diagnose", "fold_blocks", "scored_folds", "tau_int",
           "noise_level"]


@dataclass(frozen=True)
class DiagnoseConfig:
    folds: Annotated[int, Ge(2)] = 4  # cross-validation folds (the t statistic needs two)
    blocks_per_fold: Annotated[int, Ge(1)] = 6
    block_s_bounds: tuple[Annotated[float, Gt(0)], Annotated[float, Gt(0)]] = (300.0, 1800.0)  # a block's length, s
    candidates: tuple[str, ...] = CAUSES
    lif: bool = True  # warm-start the baseline from the online LIF identification
    # its identification method (lif, lif-iv, lif-iv-bv, lif-iv-ct or arx); lif made the README's findings table
    method: str = "lif"
    t_min: Annotated[float, Ge(0)] = 2.0  # least t statistic of a significant gain (module docstring, 5.)
    noise_fraction: Annotated[float, Ge(0)] = 0.5  # least explained RMS, as a fraction of the noise level
    penalty: Annotated[float, Ge(0)] = 2.0  # per extra parameter, in units of 1/n_eff (AIC: 2)
    pairs: bool = True  # the pair stage (two effects at once)
    soc_window: tuple[float, float] = (-1.0, 2.0)  # fit and score where the counted SOC lies inside (default: all)
    max_iter: Annotated[int, Ge(1)] = 12  # Levenberg-Marquardt iterations of a full fit
    max_iter_fold: Annotated[int, Ge(1)] = 5  # of a fold's refit (warm-started from the full fit)

    def __post_init__(self) -> None:
        check_bounds(self)
        unknown = [c for c in self.candidates if c not in CAUSES]
        if unknown:
            raise ValueError(f"unknown cause(s) {', '.join(unknown)}; choose from {', '.join(CAUSES)}")
        if not self.block_s_bounds[0] <= self.block_s_bounds[1]:
            raise ValueError(f"block_s_bounds must be (shortest, longest), got {self.block_s_bounds}")

    def with_(self, **changes) -> "DiagnoseConfig":
        return replace(self, **changes)


@dataclass
class Candidate:
    cause: str
    rmse_mv: float
    gain_pct: float
    explained_mv: float
    score: float
    t_stat: float
    n_eff: float
    extra_params: int
    significant: bool
    params: dict
    note: str = ""

    def as_dict(self) -> dict:
        return asdict(self)


@dataclass
class Diagnosis:
    cause: str
    baseline_rmse_mv: float
    extended_rmse_mv: float
    gain_pct: float
    candidates: list[Candidate]
    baseline_params: dict
    noise_mv: float
    scoring: str
    seconds: float
    secondary: str | None = None
    ties: list[str] = field(default_factory=list)
    joint: dict = field(default_factory=dict)
    lif: dict = field(default_factory=dict)
    # arrays for the report (not in the JSON)
    series: Series | None = None
    scored: Series | None = None
    fits: dict[str, Fit] = field(default_factory=dict)
    predictions: dict[str, np.ndarray] = field(default_factory=dict)  # in-sample, full fit, over `series`
    oos: dict[str, np.ndarray] = field(default_factory=dict)  # out-of-sample, over `scored`

    def candidate(self, cause: str) -> Candidate | None:
        return next((c for c in self.candidates if c.cause == cause), None)

    @property
    def non_physical(self) -> list[str]:
        """What the named cause's fit (the baseline's for ``none``) holds that no cell has (:func:`non_physical`)."""
        c = self.candidate(self.cause) if self.cause != "none" else None
        return non_physical(c.params if c is not None else self.baseline_params)

    def ranking(self) -> list[Candidate]:
        return sorted(self.candidates, key=lambda c: -c.score if np.isfinite(c.score) else np.inf)

    def to_json(self) -> dict:
        return {
            "cause": self.cause,
            "baseline_rmse_mv": self.baseline_rmse_mv,
            "extended_rmse_mv": self.extended_rmse_mv,
            "gain_pct": self.gain_pct,
            "candidates": [
                {"cause": c.cause, "rmse_mv": c.rmse_mv, "gain_pct": c.gain_pct, "params": c.params,
                 "explained_mv": c.explained_mv, "score": c.score, "t_stat": c.t_stat, "n_eff": c.n_eff,
                 "extra_params": c.extra_params, "significant": c.significant,
                 **({"note": c.note} if c.note else {})}
                for c in self.candidates
            ],
            "secondary": self.secondary,
            "ties": self.ties,
            "joint": self.joint,
            "baseline_params": self.baseline_params,
            "noise_mv": self.noise_mv,
            "scoring": self.scoring,
            "lif": self.lif,
            "seconds": self.seconds,
            "non_physical": self.non_physical,
        }




def non_physical(params: dict) -> list[str]:
    """The fitted values no cell has, one phrase each: a resistance below zero (the least-squares fit lets a
    resistance go negative to absorb what the model does not hold: R2 -0.15 Ohm on the Panasonic 25 degC HPPC
    file, whose count misses its discharge steps, R2 -18 mOhm at the full-SOC knot of the cycle_2 drive), a
    capacity ratio at an end of its search (the capacity is not what closes the count there)."""
    out = [f"{k} {v * 1e3:.1f} mOhm (a resistance below zero)" for k, v in params.items()
           if RESISTANCE.match(k) and isinstance(v, (int, float)) and v < 0]
    ratio = params.get("capacity_ratio")
    if isinstance(ratio, (int, float)) and not CAPACITY_RATIO_BOUNDS[0] * 1.001 < ratio < CAPACITY_RATIO_BOUNDS[1] * 0.999:
        out.append(f"capacity_ratio {ratio:.3g} (an end of its {CAPACITY_RATIO_BOUNDS[0]:g}..{CAPACITY_RATIO_BOUNDS[1]:g} "
                   "search)")
    return out


# --------------------------------------------------------------------------- helpers


def fold_blocks(n: int, dt_s: float, cfg: DiagnoseConfig) -> tuple[np.ndarray, np.ndarray]:
    """Block index and fold of every sample.

    ``folds * blocks_per_fold + 1`` blocks of 300-1800 s (at least ``2 folds + 1``);
    block 0 - the file's start, where the initial conditions (RC states from
    rest, the hysteresis state, the initial SOC) play out - has fold ``-1``: it is
    in every training set and never scored, since it tests initial conditions,
    not the model.  Block ``b >= 1`` belongs to fold ``(b - 1) mod folds``.
    """
    lo, hi = cfg.block_s_bounds
    target = n * dt_s / (cfg.folds * cfg.blocks_per_fold + 1)
    block = min(max(target, lo), hi)
    n_blocks = max(int(round(n * dt_s / block)), 2 * cfg.folds + 1)
    blocks = np.minimum((np.arange(n) * n_blocks) // n, n_blocks - 1)
    return blocks, np.where(blocks == 0, -1, (blocks - 1) % cfg.folds)


#: fewest samples inside the SOC window that a diagnosis is fitted and scored on
WINDOW_SAMPLES_MIN = 100


def window_mask(s: Series, cfg: DiagnoseConfig) -> np.ndarray:
    """Logged samples (``s.logged``) whose counted SOC lies inside ``cfg.soc_window`` (all of them by default);
    fewer than ``WINDOW_SAMPLES_MIN`` is a ``ValueError``.

    The samples of a logging gap the loader filled (the voltage a straight line between the logged ones, the
    current held) are simulated through, never fitted or scored: the Panasonic -10 degC US06 file, logged every
    60 s for its first two hours, is 68 % filled at 1 s, and its diagnosis scored those lines as measured, with a
    white-noise level of 0.00 mV."""
    lo, hi = cfg.soc_window
    m = (s.soc >= lo) & (s.soc <= hi)
    gaps = s.logged is not None and not s.logged.all()
    if gaps:
        m &= s.logged
    if m.sum() < WINDOW_SAMPLES_MIN:
        bounds = [f"at least {lo:g}"] * (lo > 0.0) + [f"at most {hi:g}"] * (hi < 1.0)
        where = f" with the counted SOC {' and '.join(bounds)}" if bounds else ""
        raise ValueError(f"only {int(m.sum())} {'logged ' if gaps else ''}samples{where}; a diagnosis needs "
                         f"{WINDOW_SAMPLES_MIN}")
    return m


def scored_folds(target: Series, cfg: DiagnoseConfig, *, validation: bool) -> tuple[np.ndarray, np.ndarray]:
    """Block index and fold of every sample of the file that is scored (``target``), fold ``-1`` where it
    is not scored; fewer than ``WINDOW_SAMPLES_MIN`` scored samples is a ``ValueError``.

    Scored are the samples inside ``cfg.soc_window`` (:func:`window_mask`) and, when ``target`` is the
    file the models are fitted on (cross-validation, ``validation=False``), outside its first block
    (:func:`fold_blocks`: it tests the initial conditions, it is trained on and never scored).  A window
    that the file's counted SOC passes only during that block leaves nothing to score (the Panasonic
    cycle_1 at 0.95-0.99: the out-of-sample errors were means of nothing and the score divided by zero).
    """
    blocks, fold_of = fold_blocks(len(target), target.dt_s, cfg)
    if validation:
        fold_of = np.maximum(fold_of, 0)  # nothing was fitted on the validation file: score all of it
    fold_of = np.where(window_mask(target, cfg), fold_of, -1)
    n = int(np.count_nonzero(fold_of >= 0))
    if n < WINDOW_SAMPLES_MIN:
        lo, hi = cfg.soc_window
        bounds = [f"at least {lo:g}"] * (lo > 0.0) + [f"at most {hi:g}"] * (hi < 1.0)
        where = f" with the counted SOC {' and '.join(bounds)}" if bounds else ""
        after = "" if validation else (f" after the first {np.count_nonzero(blocks == 0) * target.dt_s:.0f} s "
                                       "(the start, trained on and never scored)")
        raise ValueError(f"only {n} samples{where}{after} to score; a diagnosis needs {WINDOW_SAMPLES_MIN}")
    return blocks, fold_of


def tau_int(r: np.ndarray, c: float = 5.0) -> float:
    """Integrated autocorrelation time of ``r`` in samples (Sokal's automatic window, ``M >= c tau``)."""
    x = np.asarray(r, dtype=float)
    x = x[np.isfinite(x)]
    n = x.size
    if n < 8:
        return 1.0
    x = x - x.mean()
    f = np.fft.rfft(x, 2 * n)
    acf = np.fft.irfft(f * np.conj(f))[:n]
    if acf[0] <= 0:
        return 1.0
    rho = acf / acf[0]
    taus = 1.0 + 2.0 * np.cumsum(rho[1:])
    m = np.arange(1, n)
    ok = np.flatnonzero(m >= c * taus)
    t = taus[ok[0]] if ok.size else taus[-1]
    return float(min(max(t, 1.0), n))


def noise_level(r: np.ndarray, mask: np.ndarray | None = None) -> float:
    """White-noise RMS of a residual: ``1.4826 MAD(diff r) / sqrt(2)`` (slow trends and steps barely move it),
    over the steps between two neighbours both in ``mask`` (None: every step)."""
    d = np.diff(np.asarray(r, dtype=float))
    if mask is not None:
        d = d[mask[1:] & mask[:-1]]
    d = d[np.isfinite(d)]
    if d.size < 2:
        return float("nan")
    return float(1.4826 * np.median(np.abs(d - np.median(d))) / np.sqrt(2.0))


def _lif_start(s: Series, method: str) -> dict:
    run = run_identification(s.current_a, s.voltage_v, s.soc, s.ocv, s.capacity_ah, s.dt_s,
                             IdentifierConfig(method=method))
    sel = run.identified & (s.soc > 0.2) & (s.soc < 0.9)
    if sel.sum() < 10:
        sel = run.identified
    if sel.sum() < 10:
        return {}
    med = {k: float(np.median(v[sel])) for k, v in run.params.items()}
    sim = simulate_with_params(s.current_a, s.soc, s.ocv, run.params, s.dt_s)
    med["sim_rmse_mv"] = float(1e3 * np.sqrt(np.mean((sim - s.voltage_v) ** 2)))
    med["rejections"] = int(run.rejections)
    return med


def _params_json(fit: Fit) -> dict:
    return {k: ([float(x) for x in v] if isinstance(v, list) else float(v)) for k, v in fit.params().items()}


@dataclass
class _Scored:
    mse: float
    mse_f: np.ndarray  # per fold
    n_eff: float
    mse_b: np.ndarray  # per held-out block


class _Scorer:
    """Out-of-sample predictions and statistics, shared by the singles and the pair stage."""

    def __init__(self, s: Series, validate: Series | None, config: DiagnoseConfig):
        self.s, self.validate, self.config = s, validate, config
        self.window = window_mask(s, config)
        target = validate if validate is not None else s
        blocks, fold_of = scored_folds(target, config, validation=validate is not None)
        self.blocks, self.fold_of = blocks, fold_of
        self.keep = fold_of >= 0
        self.fk = fold_of[self.keep]
        cnt = np.bincount(self.fk, minlength=config.folds).astype(float)
        self.used = cnt > 0  # folds with samples inside the SOC window
        self.cnt = np.maximum(cnt, 1.0)
        self.scored = target

    def oos(self, model: Model, full: Fit) -> np.ndarray:
        s, cfg = self.s, self.config
        if self.validate is not None:
            return model.predict(self.validate, full)
        out = np.full(len(s), np.nan)
        for k in range(cfg.folds):
            held = self.fold_of == k
            fk = fit_model(model, s, mask=~held & self.window, start=dict(full.theta), cfg=full.cfg, grid=False,
                           max_iter=cfg.max_iter_fold)
            out[held] = model.predict(s, fk)[held]
        return out

    def stats(self, pred: np.ndarray) -> _Scored:
        r = (self.scored.voltage_v - pred)[self.keep]
        mse_f = np.bincount(self.fk, weights=r * r, minlength=self.config.folds) / self.cnt
        mse_f = np.maximum(mse_f[self.used], 1e-30)
        bk = self.blocks[self.keep]
        nb = int(self.blocks.max()) + 1
        cb = np.bincount(bk, minlength=nb).astype(float)
        mse_b = np.bincount(bk, weights=r * r, minlength=nb)[cb > 0] / cb[cb > 0]
        return _Scored(max(float(np.mean(r * r)), 1e-30), mse_f, len(r) / tau_int(r), np.maximum(mse_b, 1e-30))

    def compare(self, ref: _Scored, new: _Scored, k: int, noise_mv: float) -> dict:
        cfg = self.config
        score = float(np.log(ref.mse / new.mse) - cfg.penalty * k / new.n_eff)
        t_stat = _t_stat(np.log(ref.mse_f / new.mse_f))
        explained = float(1e3 * np.sqrt(max(ref.mse - new.mse, 0.0)))
        sig = bool(score > 0 and t_stat >= cfg.t_min and explained >= cfg.noise_fraction * noise_mv)
        return {"score": score, "t_stat": t_stat, "explained_mv": explained, "significant": sig,
                "rmse_mv": float(1e3 * np.sqrt(new.mse)),
                "gain_pct": float(100.0 * (1.0 - np.sqrt(new.mse / ref.mse)))}


def _t_stat(d: np.ndarray) -> float:
    """``mean(d) / (std(d) / sqrt(n))``; +-inf for a spread-free sign, 0 with fewer than 2 values."""
    if d.size < 2:
        return 0.0
    sd = float(np.std(d, ddof=1))
    m = float(np.mean(d))
    if sd > 0:
        return m / (sd / np.sqrt(d.size))
    return np.inf if m > 0 else (-np.inf if m < 0 else 0.0)


def _insample_score(fit_ref: Fit, fit_new: Fit, r_new: np.ndarray, penalty: float) -> float:
    n_eff = r_new.size / tau_int(r_new)
    return float(2.0 * np.log(fit_ref.train_rmse_mv / fit_new.train_rmse_mv)
                 - penalty * (fit_new.extra - fit_ref.extra) / n_eff)


# --------------------------------------------------------------------------- main


def diagnose(
    data: Series,
    *,
    validate: Series | None = None,
    config: DiagnoseConfig = DiagnoseConfig(),
) -> Diagnosis:
    """Name what the 2-RC model gets wrong on ``data`` (see the module docstring).

    Runs with one BLAS thread (:mod:`._blas`): the products are small and threads only cost.
    """
    with single_blas_thread():
        return _diagnose(data, validate, config)


def _diagnose(data: Series, validate: Series | None, config: DiagnoseConfig) -> Diagnosis:
    t_start = time.perf_counter()
    s = data
    lif: dict = {}
    starts: list[dict | None] = [None]
    if config.lif:
        lif = _lif_start(s, config.method)
        if lif:
            starts.insert(0, {"tau1_s": lif["tau1_s"], "tau2_s": lif["tau2_s"]})
    win = window_mask(s, config)
    mask = None if win.all() else win
    scorer = _Scorer(s, validate, config)  # (before the fits: too little to score is a ValueError, scored_folds)
    base: Fit | None = None
    for st in starts:
        f = fit_model(BASELINE, s, mask=mask, start=st, max_iter=config.max_iter)
        if base is None or f.train_rmse_mv < base.train_rmse_mv:
            base = f
    assert base is not None
    taus = {"tau1_s": base.theta["tau1_s"], "tau2_s": base.theta["tau2_s"]}

    models: dict[str, Model] = {"none": BASELINE}
    notes: dict[str, str] = {}
    for c in config.candidates:
        m = Model(c)
        why = m.applicable(s) or (m.applicable(validate) if validate is not None else None)
        if why:
            notes[c] = why.split(": ", 1)[-1]
        else:
            models[c] = m
    fits: dict[str, Fit] = {"none": base}
    for c, m in models.items():
        if c != "none":
            fits[c] = fit_model(m, s, mask=mask, start=dict(taus), max_iter=config.max_iter)
    predictions = {c: models[c].predict(s, f) for c, f in fits.items()}

    oos = {c: scorer.oos(models[c], f) for c, f in fits.items()}
    stats = {c: scorer.stats(p) for c, p in oos.items()}
    ref = stats["none"]
    res0 = scorer.scored.voltage_v - (predictions["none"] if validate is None else oos["none"])
    noise_mv = 1e3 * noise_level(res0, window_mask(scorer.scored, config))
    cands: list[Candidate] = []
    for c in config.candidates:
        if c not in fits:
            cands.append(Candidate(c, float("nan"), float("nan"), 0.0, float("-inf"), 0.0, 0.0,
                                   FEATURES[c].extra, False, {}, notes.get(c, "")))
            continue
        cmp = scorer.compare(ref, stats[c], fits[c].extra, noise_mv)
        cands.append(Candidate(c, cmp["rmse_mv"], cmp["gain_pct"], cmp["explained_mv"], cmp["score"], cmp["t_stat"],
                               stats[c].n_eff, fits[c].extra, cmp["significant"], _params_json(fits[c]),
                               notes.get(c, "")))
    sig = [c for c in cands if c.significant]
    winner = max(sig, key=lambda c: c.score).cause if sig else "none"

    def ties_of(w: str) -> list[str]:
        # significant candidates the named one does not beat block by block: indistinguishable here
        return [c.cause for c in sig if c.cause != w
                and _t_stat(np.log(stats[c.cause].mse_b / stats[w].mse_b)) < config.t_min]

    secondary, joint = None, {}
    if winner != "none" and config.pairs and len(fits) > 2:
        # partners that predict what the first choice predicts (within a quarter of what it explains)
        # only trade off against it in a joint fit
        first = next(c for c in cands if c.cause == winner)
        keep = scorer.keep
        dup = {c.cause for c in sig if c.cause != winner and
               1e3 * np.sqrt(np.mean((oos[c.cause] - oos[winner])[keep] ** 2)) < 0.25 * first.explained_mv}
        winner, secondary, joint = _pair_stage(s, winner, fits, models, scorer, stats, noise_mv, predictions,
                                               oos, config, exclude=dup)
    base_rmse = float(1e3 * np.sqrt(ref.mse))
    wc = next((c for c in cands if c.cause == winner), None)
    ties = [c for c in ties_of(winner) if c != secondary] if wc is not None else []
    return Diagnosis(
        cause=winner,
        baseline_rmse_mv=base_rmse,
        extended_rmse_mv=wc.rmse_mv if wc else base_rmse,
        gain_pct=wc.gain_pct if wc else 0.0,
        candidates=cands,
        baseline_params=_params_json(base),
        noise_mv=float(noise_mv),
        scoring=("validation file" if validate is not None else
                 f"{config.folds}-fold cross-validation over {int(scorer.blocks.max()) + 1} interleaved time blocks")
        + ("" if win.all() else f", SOC window {max(config.soc_window[0], 0.0):g}..{min(config.soc_window[1], 1.0):g}"),
        seconds=time.perf_counter() - t_start,
        secondary=secondary,
        ties=ties,
        joint=joint,
        lif=lif,
        series=s,
        scored=scorer.scored,
        fits=fits,
        predictions=predictions,
        oos=oos,
    )


def _pair_stage(s, first, fits, models, scorer, stats, noise_mv, predictions, oos, config, exclude=frozenset()):
    """Step 6 of the module docstring; returns (cause, secondary, joint-info).

    ``exclude``: candidates whose out-of-sample prediction is that of ``first`` to within a
    quarter of what ``first`` explains: they explain the same signal, and as its partner
    they would only trade off against it.
    """
    pair_fits: dict[tuple[str, str], tuple[Model, Fit, float]] = {}

    def pair(a: str, b: str):
        key = tuple(sorted((a, b)))
        if key not in pair_fits:
            m = Model(a, b)
            start = dict(fits[b].theta)
            start.update(fits[a].theta)
            f = fit_model(m, s, mask=scorer.window if not scorer.window.all() else None, start=start, grid=False,
                          max_iter=config.max_iter)
            r = (s.voltage_v - m.predict(s, f))[scorer.window]
            pair_fits[key] = (m, f, _insample_score(fits[first], f, r, config.penalty))
        return pair_fits[key]

    others = [c for c in fits if c not in ("none", first) and c not in exclude and "+" not in c]
    if not others:
        return first, None, {}
    best = max(others, key=lambda c: pair(first, c)[2])
    best_key = tuple(sorted((first, best)))
    # swap: maybe `first` only absorbed part of the other effect; try the partner with everything else
    swap = [c for c in others if c != best]
    if swap:
        alt = max(swap, key=lambda c: pair(best, c)[2])
        if pair(best, alt)[2] > pair_fits[best_key][2]:
            best_key = tuple(sorted((best, alt)))
    # a twin of `first` (same signal alone) may fit better next to the partner: with the other
    # effect accounted for, what told the twins apart is no longer masked by it
    if first in best_key:
        partner = best_key[0] if best_key[1] == first else best_key[1]
        for t in sorted(exclude):
            if t != partner and pair(t, partner)[2] > pair_fits[best_key][2]:
                best_key = tuple(sorted((t, partner)))
    m, f, _ = pair_fits[best_key]
    # the pair against the best of its members and the first choice alone, out of sample
    ref_name = min(set(best_key) | {first}, key=lambda c: stats[c].mse)
    p_oos = scorer.oos(m, f)
    p_stats = scorer.stats(p_oos)
    cmp = scorer.compare(stats[ref_name], p_stats, f.extra - fits[ref_name].extra, noise_mv)
    comps = m.components(s, f, scorer.window)
    joint = {
        "causes": list(best_key),
        "rmse_mv": cmp["rmse_mv"],
        "gain_pct": float(100.0 * (1.0 - np.sqrt(p_stats.mse / stats["none"].mse))),
        "gain_over_single_pct": cmp["gain_pct"],
        "score": cmp["score"],
        "t_stat": cmp["t_stat"],
        "explained_mv": cmp["explained_mv"],
        "significant": cmp["significant"],
        "components_mv": comps,
        "params": _params_json(f),
    }
    fits[m.name] = f
    predictions[m.name] = m.predict(s, f)
    oos[m.name] = p_oos
    if not cmp["significant"]:
        return first, None, joint
    a, b = sorted(best_key, key=lambda c: -comps[c])
    return a, b, joint
