"""One drive (or one vehicle's drives, chained) from log file to per-drive Parquet and summary rows.

This is the unit of work :mod:`.batch` hands to Dask: plain arguments in (paths, the
configuration file, the output directory), small picklable results out; the Parquet is
written by the worker. The data path is the service's, in bulk form::

    read_frames (frames.py) -> decode_frames (decode.py) -> assemble_samples (assemble.py)
      -> estimate_drive (estimate.py, the service's Pipeline.tick) -> Parquet

Decoder, sampler and estimator are built by :class:`~bms_estimator.service.daemon.Service`
from the same configuration the service runs with (so its checks and defaults apply), once
per worker process and configuration file.

A single-cell recording in the project's CSV layout (``.csv``/``.csv.gz``,
``time_s,current_a,voltage_v[,temperature_c]``, as the offline commands read) is a drive of
a one-cell pack: its 1 s bins are the samples (:meth:`.samples.SampleArrays.from_recording`),
the estimator is the configuration's with ``n_cells = 1``.

SOP/SOE/SOH (``sox=True``, ``batch --sox``): each drive also runs the service's
:class:`~bms_estimator.core.sox.SoxEstimator` (built by the service, as the daemon builds its
own) after the estimator, sample by sample (:func:`.estimate.estimate_drive`); its per-cell
outputs go to the Parquet (:attr:`SoxEstimator.output_keys`) and the summary gets per cell the
final capacity and resistance SOH (the capacity SOH with its 1-sigma; the core has none for the
resistance SOH), the final energy left (SOE) and the energy out and in during the drive. The pack
figures the service publishes (``SoxEstimator.pack_outputs``, the pack payload's keys) go per
sample to ``<log>.pack.parquet`` beside the drive's Parquet (:func:`pack_parquet_path`), and the
summary gets per drive :data:`PACK_SUMMARY` (the same values on each of the drive's cell rows). Chained,
the SOX state is carried with the estimator's (the daemon's state file layout,
:func:`~bms_estimator.service.state.resume_sox`) and rested over the time between drives.
Unchained drives with SOX are stacked like those without (:func:`run_drives`): the stacked SOX
part keeps them apart (:meth:`~bms_estimator.core.sox.SoxEstimator.set_groups`), so each drive's
limits, energy, health and pack figures are those it has alone, bit for bit.

A drive is reported and skipped (never fatal to the batch) when its log is unreadable or
corrupt, empty, holds no frame the configured DBC and mapping decode (another DBC), or
its timestamps go back by more than the sampler's rewind limit (a reset; a chained state
would be wrong). Timestamps going back by less are the service's ``backward_frames``:
counted and shown, the drive is used.
"""

from __future__ import annotations

import json
import math
import time
import warnings
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import structlog

from ..core.soc import SocEstimator, voltage_line_capacity_ah
from ..core.sox import SoxEstimator
from ..data import check_charge_span, load_recording
from ..errors import BmsEstimatorError, DataError, one_line_error
from ..scoring import counted_soc, soc_error_figures
from ..service.state import resume_sox
from .assemble import assemble_samples
from .decode import decode_frames
from .estimate import DriveEstimate, carry_state, estimate_drive, rest_between_drives
from .frames import read_frames
from .samples import SampleArrays
from .stack import StackError, estimate_stacked

__all__ = ["DriveResult", "PACK_SUMMARY", "drive_order_key", "run_drive", "run_drives", "run_vehicle",
           "pack_parquet_path", "parquet_path", "service_for"]

#: per-cell series written to each drive's Parquet (besides t_s, cell, valid, current_a)
PARQUET_KEYS = ("soc", "r0_ohm", "r1_ohm", "c1_f", "r2_ohm", "c2_f", "tau1_s", "tau2_s", "c0_v", "capacity_ah",
                "temperature_c", "voltage_v")

#: per-cell summary values of a drive with SOX (its last sample's value, or the change over the drive) -> the
#: SoxEstimator output (or energy counter) it is read from
SOX_SUMMARY = {"soh_capacity_final": "soh_capacity", "soh_capacity_sigma_final": "soh_capacity_sigma",
               "soh_resistance_final": "soh_resistance", "energy_left_wh_final": "energy_left_wh",
               "energy_discharged_wh": "energy_discharged_wh", "energy_charged_wh": "energy_charged_wh"}

#: per-drive pack summary values with SOX -> (the pack_outputs key, how a drive's series becomes one value:
#: "final" its last sample's, "min" its least over the samples, NaN before the first update left out) or, for
#: the energy in and out, the drive's pack_energy_wh key. The limit is the 10 s horizon's (sop.horizons_s;
#: NaN where it is not configured).
PACK_SUMMARY = {"pack_energy_left_wh_final": ("energy_left_wh", "final"),
                "pack_soh_capacity_min_final": ("soh_capacity_min", "final"),
                "pack_soh_resistance_max_final": ("soh_resistance_max", "final"),
                "pack_i_discharge_max_10s_a_min": ("i_discharge_max_10s_a", "min"),
                "pack_p_discharge_max_10s_w_min": ("p_discharge_max_10s_w", "min"),
                "pack_energy_discharged_wh": ("energy_discharged_wh", "drive"),
                "pack_energy_charged_wh": ("energy_charged_wh", "drive")}

_SETUPS: dict[tuple[str, float], Any] = {}

_log = structlog.get_logger("bms.fleet")


@dataclass
class DriveResult:
    """What the summary needs of one drive (small: goes back from the worker)."""

    vehicle: str
    path: str
    status: str  # "ok" or "skipped"
    error: str = ""
    parquet: str = ""
    pack_parquet: str = ""  # with SOX: the pack figures per sample
    samples: int = 0
    frames: int = 0
    duration_s: float = 0.0  # of the log (sample grid)
    # wall seconds of read, decode, assemble, estimate, write; "cpu": this process's CPU seconds of read..estimate
    # (what the drive costs on a core of its own: wall time also holds the waits of a loaded machine)
    seconds: dict[str, float] = field(default_factory=dict)
    counters: dict[str, int] = field(default_factory=dict)
    cells: dict[str, list[Any]] = field(default_factory=dict)  # per-cell summary values (and "cause")
    pack: dict[str, float] = field(default_factory=dict)  # with SOX: the drive's PACK_SUMMARY values
    # chained: seconds rested since the previous drive (None: not rested) and what was done, in words
    rested_s: float | None = None
    chain: str = ""

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


def service_for(config: str | None, n_cells: int | None = None):
    """The service built from ``config`` (cached per process and file version); ``n_cells`` overrides the pack's."""
    key = (str(config), Path(config).stat().st_mtime if config else 0.0, n_cells)
    svc = _SETUPS.get(key)
    if svc is None:
        from ..service.config import load_config
        from ..service.daemon import Service

        cfg = load_config(config)
        if n_cells is not None:
            cfg = cfg.model_copy(update={"pack": cfg.pack.model_copy(update={"n_cells": n_cells})})
        svc = _SETUPS[key] = Service(cfg)
    return svc


RECORDING_SUFFIXES = (".csv", ".csv.gz")


def is_recording(path: str | Path) -> bool:
    """A single-cell recording in the project's CSV layout (time_s,current_a,voltage_v[,temperature_c])."""
    return str(path).lower().endswith(RECORDING_SUFFIXES)


def _recording_samples(log: Path, svc) -> SampleArrays:
    try:
        rec = load_recording(log, resample_s=svc.period_s)
        # the recording's current is the pack's: n_parallel cells of pack.capacity_ah share it (sample_current)
        n_par = svc.cfg.estimator.sop.n_parallel
        check_charge_span(rec, svc.cfg.pack.capacity_ah * n_par,
                          "pack.capacity_ah" if n_par == 1 else f"{n_par} x pack.capacity_ah (estimator.sop.n_parallel)")
        return SampleArrays.from_recording(rec, svc.period_s)
    except ValueError as exc:  # DataError is one; the step check another
        raise DataError(str(exc).splitlines()[0]) from None


def parquet_path(out_dir: str | Path, vehicle: str, log: str | Path) -> Path:
    return Path(out_dir) / "drives" / vehicle / (Path(log).name + ".parquet")


def pack_parquet_path(out_dir: str | Path, vehicle: str, log: str | Path) -> Path:
    """With SOX, the drive's pack figures per sample: beside :func:`parquet_path`, ``<log>.pack.parquet``."""
    return Path(out_dir) / "drives" / vehicle / (Path(log).name + ".pack.parquet")


def drive_order_key(path: str | Path) -> tuple[float, str]:
    """Chaining order: the log's first timestamp (as ``replay`` reports it), then the name."""
    from ..replay.replay import log_span

    span = log_span(path)
    return (span[0] if span else math.inf, Path(path).name)


def _reference(log: Path, n_cells: int) -> tuple[np.ndarray, np.ndarray] | None:
    """(soc0, capacity_ah) per cell from ``<log>.truth.json`` (written by encode-log), if there is one."""
    from ..replay.encode_log import truth_path

    path = truth_path(log)
    if not path.is_file():
        return None
    try:
        cells = json.loads(path.read_text())["cells"]
        soc0 = np.array([float(c["soc0"]) for c in cells])
        cap = np.array([float(c["capacity_ah"]) for c in cells])
    except (OSError, ValueError, KeyError, TypeError):
        return None
    return (soc0, cap) if soc0.shape == (n_cells,) else None


def _summary(est: DriveEstimate, log: Path, period_s: float) -> dict[str, list[float]]:
    """Per-cell summary values of one drive; the SOC error against encode-log's truth where it exists.

    The reference SOC is the project's (:func:`bms_estimator.scoring.counted_soc`: coulomb
    counting from the cell's true start SOC with its true capacity, read at mid-sample), the
    figures :func:`bms_estimator.scoring.soc_error_figures`' ``rmse_all_pct`` and the error at
    the last sample, both in percent.
    """
    n = est.valid.shape[1] if est.valid.ndim == 2 else 0
    out: dict[str, list[float]] = {}
    if len(est) == 0:
        return out
    out["soc_final"] = est.cells["soc"][-1].tolist()
    out["valid_samples"] = np.count_nonzero(est.valid, axis=0).tolist() if n else []
    out["capacity_ah_final"] = est.cells["capacity_ah"][-1].tolist()
    if "capacity_at_bound" in est.cells:  # -1 / +1: the capacity ended at its low / high bound (a wrong stated one)
        out["capacity_at_bound_final"] = [int(x) if np.isfinite(x) else None for x in est.cells["capacity_at_bound"][-1]]
    if "vline" in est.state and "vline_q_range" in est.state:  # the c0 method's voltage-line capacity (NaN: none)
        q_v = voltage_line_capacity_ah(est.state["vline"], est.state["vline_q_range"])
        if np.isfinite(q_v).any():  # none (ekf, or not yet): no value, an empty column
            out["capacity_voltage_ah_final"] = q_v.tolist()
    out["r0_ohm_final"] = est.cells["r0_ohm"][-1].tolist()
    with warnings.catch_warnings():  # an all-NaN column (a cell never valid) is NaN, not a warning
        warnings.simplefilter("ignore", RuntimeWarning)
        out["r0_ohm_median"] = np.nanmedian(est.cells["r0_ohm"], axis=0).tolist()
        out["temperature_c_mean"] = np.nanmean(est.cells["temperature_c"], axis=0).tolist()
    ref = _reference(log, n)
    if ref is not None:
        soc0, cap = ref
        current = np.where(np.isfinite(est.current_a), est.current_a, 0.0)
        final, rmse = [], []
        for c in range(n):
            soc_ref = counted_soc(current, period_s, cap[c], soc0[c])
            final.append(float(100.0 * (est.cells["soc"][-1, c] - soc_ref[-1])))
            rmse.append(soc_error_figures(est.cells["soc"][:, c], soc_ref, est.t_s, float(est.t_s[0]))["rmse_all_pct"])
        out["soc_error_final_pct"] = final
        out["soc_rmse_pct"] = rmse
    if est.sox_keys:
        for key, name in SOX_SUMMARY.items():
            out[key] = (est.energy_wh[name] if name in est.energy_wh else est.cells[name][-1]).tolist()
    return out


def _pack_summary(est: DriveEstimate) -> dict[str, float]:
    """:data:`PACK_SUMMARY` of a drive with SOX (empty without): finals, least values and the drive's energy."""
    out = {}
    for column, (key, how) in PACK_SUMMARY.items():
        if how == "drive":
            out[column] = float(est.pack_energy_wh.get(key, math.nan))
            continue
        series = est.pack.get(key)
        if series is None or len(series) == 0:
            out[column] = math.nan
        elif how == "final":
            out[column] = float(series[-1])
        else:  # the least over the samples with a figure (NaN before the first update, or none at all)
            seen = series[~np.isnan(series)]
            out[column] = float(seen.min()) if seen.size else math.nan
    return out


def _longest_run(ok: np.ndarray) -> tuple[int, int]:
    """[start, stop) of the longest run of True in ``ok`` ((0, 0) if none)."""
    if not ok.any():
        return 0, 0
    edges = np.flatnonzero(np.diff(np.concatenate(([0], ok.astype(np.int8), [0]))))
    starts, stops = edges[0::2], edges[1::2]
    k = int(np.argmax(stops - starts))
    return int(starts[k]), int(stops[k])


#: a cell's longest stretch of valid, evenly spaced samples must be this long for diagnose (s)
DIAGNOSE_MIN_S = 1800.0


def _diagnose_cells(est: DriveEstimate, svc, period_s: float) -> list[str]:
    """``diagnose``'s named cause per cell, on the cell's longest stretch of valid, evenly spaced samples.

    The stretch starts at the estimator's SOC there (diagnose counts charge from a start SOC).
    A cell without ``DIAGNOSE_MIN_S`` of such data gets ``""``; a failure ``"error: ..."``.
    """
    from ..diagnose import Series, diagnose

    n = est.valid.shape[1]
    even = np.concatenate(([True], np.isclose(np.diff(est.t_s), period_s)))
    out = []
    for c in range(n):
        ok = est.valid[:, c] & np.isfinite(est.current_a) & np.isfinite(est.cells["soc"][:, c]) & even
        a, b = _longest_run(ok)
        if (b - a) * period_s < DIAGNOSE_MIN_S:
            out.append("")
            continue
        temp = est.cells["temperature_c"][a:b, c]
        try:
            # the cell's current: the pack's over the cells in parallel (can.sampler.sample_current)
            series = Series(est.current_a[a:b] / svc.cfg.estimator.sop.n_parallel, est.cells["voltage_v"][a:b, c],
                            svc.ocv, float(svc.cfg.pack.capacity_ah),
                            float(est.cells["soc"][a, c]), float(period_s), temp if np.isfinite(temp).all() else None)
            out.append(str(diagnose(series).cause))
        except Exception as exc:  # noqa: BLE001 - a diagnosis that fails is reported in its cell, not fatal
            out.append(f"error: {one_line_error(exc)}")
    return out


def _write_table(path: Path, cols: dict[str, Any]) -> None:
    """``cols`` as a zstd Parquet at ``path``, written to a temporary name and renamed (never half a file)."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".parquet.tmp")
    pq.write_table(pa.table(cols), tmp, compression="zstd")
    tmp.replace(path)


def _write_parquet(path: Path, est: DriveEstimate) -> None:
    k, n = est.valid.shape
    cols: dict[str, Any] = {
        "t_s": np.repeat(est.t_s, n),
        "cell": np.tile(np.arange(n, dtype=np.int32), k),
        "valid": est.valid.reshape(-1),
        "current_a": np.repeat(est.current_a, n),
    }
    for key in PARQUET_KEYS + est.sox_keys:
        if key in est.cells:
            cols[key] = est.cells[key].reshape(-1)
    _write_table(path, cols)


def _write_pack_parquet(path: Path, est: DriveEstimate) -> None:
    """The pack figures per sample (one row each): ``t_s``, ``current_a`` and the pack_outputs keys."""
    _write_table(path, {"t_s": est.t_s, "current_a": est.current_a, **est.pack})


def _samples_of(log: Path, config: str | None, res: DriveResult):
    """(service, samples) of one log: read, decode, assemble; fills ``res`` (frames, counters, seconds).

    Raises for a log to skip (:class:`~bms_estimator.errors.DataError` naming the problem).
    """
    secs = res.seconds
    if is_recording(log):  # one measured cell: its samples directly, a one-cell pack
        svc = service_for(config, n_cells=1)
        t0 = time.perf_counter()
        samples = _recording_samples(log, svc)
        secs["read"] = time.perf_counter() - t0
    else:
        svc = service_for(config)
        t0 = time.perf_counter()
        frames = read_frames(log)
        t1 = time.perf_counter()
        secs["read"] = t1 - t0
        res.frames = len(frames)
        if len(frames) == 0:
            raise DataError(f"{log}: empty log (no frames)")
        if svc.cfg.can.kernel_filters:  # the service then never sees other ids (kernel or python-can filters)
            keep = np.isin(frames.key, np.array(sorted(svc.decoder._plans), dtype=np.int64))  # noqa: SLF001
            frames = type(frames)(frames.t_s[keep], frames.key[keep], frames.length[keep], frames.data[keep],
                                  frames.ignored[keep])
        events, dcount = decode_frames(svc.decoder, frames)
        t2 = time.perf_counter()
        secs["decode"] = t2 - t1
        if dcount.decoded == 0:
            raise DataError(f"{log}: none of its {res.frames} frames is a message the configured DBC and mapping "
                            "decode (recorded with another DBC?)")
        samples = assemble_samples(frames.t_s, events, svc.sampler)  # only its settings are read
        secs["assemble"] = time.perf_counter() - t2
        res.counters = {**dcount.as_dict(), **samples.counters}
        if samples.counters["rewinds"]:
            raise DataError(f"{log}: timestamps go back by more than the rewind limit "
                            f"({samples.counters['rewinds']} time(s)): not one drive")
    if len(samples) == 0:
        raise DataError(f"{log}: no complete sample period ({res.frames} frames)")
    res.counters = res.counters or dict(samples.counters)
    return svc, samples


def _skipped(res: DriveResult, exc: BaseException) -> DriveResult:
    """``res`` as a skipped drive, its error the one line that says why."""
    log = res.path
    if isinstance(exc, BmsEstimatorError):
        res.error = exc.header if not exc.problems else f"{exc.header} {'; '.join(exc.problems)}"
    elif isinstance(exc, MemoryError):
        res.error = f"{log}: out of memory"
    else:
        res.error = f"{log}: {one_line_error(exc)}"
    res.status = "skipped"
    res.seconds.pop("cpu", None)  # a skipped drive: no cost to report
    return res


def run_drive(log: str | Path, config: str | None, out_dir: str | Path, vehicle: str,
              state: dict[str, np.ndarray] | None = None, *, write: bool = True, diagnose: bool = False,
              previous_end_s: float | None = None, sox: bool = False,
              ) -> tuple[DriveResult, dict[str, np.ndarray] | None, DriveEstimate | None]:
    """One drive; never raises for a bad log (the result says what was wrong).

    ``sox``: also run the service's SOP/SOE/SOH part (module docstring); a carried ``state``'s SOX
    part (``sox.`` keys) resumes it.

    ``diagnose``: also name each cell's model error with ``diagnose`` (:func:`_diagnose_cells`;
    slow: seconds per cell-hour).  ``previous_end_s``: with a carried ``state``, the previous
    drive's last sample time; the time since is rested over when both logs carry absolute times
    (:func:`.estimate.rest_between_drives`; ``res.rested_s``, ``res.chain`` say what was done).

    Returns the result, the estimator state at the end (``state`` unchanged when the
    drive was skipped) and the estimate itself (None when skipped).
    """
    log = Path(log)
    res = DriveResult(vehicle=vehicle, path=str(log), status="skipped")
    res.seconds["cpu"] = time.process_time()  # start; _finish makes it the CPU seconds spent
    try:
        svc, samples = _samples_of(log, config, res)
        t3 = time.perf_counter()
        est = carry_state(svc._new_estimator, state)  # noqa: SLF001 - the service's own factory
        sox_est = resume_sox(svc._new_sox, state or {}) if sox else None  # noqa: SLF001 - likewise
        if state is not None:
            res.rested_s, res.chain = rest_between_drives(est, previous_end_s, samples, sox_est)
        out = estimate_drive(samples, est, svc.decoder, svc.sampler, sox=sox_est,
                             n_parallel=svc.cfg.estimator.sop.n_parallel)
        res.seconds["estimate"] = time.perf_counter() - t3
        res.seconds["cpu"] = time.process_time() - res.seconds["cpu"]
        _finish(res, log, svc, samples, out, out_dir, vehicle, write, diagnose)
        return res, out.state, out
    except Exception as exc:  # noqa: BLE001 - one drive must never stop the batch
        return _skipped(res, exc), state, None


def _stack_factory(svc):
    """``n`` -> a fresh estimator of ``n`` cells made as the service makes its own (the service's for its ``n``)."""

    def make(n: int):
        if n == svc.n_cells:
            return svc._new_estimator()  # noqa: SLF001 - the service's own factory
        return SocEstimator(n, svc.ocv, svc.cfg.pack.capacity_ah, svc.period_s, initial_soc=None,
                            config=svc.soc_config)
    return make


def _stack_sox_factory(svc):
    """``n`` -> a fresh SOX part of ``n`` cells made as the service makes its own (the service's for its ``n``)."""

    def make(n: int):
        if n == svc.n_cells:
            return svc._new_sox()  # noqa: SLF001 - the service's own factory
        return SoxEstimator(n, svc.period_s, svc.cfg.estimator.sox_config)
    return make


def run_drives(logs: list[tuple[str, str]], config: str | None, out_dir: str | Path, *, write: bool = True,
               diagnose: bool = False, sox: bool = False) -> list[DriveResult]:
    """Independent drives ((log, vehicle) each, every one from a fresh estimator), their estimation stacked.

    Each drive is read, decoded and assembled on its own; then the drives of one pack layout
    run side by side as the cells of one estimator (:func:`.stack.estimate_stacked`: each
    drive's results are those it has alone, bit for bit), which shares the estimator's
    per-sample overhead among them. A drive's ``seconds["estimate"]`` and its CPU seconds hold
    its share (1/S) of the stacked run; ``counters["stacked_with"]`` says how many ran together.
    With ``sox`` (the SOP/SOE/SOH part, see the module docstring) it runs stacked too, its cells
    grouped per drive (:meth:`~bms_estimator.core.sox.SoxEstimator.set_groups`: each drive's SOX
    outputs, pack figures and state its own, bit for bit). If the drives cannot run stacked, they
    run one by one. Never raises for a bad log.
    """
    results: list[DriveResult] = []
    ready: dict[int, list[tuple[DriveResult, Path, Any, SampleArrays]]] = {}
    for log, vehicle in logs:
        res = DriveResult(vehicle=vehicle, path=str(log), status="skipped")
        res.seconds["cpu"] = time.process_time()
        results.append(res)
        try:
            svc, samples = _samples_of(Path(log), config, res)
        except Exception as exc:  # noqa: BLE001 - one drive must never stop the batch
            _skipped(res, exc)
            continue
        res.seconds["cpu"] = time.process_time() - res.seconds["cpu"]
        ready.setdefault(id(svc), []).append((res, Path(log), svc, samples))
    for group in ready.values():
        svc = group[0][2]
        t0, c0 = time.perf_counter(), time.process_time()
        outs: list[DriveEstimate | None] = [None] * len(group)
        together = 1
        try:
            outs = estimate_stacked([g[3] for g in group], _stack_factory(svc),
                                    _stack_sox_factory(svc) if sox else None,
                                    n_parallel=svc.cfg.estimator.sop.n_parallel)
            wall, cpu = (time.perf_counter() - t0) / len(group), (time.process_time() - c0) / len(group)
            together = len(group)
        except (StackError, MemoryError) as exc:  # then one by one (each with the service's error handling)
            _log.warning("drives run one by one", reason=str(exc))
            outs = [None] * len(group)
        for (res, path, _svc, samples), out in zip(group, outs):
            try:
                if out is None:
                    t0, c0 = time.perf_counter(), time.process_time()
                    out = estimate_drive(samples, svc._new_estimator(),  # noqa: SLF001
                                         sox=svc._new_sox() if sox else None,  # noqa: SLF001
                                         n_parallel=svc.cfg.estimator.sop.n_parallel)
                    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
                res.seconds["estimate"] = wall
                res.seconds["cpu"] += cpu
                res.counters["stacked_with"] = together
                _finish(res, path, svc, samples, out, out_dir, res.vehicle, write, diagnose)
            except Exception as exc:  # noqa: BLE001 - one drive must never stop the batch
                _skipped(res, exc)
    return results


def _finish(res: DriveResult, log: Path, svc, samples: SampleArrays, out: DriveEstimate, out_dir, vehicle: str,
            write: bool, diagnose: bool = False) -> None:
    """Summary values, optionally the diagnosis, and the Parquet of one estimated drive; ``res`` made "ok"."""
    t4 = time.perf_counter()
    res.samples = len(samples)
    res.duration_s = len(samples) * samples.period_s
    res.cells = _summary(out, log, samples.period_s)
    if out.pack:
        res.pack = _pack_summary(out)
    if diagnose:
        t5 = time.perf_counter()
        res.cells["cause"] = _diagnose_cells(out, svc, samples.period_s)
        res.seconds["diagnose"] = time.perf_counter() - t5
        t4 = time.perf_counter()
    if write:
        p = parquet_path(out_dir, vehicle, log)
        _write_parquet(p, out)
        res.parquet = str(p)
        if out.pack:
            pp = pack_parquet_path(out_dir, vehicle, log)
            _write_pack_parquet(pp, out)
            res.pack_parquet = str(pp)
    res.seconds["write"] = time.perf_counter() - t4
    res.status = "ok"


def run_vehicle(logs: list[str], config: str | None, out_dir: str | Path, vehicle: str,
                chain: bool = True, diagnose: bool = False, sox: bool = False) -> list[DriveResult]:
    """A vehicle's drives in time order, the estimator state carried from each to the next, rested over the
    time between them when the logs carry absolute times (a skipped drive carries nothing: the next good one
    rests from the last good one's end)."""
    results = []
    state, end_s = None, None
    for log in sorted(logs, key=drive_order_key):
        res, new_state, out = run_drive(log, config, out_dir, vehicle, state if chain else None, diagnose=diagnose,
                                        previous_end_s=end_s, sox=sox)
        if chain:
            state = new_state
            if out is not None and len(out):
                end_s = float(out.t_s[-1])
        results.append(res)
    return results
