"""SOP back-test on a recording: the online estimator's voltage prediction and limits against what the cell did.

The online estimator (core.soc.SocEstimator + core.sox.SoxEstimator, one cell) runs
over the recording sample by sample.  Windows of ``n = horizon_s / Ts`` samples:

* HPPC file (at least 3 pulses found as long as the window: a current run of ``n`` samples
  to ``MAX_PULSE_S`` after at least ``MIN_REST_S`` of rest): one window at every such pulse
  onset, its first ``n`` samples (shorter pulses are skipped);
* otherwise: consecutive windows every ``n`` samples of the whole file.

Only pulses the windows can score decide: a current sensor's noise crossing the rest
threshold (``REST_C``, C/50) inside a rest is a run of a sample or two after a rest, and
a drive cycle that ends in a rest read with 20 mA of noise on a 2.5 Ah cell (C/125) had
ten such "pulses", was taken for an HPPC file and refused ("no pulse of the recording is
as long as the horizon").  An HPPC file given a horizon longer than its pulses is so
back-tested by drive windows; ``mode="hppc"`` still refuses a file without such a pulse.

At the start ``a`` of each window (the estimator has seen the samples before ``a``):

    predicted   v_hat = v(D, I_w) of core.sop, I_w = the window's mean current, D = n Ts, with R_D
                corrected by what the cell's own earlier current steps showed it to miss
                (core.sop_residual; ``residual=ResidualConfig(enabled=False)``: the model alone)
    measured    v     = the voltage of the window's last sample;   error = v_hat - v
                (scored over the windows under load, |I_w| >= REST_C C: a rest is predicted trivially)
    limits      I_dis, I_chg at D (Plett's model with its model-error margin, and the HPPC
                static-resistance baseline without one)
    within      every sample's current of the window is within [-I_dis, I_chg]
    exceeded    within, and some sample's voltage of the window is past v_min or v_max

Under a current within the limits at every instant, the model says the voltage stays
inside the bounds over the whole window (the constant limit current is the worst
case), so an exceedance is the model's failure, not the driver's.

Logging gaps (``rest_over_gaps``, the default)
----------------------------------------------
A recording on a resampled grid marks the bins that held no sample of the file
(``unlogged``: :attr:`CellRecording.filled <bms_estimator.data.CellRecording.filled>`).
A run of them longer than the sampler's :data:`~bms_estimator.gaps.MAX_GAP_S`
(:func:`~bms_estimator.gaps.logging_gaps`; which samples are fed and the rests before them
are :func:`bms_estimator.gaps.rest_plan`'s, as for ``soc`` and the SOC matrix) is what the
service sees as a time jump: the logger was off,
and whatever the cell did meanwhile (the HPPC files' SOC steps) is not in the file.
The back-test does what the service does there: the bins of the run are not fed
(no update), and before the first sample after it the estimator rests over the
time without samples, ``T = gap_before_s`` of the samples either side (= the run's
length), ``core.sox.rest_estimators`` (SOX, then SOC: the service pipeline's order;
a rest of ``rest_relaxation_s`` or longer reads the SOC from the OCV at the next
sample at rest).  A window is scored only if none of its samples, nor the sample
before it (the state the prediction is made from, which the service would have
published), lies in such a run, and no rest falls inside it: a window across a gap is
not scored.  A file not resampled (logged at the grid's step or coarser) has no
filled bins; a jump of its time axis longer than ``MAX_GAP_S`` is rested over the
same way.  Shorter runs (the HPPC files' 1.2 s holes at the pulse edges) the service
bridges with stale samples; they are fed as ``load_recording`` filled them.  ``rest_over_gaps=False``
feeds every bin, the gaps as if contiguous samples.

The energy delivered to the end counts the file's own charge only (every bin's
``-v i Ts``, the gap bins' held current included, as ``load_recording``'s coulomb
count): the charge taken out inside a logging gap is not in the file, so on the
HPPC files it is short of what the cell delivered.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from .core.soc import SocConfig, SocEstimator
from .core.soe import SoeConfig, energy_left_wh
from .core.sop import SopConfig, predict_voltage, sop_limits
from .core.sop_residual import ResidualConfig
from .core.sox import SoxConfig, SoxEstimator, rest_estimators
from .gaps import rest_plan

__all__ = ["BacktestResult", "find_pulses", "run_backtest", "summary"]

MIN_REST_S = 60.0  # rest before a pulse
MAX_PULSE_S = 60.0  # a longer current run is not a pulse
REST_C = 0.02  # |i| below this C-rate is rest


@dataclass(frozen=True)
class BacktestResult:
    """One row per window."""

    mode: str  # "hppc" or "drive"
    horizon_s: float
    start_s: np.ndarray
    current_a: np.ndarray  # the window's mean current
    soc: np.ndarray  # estimated SOC at the start
    temperature_c: np.ndarray
    v_pred: np.ndarray
    v_meas: np.ndarray
    v_min_meas: np.ndarray  # the lowest / highest voltage of the window
    v_max_meas: np.ndarray
    i_dis_a: np.ndarray  # model limits at the horizon
    i_chg_a: np.ndarray
    i_dis_hppc_a: np.ndarray
    i_chg_hppc_a: np.ndarray
    within: np.ndarray  # the window's current stayed within the model limits
    exceeded: np.ndarray
    within_hppc: np.ndarray
    exceeded_hppc: np.ndarray
    capacity_ah: float  # the estimator's capacity at the end
    energy_left_wh: np.ndarray  # SOE at the start, at the recent mean discharge rate (core.soe)
    energy_to_end_wh: np.ndarray  # what the cell then delivered to the recording's end
    #: v_min -> (within, exceeded) of the model limits computed for that v_min
    by_v_min: dict = None  # type: ignore[assignment]
    logging_gaps: int = 0  # logging gaps rested over (module docstring)
    rested_s: float = 0.0  # their total length
    windows_across_gaps: int = 0  # windows not scored because they span (or start right after) one

    @property
    def error_mv(self) -> np.ndarray:
        return 1e3 * (self.v_pred - self.v_meas)


def find_pulses(current_a: np.ndarray, dt_s: float, capacity_ah: float) -> list[tuple[int, int]]:
    """(start, end) sample ranges of the pulses (module docstring)."""
    i = np.asarray(current_a, dtype=float)
    rest = np.abs(i) < REST_C * capacity_ah
    out = []
    k, n = 0, len(i)
    min_rest = int(round(MIN_REST_S / dt_s))
    max_len = int(round(MAX_PULSE_S / dt_s))
    run_rest = 0
    while k < n:
        if rest[k]:
            run_rest += 1
            k += 1
            continue
        b = k
        while b < n and not rest[b]:
            b += 1
        if run_rest >= min_rest and b - k <= max_len and b < n:
            out.append((k, b))
        run_rest = 0
        k = b
    return out


def run_backtest(current_a, voltage_v, temperature_c, dt_s: float, ocv, capacity_ah: float, *,
                 horizon_s: float = 10.0, initial_soc: float | None = 1.0, soc_config: SocConfig = SocConfig(),
                 sop_config: SopConfig | None = None, mode: str = "auto",
                 extra_v_min: tuple[float, ...] = (), residual: ResidualConfig = ResidualConfig(),
                 time_s=None, unlogged=None, rest_over_gaps: bool = True) -> BacktestResult:
    """Run the estimator over the recording and score every window (module docstring).

    ``extra_v_min``: further cut-offs to compute the model's discharge limits for and check.
    ``time_s``: the samples' times (None: ``k dt_s``); ``unlogged``: per sample, True where the file logged
    nothing (``CellRecording.filled``; None: every sample logged).  With ``rest_over_gaps`` the estimator
    rests over the :func:`logging_gaps` of ``unlogged`` instead of being fed them, and over a jump of
    ``time_s`` longer than the sampler bridges (a file logged at its own step, not resampled) (module
    docstring, "Logging gaps").
    """
    i = np.asarray(current_a, dtype=float)
    v = np.asarray(voltage_v, dtype=float)
    temp = None if temperature_c is None else np.asarray(temperature_c, dtype=float)
    n_all = len(i)
    n_w = int(round(horizon_s / dt_s))
    if n_w < 1:
        raise ValueError(f"--horizon-s {horizon_s:g} is shorter than one sample ({dt_s:g} s)")
    if n_w >= n_all:
        raise ValueError(f"--horizon-s {horizon_s:g} is longer than the recording ({n_all * dt_s:.0f} s)")
    # the logging gaps: not fed, rested over before the next sample (module docstring; gaps.rest_plan)
    plan = rest_plan(n_all, dt_s, unlogged=unlogged, time_s=time_s, rest_over_gaps=rest_over_gaps)
    skip = ~plan.fed
    rest_before = plan.rest_before_s
    starts = [a for a, b in find_pulses(i, dt_s, capacity_ah) if b - a >= n_w]  # the pulses a window scores
    use_pulses = mode == "hppc" or (mode == "auto" and len(starts) >= 3)
    if use_pulses:
        if not starts:
            raise ValueError(f"no pulse of the recording is as long as the horizon ({horizon_s:g} s)")
    else:
        starts = list(range(1, n_all - n_w + 1, n_w))
    # a window is scored only if neither it nor the sample before it lies in a logging gap, and no rest
    # falls inside it (its first sample, or a later one, the first after a gap)
    skipped = np.r_[0, np.cumsum(skip)]  # skipped[k] = skipped samples among 0..k-1
    rested = np.r_[0, np.cumsum(rest_before > 0)]
    spans = [skipped[a + n_w] - skipped[max(a - 1, 0)] + rested[a + n_w] - rested[a] > 0 for a in starts]
    across = [a for a, x in zip(starts, spans) if x]
    starts = [a for a, x in zip(starts, spans) if not x]
    if not starts:
        raise ValueError("every window of the recording spans a logging gap: none can be scored")
    d = n_w * dt_s
    sop_cfg = sop_config or SopConfig()
    sop_cfg = replace(sop_cfg, horizons_s=(d,))
    est = SocEstimator(1, ocv, capacity_ah, dt_s, initial_soc=initial_soc, config=soc_config)
    sox = SoxEstimator(1, dt_s, SoxConfig(sop=sop_cfg, residual=residual))
    rows: dict[str, list[float]] = {k: [] for k in (
        "start_s", "current_a", "soc", "temperature_c", "v_pred", "v_meas", "v_min_meas", "v_max_meas",
        "i_dis_a", "i_chg_a", "i_dis_hppc_a", "i_chg_hppc_a", "energy_left_wh")}
    extra = {vm: [] for vm in extra_v_min}
    start_set = set(starts)
    v1 = np.empty(1)
    t1 = None if temp is None else np.empty(1)
    for k in range(n_all):
        if skip[k]:
            continue
        if rest_before[k]:  # the first sample after a logging gap: rest over it, as the service's pipeline
            rest_estimators(est, sox, float(rest_before[k]))
        if k in start_set and np.isfinite(sox.v_anchor[0]):
            ocv_f, slope_f = sox.ocv_functions(est)
            kw = sox.model(est)
            seg = slice(k, k + n_w)
            i_w = float(np.mean(i[seg]))
            dr = sox.residual.correction(kw["soc"])  # the learnt R_D correction, (2, 1): discharge, charge
            dr_w = None if dr is None else dr[0 if i_w < 0 else 1]
            v_hat = float(predict_voltage(np.array([i_w]), d, ocv=ocv_f, dr_ohm=dr_w, **kw)[0])
            lim = sop_limits(temperature_c=est.temperature_c, ocv=ocv_f, docv_dsoc=slope_f, config=sop_cfg,
                             v_margin=sox.v_margin, dr_ohm=dr, **kw)
            base = sop_limits(temperature_c=est.temperature_c, ocv=ocv_f, docv_dsoc=slope_f, config=sop_cfg,
                              method="hppc", **kw)
            for vm in extra:
                cfg_vm = replace(sop_cfg, v_min=vm)
                extra[vm].append(float(sop_limits(temperature_c=est.temperature_c, ocv=ocv_f, docv_dsoc=slope_f,
                                                  config=cfg_vm, v_margin=sox.v_margin, dr_ohm=dr,
                                                  **kw).discharge_a[0, 0]))
            rate = max(-float(sox.mean_current_a[0]), 0.0) / float(kw["capacity_ah"][0])
            e_left, _ = energy_left_wh(kw["soc"], kw["capacity_ah"], kw["r0_ohm"] + kw["r_ohm"].sum(axis=1),
                                       lambda z: ocv_f(z), v_min=sop_cfg.v_min, config=SoeConfig(rate_c=rate))
            for key, val in (("start_s", k * dt_s), ("current_a", i_w), ("soc", kw["soc"][0]),
                             ("temperature_c", est.temperature_c[0]), ("v_pred", v_hat), ("v_meas", v[k + n_w - 1]),
                             ("v_min_meas", np.min(v[seg])), ("v_max_meas", np.max(v[seg])),
                             ("i_dis_a", lim.discharge_a[0, 0]), ("i_chg_a", lim.charge_a[0, 0]),
                             ("i_dis_hppc_a", base.discharge_a[0, 0]), ("i_chg_hppc_a", base.charge_a[0, 0]),
                             ("energy_left_wh", e_left[0])):
                rows[key].append(float(val))
        v1[0] = v[k]
        if t1 is not None:
            t1[0] = temp[k]
        est.update(i[k], v1, temperature_c=t1)
        sox.update(est, i[k], v1)  # track, and the SOP whose basis the learnt correction needs
    if not rows["start_s"]:
        raise ValueError("no window could be scored (the voltage is never finite before a window)")
    r = {k: np.asarray(x) for k, x in rows.items()}
    starts_k = np.round(r["start_s"] / dt_s).astype(int)
    i_max = np.array([np.max(i[a:a + n_w]) for a in starts_k])
    i_min = np.array([np.min(i[a:a + n_w]) for a in starts_k])

    def check(i_dis, i_chg):
        within = (-i_min <= i_dis + 1e-9) & (i_max <= i_chg + 1e-9)
        past = (r["v_min_meas"] < sop_cfg.v_min) | (r["v_max_meas"] > sop_cfg.v_max)
        return within, within & past

    w, e = check(r["i_dis_a"], r["i_chg_a"])
    wh, eh = check(r["i_dis_hppc_a"], r["i_chg_hppc_a"])
    by_v_min = {}
    for vm, lims in extra.items():
        lim = np.asarray(lims)
        within_vm = -i_min <= lim + 1e-9
        by_v_min[vm] = (within_vm, within_vm & (r["v_min_meas"] < vm))
    # energy delivered from each window's start to the end (positive = out of the cell): the file's own
    # charge only (module docstring), the same with and without rest_over_gaps
    e_out = -np.nan_to_num(v * i) * dt_s / 3600.0
    tail = np.cumsum(e_out[::-1])[::-1]
    return BacktestResult("hppc" if use_pulses else "drive", d, within=w, exceeded=e, within_hppc=wh,
                          exceeded_hppc=eh, capacity_ah=float(est.capacity_ah[0]), energy_to_end_wh=tail[starts_k],
                          by_v_min=by_v_min, logging_gaps=plan.gaps, rested_s=plan.rested_s,
                          windows_across_gaps=len(across), **r)


def _stats(x: np.ndarray) -> dict[str, float]:
    x = x[np.isfinite(x)]
    if x.size == 0:
        return {"median": float("nan"), "p95": float("nan"), "n": 0}
    return {"median": float(np.median(x)), "p95": float(np.percentile(x, 95)), "n": int(x.size)}


def summary(res: BacktestResult, capacity_stated_ah: float | None = None) -> dict:
    """The command's JSON: the issue's keys first, then the breakdowns (C-rates of the stated
    capacity when given, else of the estimated one)."""
    q = capacity_stated_ah or (res.capacity_ah if res.capacity_ah > 0 else 1.0)
    # the voltage error is scored over the windows under load (a rest window is predicted trivially)
    loaded = np.abs(res.current_a) >= REST_C * q
    err = np.abs(res.error_mv)[loaded]
    n = len(res.error_mv)
    out = {
        "windows": n,
        "voltage_error_mv": {k: v for k, v in _stats(err).items() if k != "n"},
        "windows_loaded": int(np.count_nonzero(loaded)),
        "limit_exceeded_pct": float(100.0 * np.count_nonzero(res.exceeded) / n),
        "mode": res.mode,
        "horizon_s": res.horizon_s,
        "signed_error_mv": {k: v for k, v in _stats(res.error_mv[loaded]).items() if k != "n"},
        "windows_within_limit": int(np.count_nonzero(res.within)),
        "limit_exceeded": int(np.count_nonzero(res.exceeded)),
        "hppc_method": {
            "windows_within_limit": int(np.count_nonzero(res.within_hppc)),
            "limit_exceeded": int(np.count_nonzero(res.exceeded_hppc)),
            "limit_exceeded_pct": float(100.0 * np.count_nonzero(res.exceeded_hppc) / n),
        },
        "discharge_limit_a": {"model": _stats(res.i_dis_a), "hppc": _stats(res.i_dis_hppc_a)},
        "capacity_ah_estimated": res.capacity_ah,
        "logging_gaps": {"rested": res.logging_gaps, "rested_s": res.rested_s,
                         "windows_not_scored": res.windows_across_gaps},
    }
    # breakdowns of the loaded windows: by SOC decile and C-rate (of the window's mean current)
    soc = res.soc[loaded]
    by_soc = {}
    for lo in np.arange(0.0, 1.0, 0.1):
        m = (soc >= lo) & (soc < lo + 0.1 + (1e-9 if lo >= 0.9 else 0))
        if m.any():
            by_soc[f"{lo:.1f}-{lo + 0.1:.1f}"] = _stats(err[m])
    by_rate = {}
    c = np.abs(res.current_a[loaded]) / q
    for lo, hi in ((0, 0.75), (0.75, 1.5), (1.5, 3.0), (3.0, 5.0), (5.0, 100.0)):
        m = (c >= lo) & (c < hi)
        if m.any():
            by_rate[f"{lo:g}-{hi:g}C"] = _stats(err[m])
    out["abs_error_mv_by_soc"] = by_soc
    out["abs_error_mv_by_c_rate"] = by_rate
    out["temperature_c_median"] = float(np.nanmedian(res.temperature_c))
    for vm, (w, e) in (res.by_v_min or {}).items():
        out.setdefault("limit_exceeded_at_v_min", {})[f"{vm:g}"] = {
            "windows_within_limit": int(np.count_nonzero(w)), "limit_exceeded": int(np.count_nonzero(e)),
            "limit_exceeded_pct": float(100.0 * np.count_nonzero(e) / n)}
    return out
