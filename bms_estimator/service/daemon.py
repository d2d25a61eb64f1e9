"""The estimator daemon: CAN in -> samples on frame time -> one estimator -> CAN + MQTT out.

Data path (one asyncio task, ``Service._consume``)::

    ResilientBus.recv() -> FrameDecoder.decode() -> SampleAssembler.feed_frame(events, msg.timestamp)
        -> per Sample: SocEstimator.update(current, cell voltages, valid)     (one call for all cells)
                       MqttPublisher.submit_cells/submit_pack                  (never blocks)
                       StateEncoder frames -> ResilientBus.send_many           (on the sample grid)
                       state snapshot -> save in a worker thread               (every save_interval_s of sample time)
                       Heartbeat.beat(), metrics

Timing: everything the estimator and its outputs see is on the frames' own time
base (``msg.timestamp``); the event-loop clock is read only for liveness
(heartbeat, loop lag, "no input" status frames, uptime). Replaying a log at any
speed therefore gives identical estimator states, CAN cell/pack frames and
MQTT payloads. The CAN output is sent when a sample's end time ``t_s`` enters a
new ``can.output.period_s`` bucket (``floor(t_s / period)``), so with the
defaults every 1 s sample produces one set of frames.

Robustness: bad frames are counted by the decoder and the sampler; a sample
whose current is invalid skips the estimator update (``samples_current_invalid``);
an exception inside one frame/tick is logged (rate-limited) and counted
(``tick_errors``) and the loop goes on; the bus reopens itself; MQTT runs in its
own task with a bounded latest-value buffer, so a broker that is down never
holds the estimator or the CAN output back.

State: restored at start by :func:`~bms_estimator.service.state.load_state`
(stale/corrupt/foreign files are set aside there). A file made with another
structural estimator configuration (sample period, identification method,
LIF window, stated capacity) or that the estimator rejects is set aside as
``foreign`` and the estimator starts fresh (SOC from the OCV of the first valid
sample). ``saved_at`` of a state file is the wall time of the newest sample in
it, so ``state.max_age_s`` measures how old the *estimate* is.

Lifecycle: :meth:`Service.run` opens the bus, sends ``READY=1`` once the bus is
open, runs until ``stop_event`` is set (or the task is cancelled), then sends
``STOPPING=1``, saves the state, publishes ``offline`` and closes the bus.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import hashlib
import json
import math
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import can
import numpy as np
import structlog
from pydantic import ValidationError

from ..can.bus import BusConfig, ResilientBus, open_bus
from ..can.dbc import load_db
from ..can.decoder import FrameDecoder
from ..can.encoder import StateEncoder
from ..can.mapping import MappingError
from ..can.sampler import Sample, SampleAssembler
from ..core.identifier import METHODS, IdentifierConfig
from ..core.ocv import OcvCurve
from ..core.soc import CAPACITY_SOC_UPDATES, SocConfig, SocEstimator
from . import systemd
from .config import ConfigError, ServiceConfig
from .health import HealthServer, Heartbeat, Metrics, _counter, _gauge
from .mqtt import MqttPublisher, pack_summary
from .state import _move_aside, load_state, save_state

__all__ = ["DEFAULT_OCV_CELL", "Service", "ServiceMetrics", "run_service", "soc_config_from_core"]

log = structlog.get_logger("bms.daemon")

#: sample OCV curve used when ``pack.ocv_csv`` is not set
DEFAULT_OCV_CELL = "panasonic-18650pf"

_STATE_INIT, _STATE_RUNNING, _STATE_DEGRADED, _STATE_NO_INPUT = 0, 1, 2, 3
_LOG_EVERY = 1000  # after the first few, log every n-th repeated error


# ----------------------------------------------------------------------- metrics
@dataclasses.dataclass
class ServiceMetrics(Metrics):
    """:class:`~bms_estimator.service.health.Metrics` plus the daemon's own counters.

    Counters owned by other components (decoder, sampler, bus) are copied in
    by :meth:`render` through the ``refresh`` hook, so ``/metrics`` is
    current even while no sample is produced.
    """

    can_frames_received: int = _counter("CAN frames received")
    can_frames_unknown_id: int = _counter("CAN frames with an identifier not in the DBC (ignored)")
    can_frames_unmapped: int = _counter("CAN frames of the DBC that carry no mapped input (ignored)")
    can_frames_ignored: int = _counter("CAN error and remote frames (ignored)")
    decode_short_frames: int = _counter("CAN frames shorter than their DBC length")
    decode_bad_mux: int = _counter("CAN frames with a multiplexer value the DBC does not define")
    decode_out_of_range: int = _counter("values outside the mapping's valid range")
    decode_not_available: int = _counter("values sent as NotAvailable")
    decode_non_finite: int = _counter("NaN/inf values")
    decode_flagged_invalid: int = _counter("values flagged invalid by the sender")
    samples_current_invalid: int = _counter("samples without a valid current: estimator update skipped")
    sample_time_jumps: int = _counter("forward gaps in the frame time (sample grid re-anchored)")
    sample_rewinds: int = _counter("frame time went back by more than rewind_s (sampler reset)")
    sample_backward_frames: int = _counter("frames ignored because their time went backwards")
    tick_errors: int = _counter("exceptions while processing a frame or sample (logged, skipped)")
    estimator_corrections: int = _counter("SOC corrections from the OCV bias, all cells")
    estimator_restarts: int = _counter(
        "identifications restarted after a run of guard rejections (a cell stuck against the admissible set), all cells")
    can_tx_frames: int = _counter("CAN frames sent")
    can_tx_dropped: int = _counter("CAN frames dropped (bus down or send queue full)")
    can_tx_errors: int = _counter("CAN send errors")
    can_rx_dropped: int = _counter("received CAN frames dropped (receive queue full)")
    can_bus_opens: int = _counter("CAN bus opens")
    can_bus_open_failures: int = _counter("failed CAN bus opens")
    can_bus_errors: int = _counter("CAN bus failures that caused a reopen")
    tick_seconds: float = _gauge("processing time of the last estimator tick")
    estimator_state: int = _gauge("0 init, 1 running, 2 degraded, 3 no input")
    state_restored: int = _gauge("1 when the estimator resumed from a saved state")
    last_sample_time_seconds: float = _gauge("end time of the last sample on the frames' time base", math.nan)

    def __post_init__(self) -> None:
        super().__post_init__()
        self.refresh: Callable[[], None] | None = None

    def render(self, heartbeat: Heartbeat | None = None) -> str:
        hook = self.refresh
        if hook is not None:
            try:
                hook()
            except Exception:  # noqa: BLE001 - metrics must render whatever happens
                log.exception("metrics refresh failed")
        return super().render(heartbeat)


# -------------------------------------------------------------- estimator config
def _coerce(name: str, value: Any, default: Any) -> Any:
    """``value`` as the type of ``default`` (bool, int, float, str, tuple of floats)."""
    if isinstance(default, bool):
        if not isinstance(value, bool):
            raise ValueError(f"must be true or false (got {value!r})")
        return value
    if isinstance(default, int):
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not float(value).is_integer():
            raise ValueError(f"must be an integer (got {value!r})")
        return int(value)
    if isinstance(default, float):
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise ValueError(f"must be a finite number (got {value!r})")
        return float(value)
    if isinstance(default, str):
        if not isinstance(value, str):
            raise ValueError(f"must be a string (got {value!r})")
        return value
    if isinstance(default, tuple):
        if (
            not isinstance(value, (list, tuple))
            or len(value) != len(default)
            or not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in value)
        ):
            raise ValueError(f"must be a list of {len(default)} numbers (got {value!r})")
        return tuple(float(v) for v in value)
    raise ValueError(f"cannot be set from the configuration ({name})")  # pragma: no cover


def _range_problems(soc: dict[str, Any], ident: dict[str, Any]) -> list[tuple[str, str]]:
    out: list[tuple[str, str]] = []
    for group in (soc, ident):
        for key, v in group.items():
            if isinstance(v, (int, float)) and not isinstance(v, bool) and v < 0:
                out.append((key, f"must be >= 0 (got {v!r})"))
    for key in ("window", "init_samples", "error_window", "iv_model_every"):
        if ident.get(key, 1) < 1:
            out.append((key, f"must be >= 1 (got {ident[key]!r})"))
    if not 0.0 < ident.get("forgetting", 1.0) <= 1.0:
        out.append(("forgetting", f"must be in (0, 1] (got {ident['forgetting']!r})"))
    if ident.get("method", IdentifierConfig().method) not in METHODS:
        out.append(("method", f"must be one of {', '.join(map(repr, METHODS))} (got {ident['method']!r})"))
    tmin, tmax = ident.get("tau_min_s", 1.0), ident.get("tau_max_s", 500.0)
    if not 0.0 < tmin < tmax:
        out.append(("tau_max_s", f"need 0 < tau_min_s < tau_max_s (got {tmin!r}, {tmax!r})"))
    if soc.get("capacity_soc_update", "none") not in CAPACITY_SOC_UPDATES:
        out.append(("capacity_soc_update", f"must be one of {', '.join(CAPACITY_SOC_UPDATES)} "
                                           f"(got {soc['capacity_soc_update']!r})"))
    if soc.get("c0_window_s", 1.0) <= 0:
        out.append(("c0_window_s", "must be > 0"))
    lo, hi = soc.get("capacity_bounds", (0.6, 1.4))
    if not 0.0 < lo < hi:
        out.append(("capacity_bounds", f"need 0 < low < high (got {[lo, hi]!r})"))
    return out


def soc_config_from_core(core: Mapping[str, Any]) -> SocConfig:
    """``estimator.core`` -> :class:`SocConfig`.

    Keys are the fields of :class:`SocConfig` and :class:`IdentifierConfig`
    (flat, or the identifier's in an ``identifier`` table). Raises
    :class:`ConfigError` with one ``estimator.core.<key>: ...`` line per problem
    (unknown keys, wrong types, values out of range).
    """
    soc_defaults = {f.name: getattr(SocConfig(), f.name) for f in dataclasses.fields(SocConfig) if f.name != "identifier"}
    id_defaults = IdentifierConfig().as_dict()
    soc_kw: dict[str, Any] = {}
    id_kw: dict[str, Any] = {}
    where: dict[str, str] = {}
    problems: list[str] = []

    def put(key: str, value: Any, prefix: str, only_identifier: bool = False) -> None:
        loc = f"{prefix}{key}"
        if key in id_defaults:
            target, default = id_kw, id_defaults[key]
        elif key in soc_defaults and not only_identifier:
            target, default = soc_kw, soc_defaults[key]
        else:
            known = sorted(id_defaults) if only_identifier else sorted({*soc_defaults, *id_defaults})
            problems.append(f"{loc}: unknown estimator parameter; known: {', '.join(known)}")
            return
        try:
            target[key] = _coerce(key, value, default)
            where[key] = loc
        except ValueError as exc:
            problems.append(f"{loc}: {exc}")

    for key, value in core.items():
        if key == "identifier" and isinstance(value, Mapping):
            for k2, v2 in value.items():
                put(str(k2), v2, "estimator.core.identifier.", only_identifier=True)
        else:
            put(str(key), value, "estimator.core.")
    merged_id = {**id_defaults, **id_kw}
    merged_soc = {**soc_defaults, **soc_kw}
    for key, msg in _range_problems(merged_soc, merged_id):
        problems.append(f"{where.get(key, 'estimator.core.' + key)}: {msg}")
    if problems:
        raise ConfigError("invalid configuration:", problems)
    return SocConfig(identifier=IdentifierConfig(**merged_id), **soc_kw)


# --------------------------------------------------------------------- service
class Service:
    """The daemon; see the module docstring.

    Construction loads and checks everything that can be wrong in the
    configuration (DBC, mapping, OCV table, estimator parameters, bus options)
    and raises :class:`ConfigError` naming each problem; it opens nothing.
    :meth:`run` does the rest.
    """

    def __init__(
        self,
        cfg: ServiceConfig,
        *,
        bus_factory: Callable[[BusConfig], can.BusABC] | None = None,
        metrics: ServiceMetrics | None = None,
    ) -> None:
        self.cfg = cfg
        self.n_cells = n = cfg.pack.n_cells
        self.period_s = cfg.estimator.sample_period_s
        problems: list[str] = []

        self.db = None
        try:
            self.db = load_db(cfg.can.dbc)
        except Exception as exc:  # noqa: BLE001 - cantools raises many kinds
            problems.append(f"can.dbc: cannot load {cfg.can.dbc or 'the project DBC'}: {exc}")
        self.decoder: FrameDecoder | None = None
        self.encoder: StateEncoder | None = None
        if self.db is not None:
            try:
                self.decoder = FrameDecoder(self.db, cfg.can.mapping, n)
            except (MappingError, ValueError) as exc:
                problems.extend(f"can.mapping: {line.strip()}" for line in str(exc).splitlines() if line.strip())
            if cfg.can.output.enabled:
                try:
                    self.encoder = StateEncoder(self.db)
                except KeyError as exc:
                    problems.append(f"can.dbc: output message {exc} missing (can.output.enabled needs the project's messages)")
        try:
            self.bus_cfg = BusConfig(**cfg.can.bus_kwargs())
        except ValidationError as exc:
            for err in exc.errors(include_url=False):
                loc = ".".join(str(p) for p in err.get("loc", ()))
                problems.append(f"can.bus.{loc}: {err.get('msg', 'invalid')}")
        try:
            if cfg.pack.ocv_csv is None:
                from ..samples import ocv_table

                self.ocv_source = str(ocv_table(DEFAULT_OCV_CELL))
            else:
                self.ocv_source = str(cfg.pack.ocv_csv)
            self.ocv = OcvCurve.from_csv(self.ocv_source)
        except (OSError, ValueError) as exc:
            problems.append(f"pack.ocv_csv: {exc}")
        try:
            self.soc_config = soc_config_from_core(cfg.estimator.core)
        except ConfigError as exc:
            problems.extend(exc.problems)
        try:
            self.sampler = SampleAssembler(
                n, period_s=self.period_s, staleness_s=cfg.estimator.staleness_s,
                max_gap_s=max(5.0, cfg.estimator.staleness_s, 2.0 * self.period_s),
                rewind_s=max(5.0, 2.0 * self.period_s),
            )
        except ValueError as exc:
            problems.append(f"estimator: {exc}")
        if problems:
            raise ConfigError("invalid configuration:", problems)
        try:  # anything the core still rejects (it validates more than the checks above)
            self.estimator = self._new_estimator()
        except ValueError as exc:
            raise ConfigError("invalid configuration:", [f"estimator.core: {exc}"]) from None
        if cfg.pack.ocv_csv is None:
            log.warning("pack.ocv_csv not set: using the built-in sample OCV curve", cell=DEFAULT_OCV_CELL)

        self.metrics = metrics if metrics is not None else ServiceMetrics()
        self.metrics.refresh = self._refresh_metrics
        self.heartbeat = Heartbeat(self.period_s, cfg.health.stale_after_periods)
        self.publisher = MqttPublisher(cfg.mqtt, cfg.pack.pack_id, n, metrics=self.metrics)
        self._bus_factory = bus_factory if bus_factory is not None else open_bus
        self.bus: ResilientBus | None = None
        self.health: HealthServer | None = None
        self.ready = asyncio.Event()
        self.restored = False
        self.fingerprint = self._fingerprint()

        self._started_mono = time.monotonic()
        self._last_sample: Sample | None = None
        self._last_sample_mono: float | None = None
        self._last_sample_wall: float | None = None
        self._restored_saved_at: float | None = None
        self._out_bucket: int | None = None
        self._save_anchor: float | None = None
        self._save_task: asyncio.Task[None] | None = None
        self._errors_logged = 0
        self._state_code = _STATE_INIT
        self._no_input_logged = False
        self._last_frame_mono: float | None = None

    # ------------------------------------------------------------- estimator
    def _new_estimator(self) -> SocEstimator:
        return SocEstimator(
            self.n_cells, self.ocv, self.cfg.pack.capacity_ah, self.period_s, initial_soc=None, config=self.soc_config
        )

    def _fingerprint(self) -> str:
        """What a saved state must have been made with to be resumed."""
        ident = self.soc_config.identifier
        key = {
            "dt_s": self.period_s,
            "method": ident.method,
            "window": ident.window,
            "c0_window_s": self.soc_config.c0_window_s,
            "capacity_ah": self.cfg.pack.capacity_ah,
        }
        return hashlib.sha256(json.dumps(key, sort_keys=True).encode()).hexdigest()[:16]

    def restore(self) -> bool:
        """Load the saved state if it is fresh and fits; True when resumed. Never raises."""
        st = self.cfg.state
        pack_id = self.cfg.pack.pack_id
        saved = load_state(st.path, pack_id=pack_id, n_cells=self.n_cells, max_age_s=st.max_age_s)
        if saved is None:
            return False
        meta = getattr(saved, "meta", {}) or {}
        reason = None
        if meta.get("fingerprint") != self.fingerprint:
            reason = "made with another estimator configuration (sample period, method, window, c0 window or capacity)"
        else:
            est = self._new_estimator()
            try:
                est.load_state_dict(dict(saved))
            except Exception as exc:  # noqa: BLE001 - ValueError, KeyError, shape errors...
                reason = f"rejected by the estimator: {type(exc).__name__}: {exc}"
            else:
                self.estimator = est
        if reason is not None:
            aside = _move_aside(Path(st.path), "foreign") if Path(st.path).exists() else None
            log.warning("saved estimator state not used; starting fresh", path=str(st.path), reason=reason,
                        moved_to=str(aside) if aside else None)
            self.estimator = self._new_estimator()
            return False
        self.restored = True
        self._restored_saved_at = float(meta.get("saved_at", time.time()))
        soc = self.estimator.soc
        log.info("estimator resumed from saved state", path=str(st.path), age_s=round(float(meta.get("age_s", 0)), 1),
                 t_s=meta.get("t_s"), soc_mean=float(np.nanmean(soc)) if np.isfinite(soc).any() else None)
        return True

    # -------------------------------------------------------------- frames
    def process_frame(self, msg: can.Message) -> int:
        """Decode one frame, assemble, and run a tick for every completed sample; returns their number."""
        assert self.decoder is not None
        events = self.decoder.decode(msg)
        samples = self.sampler.feed_frame(events, msg.timestamp)
        for sample in samples:
            self.tick(sample)
        return len(samples)

    def tick(self, sample: Sample) -> None:
        """One estimator step on ``sample``; exceptions are logged and counted, never raised."""
        t0 = time.perf_counter()
        m = self.metrics
        try:
            est = self.estimator
            m.samples += 1
            if sample.current_valid and math.isfinite(sample.current_a):
                est.update(sample.current_a, sample.cell_voltage_v, sample.valid)
            else:
                m.samples_current_invalid += 1
            self._last_sample = sample
            self._last_sample_mono = time.monotonic()
            self._last_sample_wall = time.time()
            valid = np.asarray(sample.valid, dtype=bool)
            n_valid = int(np.count_nonzero(valid))
            soc = est.soc
            params = est.params
            if not np.isfinite(soc).any():
                self._state_code = _STATE_INIT
            elif n_valid < self.n_cells or not sample.current_valid:
                self._state_code = _STATE_DEGRADED
            else:
                self._state_code = _STATE_RUNNING
            m.cells_stale = self.n_cells - n_valid
            m.last_sample_time_seconds = sample.t_s
            self._publish_mqtt(sample, soc, params, valid, n_valid)
            self._send_can(sample, soc, params, n_valid)
            self._maybe_save(sample.t_s)
            self.heartbeat.beat()
        except Exception as exc:  # noqa: BLE001 - one bad tick must not stop the service
            self._tick_failed("tick", exc)
        finally:
            m.tick_seconds = time.perf_counter() - t0

    def _tick_failed(self, where: str, exc: BaseException) -> None:
        self.metrics.tick_errors += 1
        if self._errors_logged < 5 or self.metrics.tick_errors % _LOG_EVERY == 0:
            self._errors_logged += 1
            log.error("estimator tick failed", where=where, error=f"{type(exc).__name__}: {exc}",
                      errors=self.metrics.tick_errors, exc_info=exc)

    def _publish_mqtt(self, sample: Sample, soc: np.ndarray, params: dict[str, np.ndarray],
                      valid: np.ndarray, n_valid: int) -> None:
        pub = self.publisher
        if not self.cfg.mqtt.enabled:
            return
        arrays: dict[str, Any] = {"soc": soc, **params, "stale": ~valid,
                                  "voltage_v": sample.cell_voltage_v,
                                  "temperature_c": sample.cell_temperature_c,
                                  "capacity_ah": self.estimator.capacity_ah}
        pub.submit_cells(sample.t_s, arrays)
        pub.submit_pack(pack_summary(
            sample.t_s, soc, sample.current_a if math.isfinite(sample.current_a) else None,
            stale=~valid,
            pack_voltage_v=sample.pack_voltage_v if math.isfinite(sample.pack_voltage_v) else None,
            current_valid=bool(sample.current_valid),
            cells_valid=n_valid,
            capacity_ah_mean=float(np.mean(self.estimator.capacity_ah)),
        ))

    def _status_counters(self, state: int, stale_cells: int) -> dict[str, Any]:
        dc, sc = self.decoder.counters, self.sampler.counters  # type: ignore[union-attr]
        return {
            "uptime_s": time.monotonic() - self._started_mono,
            "samples": sc.samples,
            "decode_errors": dc.errors,
            "rejections": int(np.sum(self.estimator.identifier.rejections)),
            "stale_cells": stale_cells,
            "time_jumps": sc.time_jumps + sc.rewinds,
            "backward_frames": sc.backward_frames,
            "estimator_state": state,
        }

    def _send_can(self, sample: Sample, soc: np.ndarray, params: dict[str, np.ndarray], n_valid: int) -> None:
        enc, bus = self.encoder, self.bus
        if enc is None or bus is None:
            return
        bucket = math.floor(sample.t_s / self.cfg.can.output.period_s + 1e-9)
        if bucket == self._out_bucket:
            return
        self._out_bucket = bucket
        frames = enc.encode_cells(
            np.arange(self.n_cells), soc, params["r0_ohm"], params["r1_ohm"], params["c1_f"],
            params["r2_ohm"], params["c2_f"], params["c0_v"], timestamp=sample.t_s,
        )
        frames += enc.encode_pack_summary(soc, sample.current_a, sample.pack_voltage_v,
                                          cells_valid=n_valid, timestamp=sample.t_s)
        frames += enc.encode_status(self._status_counters(self._state_code, self.n_cells - n_valid),
                                    timestamp=sample.t_s)
        bus.send_many(frames)

    # ----------------------------------------------------------------- state
    def _maybe_save(self, t_s: float) -> None:
        anchor = self._save_anchor
        if anchor is None or t_s < anchor:
            self._save_anchor = t_s
            return
        if t_s - anchor < self.cfg.state.save_interval_s:
            return
        if self._save_task is not None and not self._save_task.done():
            return  # the previous save is still being written: try again next sample
        self._save_anchor = t_s
        state, meta, saved_at = self._snapshot()
        self._save_task = asyncio.get_running_loop().create_task(self._write(state, meta, saved_at))

    def _snapshot(self) -> tuple[dict[str, Any], dict[str, Any], float]:
        est = self.estimator
        sample = self._last_sample
        meta = {
            "pack_id": self.cfg.pack.pack_id,
            "n_cells": self.n_cells,
            "fingerprint": self.fingerprint,
            "t_s": sample.t_s if sample is not None else None,
            "samples": est.samples,
            "sample_period_s": self.period_s,
            "capacity_ah": self.cfg.pack.capacity_ah,
        }
        if self._last_sample_wall is not None:
            saved_at = self._last_sample_wall
        elif self._restored_saved_at is not None:
            saved_at = self._restored_saved_at
        else:
            saved_at = time.time()
        # own copies: the worker thread writes them while the estimator moves on
        state = {k: np.array(v, copy=True) for k, v in est.state_dict().items()}
        return state, meta, saved_at

    async def _write(self, state: dict[str, Any], meta: dict[str, Any], saved_at: float) -> bool:
        path = self.cfg.state.path
        try:
            await asyncio.to_thread(save_state, path, state, meta, saved_at=saved_at)
        except Exception as exc:  # noqa: BLE001 - a failed save must not stop the service
            self.metrics.state_save_errors += 1
            log.error("state save failed", path=str(path), error=f"{type(exc).__name__}: {exc}")
            return False
        self.metrics.state_saves += 1
        log.debug("state saved", path=str(path), t_s=meta.get("t_s"))
        return True

    async def save_now(self) -> bool:
        """Wait for a save in progress, then write the current state. Never raises."""
        task = self._save_task
        if task is not None and not task.done():
            with contextlib.suppress(Exception):
                await asyncio.shield(task)
        if self.restored and self._last_sample is None:
            return True  # nothing new since the restore: the file on disk is that state
        state, meta, saved_at = self._snapshot()
        self._save_task = asyncio.get_running_loop().create_task(self._write(state, meta, saved_at))
        return await asyncio.shield(self._save_task)

    # ------------------------------------------------------------------- run
    def _refresh_metrics(self) -> None:
        m = self.metrics
        dec = self.decoder
        if dec is not None:
            dc = dec.counters
            m.frames_decoded = dc.decoded
            m.decode_errors = dc.errors
            m.can_frames_unknown_id = dc.unknown_id
            m.can_frames_unmapped = dc.unmapped
            m.can_frames_ignored = dc.ignored
            m.decode_short_frames = dc.short_frame
            m.decode_bad_mux = dc.bad_mux
            m.decode_out_of_range = dc.out_of_range
            m.decode_not_available = dc.not_available
            m.decode_non_finite = dc.non_finite
            m.decode_flagged_invalid = dc.flagged_invalid
            m.can_frames_received = dc.frames
        sc = self.sampler.counters
        m.sample_time_jumps = sc.time_jumps
        m.sample_rewinds = sc.rewinds
        m.sample_backward_frames = sc.backward_frames
        est = self.estimator
        m.estimator_rejections = int(np.sum(est.identifier.rejections))
        m.estimator_corrections = int(np.sum(est.corrections))
        m.estimator_restarts = int(np.sum(est.identifier.restarts))
        m.estimator_state = self._state_code
        m.state_restored = int(self.restored)
        bus = self.bus
        if bus is not None:
            bc = bus.counters
            m.can_tx_frames = bc.tx_frames
            m.can_tx_dropped = bc.tx_dropped
            m.can_tx_errors = bc.tx_errors
            m.can_rx_dropped = bc.rx_dropped
            m.can_bus_opens = bc.opens
            m.can_bus_open_failures = bc.open_failures
            m.can_bus_errors = bc.bus_errors

    @property
    def health_port(self) -> int | None:
        return self.health.port if self.health is not None else None

    async def _consume(self) -> None:
        bus = self.bus
        assert bus is not None
        since_yield = 0
        while True:
            try:
                msg = await bus.recv()
            except RuntimeError:  # closed
                return
            except asyncio.CancelledError:
                raise
            except Exception as exc:  # noqa: BLE001 - never let the receive loop die
                self._tick_failed("receive", exc)
                await asyncio.sleep(0.1)
                continue
            self._last_frame_mono = time.monotonic()
            try:
                produced = self.process_frame(msg)
            except Exception as exc:  # noqa: BLE001
                self._tick_failed("frame", exc)
                produced = 0
            since_yield += 1
            if produced or since_yield >= 256:
                # a replayed burst must not starve MQTT, health and the watchdog
                since_yield = 0
                await asyncio.sleep(0)

    async def _ready_when_open(self) -> None:
        assert self.bus is not None
        await self.bus.wait_open()
        self.ready.set()
        systemd.notify_ready(f"estimating {self.n_cells} cells on {self.cfg.can.interface}:{self.cfg.can.channel}")
        log.info("service ready", n_cells=self.n_cells, restored=self.restored,
                 can=f"{self.cfg.can.interface}:{self.cfg.can.channel}")

    def watchdog_ok(self) -> bool:
        """Whether to ping the systemd watchdog: the estimator heartbeat is fresh, or no frame
        arrives at all (a silent bus is not a hung daemon: restarting would not help, and a
        vehicle asleep would run the unit into its start limit). Frames arriving without
        estimator ticks (a tick that keeps failing, a stuck sampler) withhold the pings.
        A blocked event loop withholds them anyway (the pinging task cannot run)."""
        if self.heartbeat.is_fresh():
            return True
        last = self._last_frame_mono
        return last is None or time.monotonic() - last > self.heartbeat.max_age_s

    async def _monitor(self) -> None:
        """Loop lag, and 'no input' status frames while no sample arrives (wall clock)."""
        interval = min(0.25, self.period_s / 4)
        silent_after = max(self.cfg.estimator.staleness_s, 3.0 * self.period_s)
        out_period = self.cfg.can.output.period_s
        next_status = time.monotonic() + silent_after
        next_sd_status = time.monotonic() + 10.0
        while True:
            t0 = time.monotonic()
            await asyncio.sleep(interval)
            now = time.monotonic()
            self.metrics.loop_lag_seconds = max(0.0, now - t0 - interval)
            if now >= next_sd_status:  # `systemctl status` line
                next_sd_status = now + 10.0
                soc = self.estimator.soc
                systemd.notify_status(
                    f"{self.metrics.samples} samples, SOC mean "
                    + (f"{100 * float(np.nanmean(soc)):.1f} %" if np.isfinite(soc).any() else "n/a")
                    + f", MQTT {'connected' if self.publisher.connected else 'not connected'}"
                )
            last = self._last_sample_mono if self._last_sample_mono is not None else self._started_mono
            if now - last <= silent_after:
                self._no_input_logged = False
                next_status = now + out_period
                continue
            if not self._no_input_logged:
                self._no_input_logged = True
                self._state_code = _STATE_NO_INPUT
                log.warning("no input samples", silent_s=round(now - last, 1))
                systemd.notify_status(f"no input samples for {now - last:.0f} s")
            if now >= next_status:
                next_status = now + out_period
                self._state_code = _STATE_NO_INPUT
                if self.encoder is not None and self.bus is not None and self.bus.is_open:
                    try:
                        self.bus.send_many(self.encoder.encode_status(
                            self._status_counters(_STATE_NO_INPUT, self.n_cells)))
                    except Exception as exc:  # noqa: BLE001
                        self._tick_failed("status", exc)

    async def run(self, stop_event: asyncio.Event | None = None) -> None:
        """Run until ``stop_event`` is set or the task is cancelled; then shut down cleanly."""
        stop_event = stop_event if stop_event is not None else asyncio.Event()
        self._started_mono = time.monotonic()
        self.restore()
        background: list[asyncio.Task[Any]] = []
        consume: asyncio.Task[None] | None = None
        try:
            if self.cfg.health.enabled:
                self.health = HealthServer.from_config(self.cfg.health, self.heartbeat, self.metrics)
                try:
                    await self.health.start()
                except OSError as exc:
                    log.error("health server not started", host=self.cfg.health.host,
                              port=self.cfg.health.port, error=str(exc))
                    self.health = None
            background.append(asyncio.create_task(self.publisher.run(), name="bms-mqtt"))
            self.bus = ResilientBus(self.bus_cfg, bus_factory=self._bus_factory)
            await self.bus.start()
            background.append(asyncio.create_task(self._ready_when_open(), name="bms-ready"))
            background.append(asyncio.create_task(systemd.watchdog_loop(_WatchdogGate(self)), name="bms-watchdog"))
            background.append(asyncio.create_task(self._monitor(), name="bms-monitor"))
            consume = asyncio.create_task(self._consume(), name="bms-consume")
            stopper = asyncio.create_task(stop_event.wait(), name="bms-stop")
            try:
                await asyncio.wait({consume, stopper}, return_when=asyncio.FIRST_COMPLETED)
            finally:
                stopper.cancel()
            if consume.done() and not consume.cancelled() and consume.exception() is not None:
                log.error("receive loop ended", error=repr(consume.exception()))
        finally:
            await self._shutdown(consume, background)

    async def _shutdown(self, consume: asyncio.Task[None] | None, background: list[asyncio.Task[Any]]) -> None:
        systemd.notify_stopping("stopping: saving state")
        log.info("service stopping")
        if consume is not None and not consume.done():
            consume.cancel()
            with contextlib.suppress(BaseException):
                await consume
        ok = await self.save_now()
        log.info("estimator state saved" if ok else "final state save failed", path=str(self.cfg.state.path))
        with contextlib.suppress(Exception):
            await self.publisher.close(timeout_s=5.0)
        if self.bus is not None:
            with contextlib.suppress(Exception):
                await self.bus.drain(1.0)
            with contextlib.suppress(Exception):
                await self.bus.close()
        for task in background:
            task.cancel()
        for task in background:
            with contextlib.suppress(BaseException):
                await asyncio.wait_for(task, 2.0)
        if self.health is not None:
            with contextlib.suppress(Exception):
                await self.health.close()
        log.info("service stopped", samples=self.metrics.samples)


class _WatchdogGate:
    def __init__(self, svc: Service) -> None:
        self._svc = svc

    def is_fresh(self) -> bool:
        return self._svc.watchdog_ok()


async def run_service(
    cfg: ServiceConfig,
    *,
    bus_factory: Callable[[BusConfig], can.BusABC] | None = None,
    stop_event: asyncio.Event | None = None,
    started: Callable[[Service], None] | None = None,
) -> Service:
    """Build a :class:`Service` (raises :class:`ConfigError`), run it until
    ``stop_event`` is set or the task is cancelled, and return it.

    ``started`` is called with the service before it runs (tests use it to
    reach the metrics and the health port).
    """
    svc = Service(cfg, bus_factory=bus_factory)
    if started is not None:
        started(svc)
    await svc.run(stop_event)
    return svc
