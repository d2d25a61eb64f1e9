"""The estimator daemon: lifecycle, the bus, state saves, the no-input monitor.

The data path is :mod:`bms_estimator.service.pipeline` (its docstring names every hop);
the daemon feeds it frames and attaches the outputs as ``on_snapshot`` hooks::

    receive thread -> bounded queue -> ResilientBus.recv_batch() -> Pipeline.process_frame(msg) -> Snapshot per sample
        -> MqttPublisher.submit_snapshot        (never blocks)
        -> StateEncoder.encode_snapshot -> ResilientBus.send_many   (on the can.output.period_s grid)
        -> state save in a worker thread        (every state.save_interval_s of sample time)
        -> Heartbeat.beat(), metrics

Timing: everything the estimator and its outputs see is on the frames' own time
base (``msg.timestamp``); the event-loop clock is read only for liveness
(heartbeat, loop lag, "no input" status frames, uptime), and the receive clock only to tell a
step of the wall clock that stamps the frames from a silence (:class:`ClockStepGuard`: a step is
not rested over as a park). Replaying a log at any
speed therefore gives identical estimator states, CAN cell/pack frames and
MQTT payloads. The CAN output is sent when a sample's end time ``t_s`` enters a
new ``can.output.period_s`` bucket (``floor(t_s / period)``), so with the
defaults every 1 s sample produces one set of frames.

Robustness: bad frames are counted by the decoder and the sampler; a sample
whose current is invalid is counted with the current's running mean, its voltages not read
(``samples_current_invalid``; :meth:`~bms_estimator.core.soc.SocEstimator.update`);
an exception inside one frame/tick is logged (rate-limited) and counted
(``tick_errors``) and the loop goes on; the bus reopens itself; MQTT runs in its
own task with a bounded latest-value buffer, so a broker that is down never
holds the estimator or the CAN output back.

State: restored at start by :func:`~bms_estimator.service.state.load_state`
(stale/corrupt/foreign files are set aside there), then rested over its age (the pack
parked while the service was down: ``SocEstimator.rest`` and ``SoxEstimator.rest``); a state
saved again before any sample records in its meta the time it is rested up to
(``rested_until``), so the next restart rests it only over the time since. A file made with another
structural estimator configuration (sample period, identification method,
LIF window, stated capacity) or that the estimator rejects is set aside as
``foreign`` and the estimator starts fresh (SOC from the OCV of the first valid
sample). ``saved_at`` of a state file is the wall time of the newest sample in
it, so ``state.max_age_s`` measures how old the *estimate* is.

Lifecycle: :meth:`Service.run` starts the bus (it opens and reopens itself in the
background), sends ``READY=1`` at once, runs until ``stop_event`` is set (or the task is cancelled), then sends
``STOPPING=1``, saves the state, publishes ``offline`` and closes the bus.

Reload (SIGHUP, ``systemctl reload``): :func:`serve` builds a new :class:`Service` from the
configuration as it is now, in a thread of its own while the running one goes on. One that does not
build (:class:`ConfigError`, :class:`DataError`, or anything else) is logged with every problem and
the running service keeps its configuration. Otherwise the running service stops as on SIGTERM but
says ``RELOADING=1`` (the state saved), and the new one starts from that state (``READY=1``), from memory
where that save failed (:meth:`Service.takes_over`); a stop requested meanwhile ends there instead.
Where the new configuration keeps the broker and availability topic, the stopping service does not
publish ``offline``, so Home Assistant's entities stay available across the reload.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import hashlib
import json
import math
import time
from collections.abc import Callable, Iterable
from dataclasses import replace
from pathlib import Path
from typing import Any

import can
import numpy as np
import structlog
from pydantic import ValidationError

from .. import aio
from ..can.bus import BusConfig, ResilientBus, open_bus
from ..can.dbc import dbc_size_note, load_db
from ..can.decoder import FrameDecoder
from ..can.encoder import StateEncoder
from ..can.mapping import MappingError
from ..can.sampler import SampleAssembler
from ..core.ocv import OcvCurve
from ..core.ocv_surface import OcvSurface, stated_capacity_ratio, table_capacities_ah
from ..core.soc import SocEstimator
from ..core.sop import default_ratings_note
from ..core.sox import SoxEstimator
from ..errors import BmsEstimatorError, DataError, one_line_error
from ..ocv_table import read_ocv_table, read_ocv_tables
from . import systemd
from .config import ConfigError, EstimatorConfig, ServiceConfig
from .health import HealthServer, Heartbeat
from .metrics import ServiceMetrics
from .mqtt import MqttPublisher, tls_context
from .pipeline import Pipeline, Snapshot
from .schema import EstimatorState
from .state import StateDict, _move_aside, estimator_state, load_state, resume_sox, save_state

__all__ = ["DEFAULT_OCV_CELL", "ClockStepGuard", "Service", "ServiceMetrics", "run_service", "serve"]

log = structlog.get_logger("bms.daemon")

#: sample OCV curve used when ``pack.ocv_csv`` is not set
DEFAULT_OCV_CELL = "panasonic-18650pf"
#: frames taken in a row before the loop is yielded to (it is anyway after each sample)
_YIELD_EVERY = 256



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
        data_problems: list[str] = []  # a file the configuration names is itself malformed

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
            except MappingError as exc:
                problems.extend(f"can.mapping: {line}" for line in [exc.header, *exc.problems])
            except ValueError as exc:
                problems.append(f"can.mapping: {exc}")
            if cfg.can.output.enabled:
                try:
                    self.encoder = StateEncoder(self.db)
                except KeyError as exc:
                    what = exc.args[0] if exc.args else exc
                    what = f"message {what!r} not in the DBC" if isinstance(what, str) and " " not in what else what
                    problems.append(f"can.dbc: {what}: can.output.enabled sends the project DBC's output "
                                    "messages; set [can.output] enabled = false, or use a DBC that has them")
        try:
            bus_kwargs = cfg.can.bus_kwargs()
            if cfg.can.kernel_filters and "can_filters" not in bus_kwargs and self.decoder is not None:
                bus_kwargs["can_filters"] = self.decoder.can_filters()
            self.bus_cfg = BusConfig(**bus_kwargs)
        except ValidationError as exc:
            for err in exc.errors(include_url=False):
                loc = ".".join(str(p) for p in err.get("loc", ()))
                problems.append(f"can.bus.{loc}: {err.get('msg', 'invalid')}")
        state_problem = cfg.state.path_problem()
        if state_problem is not None:
            problems.append(f"state.path: {state_problem}")
        if cfg.mqtt.enabled:
            try:
                tls_context(cfg.mqtt.tls)  # its files: the client makes it again at its first connect
            except ConfigError as exc:
                problems.extend(exc.problems)
            if cfg.mqtt.buffer_max < n + 1:  # a sample queues all its topics at once; a full buffer evicts the oldest
                problems.append(f"mqtt.buffer_max: {cfg.mqtt.buffer_max} is less than the {n + 1} topics of one sample "
                                f"(pack.n_cells {n} and the pack): its first cells would be evicted unsent, every "
                                f"sample; give at least {n + 1}")
        self.ocv: OcvCurve | OcvSurface | None = None
        try:
            if cfg.pack.ocv_csv is None:
                from ..samples import ocv_table

                self.ocv_source = str(ocv_table(DEFAULT_OCV_CELL))
                self.ocv = read_ocv_table(self.ocv_source)
            else:
                paths = cfg.pack.ocv_csv if isinstance(cfg.pack.ocv_csv, list) else [cfg.pack.ocv_csv]
                if not paths:
                    problems.append("pack.ocv_csv: an empty list: give one table, or one per temperature")
                else:
                    self.ocv_source = ", ".join(str(p) for p in paths)
                    # several tables: OCV(soc, T), read at each cell's temperature from CAN
                    self.ocv = read_ocv_table(paths[0]) if len(paths) == 1 else read_ocv_tables(paths)
        except (FileNotFoundError, IsADirectoryError, NotADirectoryError) as exc:  # the key names no file: its fault
            problems.append(f"pack.ocv_csv: {exc.filename}: {exc.strerror.lower()}")
        except (OSError, ValueError) as exc:  # the table itself: a data error, not the configuration's
            data_problems.append(f"pack.ocv_csv: {exc}")
        self.soc_config = cfg.estimator.soc_config
        # Counting starts on the tables' C/20 capacity (the scale SOC is defined on), except where it is
        # not this pack's cells': the built-in curve stands in for the OCV's shape only (its 3.0 Ah is the
        # sample cell's), and a table more than 2x from pack.capacity_ah was measured on another cell (one
        # cell of a parallel group, say).  Counting with it, the EKF's first step would clip it into
        # capacity_bounds x stated, a wrong capacity with nothing to say so.
        self.capacity_note: str | None = None
        # versions before this rule started the count on the tables' capacity here, and the EKF's first step
        # clipped it to this bound (-1 low, +1 high) where it lies outside capacity_bounds x stated (restore)
        self._legacy_clip_side = 0
        if self.ocv is not None and self.soc_config.capacity_from_ocv:
            ratio = stated_capacity_ratio(cfg.pack.capacity_ah, self.ocv)
            if cfg.pack.ocv_csv is None or ratio is not None:
                self.soc_config = replace(self.soc_config, capacity_from_ocv=False)
                tables = table_capacities_ah(self.ocv)
                if tables:
                    q, (lo, hi) = float(np.median(tables)), self.soc_config.capacity_bounds
                    self._legacy_clip_side = -1 if q < lo * cfg.pack.capacity_ah else (
                        1 if q > hi * cfg.pack.capacity_ah else 0)
            if cfg.pack.ocv_csv is not None and ratio is not None:
                self.capacity_note = (
                    f"pack.capacity_ah {cfg.pack.capacity_ah:g} Ah is {ratio:.3g} times the C/20 capacity "
                    f"{float(np.median(table_capacities_ah(self.ocv))):.3f} Ah of pack.ocv_csv: counting with "
                    "pack.capacity_ah (a table of one cell of a parallel group: scale its capacity_ah column; "
                    "another cell's table, or a wrong pack.capacity_ah: fix it)")
        cell_cycle_s = self.decoder.mapping.cell_cycle_s if self.decoder is not None else None
        self.staleness_s = staleness_for(cfg.estimator, cell_cycle_s)
        try:
            self.sampler = SampleAssembler(
                n, period_s=self.period_s, staleness_s=self.staleness_s,
                max_gap_s=max(5.0, self.staleness_s, 2.0 * self.period_s),
                rewind_s=max(5.0, 2.0 * self.period_s),
            )
        except ValueError as exc:
            problems.append(f"estimator: {exc}")
        if problems:
            raise ConfigError("invalid configuration:", problems + data_problems)
        if data_problems:
            raise DataError("unreadable or malformed input data:", data_problems)
        try:  # anything the core still rejects (it validates more than the checks above)
            estimator = self._new_estimator()
        except ValueError as exc:
            raise ConfigError("invalid configuration:", [f"estimator.core: {exc}"]) from None
        if cfg.pack.ocv_csv is None:
            log.warning("pack.ocv_csv not set: using the built-in sample OCV curve", cell=DEFAULT_OCV_CELL)
        if self.capacity_note is not None:
            log.warning(self.capacity_note, stated_ah=cfg.pack.capacity_ah, config_key="pack.capacity_ah")
        # the SOP's current ratings left at an 18650's (20 A / 6 A) for a cell of another size: a 50 Ah cell's
        # limits sat at 0.4 C / 0.12 C (times n_parallel) with nothing to say so
        ratings = [f"estimator.sop.{k}" for k in ("i_discharge_max_a", "i_charge_max_a")
                   if k not in cfg.estimator.sop.model_fields_set]
        ratings_note = default_ratings_note(cfg.pack.capacity_ah, ratings, "pack.capacity_ah")
        if ratings_note is not None:
            log.warning(ratings_note, stated_ah=cfg.pack.capacity_ah, config_key="estimator.sop")
        # the example configuration of earlier versions spelt out the 7-day default of state.max_age_s: copied,
        # it kept a vehicle parked a fortnight starting fresh after the default moved to 366 days
        if cfg.state.max_age_s == LEGACY_MAX_AGE_S and "max_age_s" in cfg.state.model_fields_set:
            log.warning("state.max_age_s 604800 s (7 days) is the default that the example configuration of earlier "
                        "versions spelt out; the default is now 366 days (a parked month keeps the learnt "
                        "capacity, the commissioning R0 and the energy counters): remove the key to take it, or "
                        "keep it to set aside a state older than 7 days", config_key="state.max_age_s")
        # the shipped DBC's ranges against the cell's size (a 57 Ah cell's C1 went out clamped at 13,106.8 F)
        dbc_note = dbc_size_note(cfg.pack.capacity_ah, cfg.can.dbc) if cfg.can.output.enabled else None
        if dbc_note is not None:
            log.warning(dbc_note, stated_ah=cfg.pack.capacity_ah, config_key="can.dbc")
        if getattr(self.ocv, "mixed_cells", None):  # tables of two cells? (core.ocv_surface, item 9)
            log.warning(self.ocv.mixed_cells, config_key="pack.ocv_csv")
        self._check_staleness(self.staleness_s, cell_cycle_s)

        assert self.decoder is not None
        self.pipeline = Pipeline(self.decoder, self.sampler, estimator, sox=self._new_sox(),
                                 n_parallel=cfg.estimator.sop.n_parallel)  # as batch passes it
        self.metrics = metrics if metrics is not None else ServiceMetrics(cell_metrics=cfg.health.cell_metrics)
        self.metrics.attach(self)
        self.pipeline.observe_tick = self.metrics.observe_tick
        self.heartbeat = Heartbeat(self.period_s, cfg.health.stale_after_periods)
        m = cfg.mqtt
        longest_gap_s = max(self.period_s, m.publish_period_s, m.max_period_s if m.soc_deadband > 0 else 0.0)
        self.publisher = MqttPublisher(m, cfg.pack.pack_id, n, metrics=self.metrics,
                                       expire_after_s=max(10.0, 3.0 * longest_gap_s),
                                       sop_horizons_s=cfg.estimator.sox_config.sop.horizons_s)
        self.pipeline.add_hook(self._on_snapshot)
        self._bus_factory = bus_factory if bus_factory is not None else open_bus
        self.bus: ResilientBus | None = None
        self.health: HealthServer | None = None
        self.ready = asyncio.Event()
        self.restored = False
        self.fingerprint = self._fingerprint()

        self._started_mono = time.monotonic()
        self._last_sample_mono: float | None = None
        self._restored_saved_at: float | None = None
        self._rested_until: float | None = None  # the wall time the resumed state is rested up to
        self._out_bucket: int | None = None
        self._save_anchor: float | None = None
        self._save_task: asyncio.Task[None] | None = None
        self._no_input_logged = False
        self._last_frame_mono: float | None = None
        self.reloading = False  # set by serve(): the stop ahead is a reload (RELOADING=1, not STOPPING=1)
        self.stays_online = False  # set by serve(): the reload's service announces on the same availability topic
        self.unsaved: StateDict | None = None  # the state the final save could not write (set at the stop)
        self.handover: StateDict | None = None  # set by serve(): the unsaved state of the service this one follows
        self.clock_guard = ClockStepGuard(self.sampler.max_gap_s)

    @property
    def estimator(self) -> SocEstimator:
        return self.pipeline.estimator

    @staticmethod
    def _check_staleness(staleness_s: float, cell_cycle_s: float | None) -> None:
        """One WARNING at start when a cell's value is refreshed (the mapping's ``cell_cycle_s``: foxBMS'
        5.4 s) no sooner than ``estimator.staleness_s`` ages it: every cell would read stale between its
        frames on a healthy bus (only a staleness the configuration sets can be that short:
        :func:`staleness_for`)."""
        if cell_cycle_s is not None and staleness_s <= cell_cycle_s:
            log.warning(f"estimator.staleness_s {staleness_s:g} s is not above the CAN mapping's cell_cycle_s "
                        f"{cell_cycle_s:g} s: cells will read stale between their frames; set it to about "
                        f"{2 * cell_cycle_s:g} s", staleness_s=staleness_s, cell_cycle_s=cell_cycle_s,
                        config_key="estimator.staleness_s")

    # ------------------------------------------------------------- estimator
    def _new_estimator(self) -> SocEstimator:
        return SocEstimator(
            self.n_cells, self.ocv, self.cfg.pack.capacity_ah, self.period_s, initial_soc=None, config=self.soc_config
        )

    def _new_sox(self) -> SoxEstimator:
        return SoxEstimator(self.n_cells, self.period_s, self.cfg.estimator.sox_config)

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
        # Cells in parallel: each is fed the pack current / n_parallel, so what a state learnt (its SOC count,
        # resistances, capacity, energy) is at that current. Left out at 1, so that the states of one cell
        # per series element saved before it was part of the key keep their fingerprint; a state of a
        # parallel pack saved before it was (its cells fed the whole pack current) no longer matches.
        n_parallel = self.cfg.estimator.sop.n_parallel
        if n_parallel != 1:
            key["n_parallel"] = n_parallel
        return hashlib.sha256(json.dumps(key, sort_keys=True).encode()).hexdigest()[:16]

    def _fingerprint_mismatch(self, meta: dict[str, Any]) -> str:
        """Why a state of another fingerprint is not resumed: what its meta says differs, else the list."""
        k, saved_k = self.cfg.estimator.sop.n_parallel, meta.get("n_parallel")
        if saved_k is None and k != 1:
            return (f"saved without estimator.sop.n_parallel (by an earlier version, which fed each of the {k} "
                    "cells in parallel the whole pack current: its SOC, resistances, capacity and energy are "
                    "not a cell's), or with another estimator configuration")
        if saved_k is not None and saved_k != k:
            return (f"saved with estimator.sop.n_parallel {saved_k}, configured {k}: its SOC, resistances, "
                    "capacity and energy are at another current per cell")
        return ("made with another estimator configuration (sample period, method, window, c0 window, capacity "
                "or cells in parallel)")

    def restore(self) -> bool:
        """Load the saved state if it is fresh and fits; True when resumed. Never raises."""
        st = self.cfg.state
        pack_id = self.cfg.pack.pack_id
        saved = self.handover
        if saved is None:
            saved = load_state(st.path, pack_id=pack_id, n_cells=self.n_cells, max_age_s=st.max_age_s)
        if saved is None:
            return False
        meta = getattr(saved, "meta", {}) or {}
        reason = None
        sox_only = False  # the SOC part set aside, the SOP/SOE/SOH part resumed
        if meta.get("fingerprint") != self.fingerprint:
            reason = self._fingerprint_mismatch(meta)
        else:
            est = self._new_estimator()
            try:
                est.load_state_dict(dict(saved))
            except Exception as exc:  # noqa: BLE001 - ValueError, KeyError, shape errors...
                reason = f"rejected by the estimator: {type(exc).__name__}: {exc}"
            else:
                reason = self._legacy_clipped_capacity(meta, est)
                sox_only = reason is not None
                if reason is None:
                    self.pipeline.estimator = est
                    self._restore_sox(saved)
        if reason is not None:
            on_disk = self.handover is None and Path(st.path).exists()  # a state handed over is not the file's
            aside = _move_aside(Path(st.path), "foreign") if on_disk else None
            log.warning("saved estimator state not used; starting fresh", path=str(st.path), reason=reason,
                        moved_to=str(aside) if aside else None)
            self.pipeline.estimator = self._new_estimator()
            if sox_only:
                self._resume_sox_only(saved, meta)
            return False
        self.restored = True
        self._restored_saved_at = float(meta.get("saved_at", time.time()))
        self._rested_until = self._rest_since_saved(_rested_until(meta, self._restored_saved_at))
        soc = self.estimator.soc
        log.info("estimator resumed from saved state", path=str(st.path), age_s=round(float(meta.get("age_s", 0)), 1),
                 t_s=meta.get("t_s"), soc_mean=float(np.nanmean(soc)) if np.isfinite(soc).any() else None)
        return True

    def _legacy_clipped_capacity(self, meta: dict[str, Any], est: SocEstimator) -> str | None:
        """Why a state an earlier version counted with a capacity nobody stated is not resumed, else None.

        Versions that did not record ``capacity_from_ocv`` in the meta started the count on the OCV tables'
        capacity even where it is not this pack's cells' (the built-in curve's 3.0 Ah, a table more than 2x
        from pack.capacity_ah), and the EKF's first step clipped it to a capacity bound: a 50 Ah pack counted
        with 30 Ah. Resumed, that capacity stays, the SOC is counted with it and the bound flag blames
        pack.capacity_ah. Cells of such a file still at that bound: the file is set aside."""
        side = self._legacy_clip_side
        if side == 0 or "capacity_from_ocv" in meta or not np.any(est.capacity_at_bound == side):
            return None
        lo, hi = self.soc_config.capacity_bounds
        factor = lo if side < 0 else hi
        cells = np.flatnonzero(est.capacity_at_bound == side)
        return (f"saved by an earlier version, which started the count on the OCV table's capacity, not this "
                f"pack's cells', and (EKF) clipped it to {factor * self.cfg.pack.capacity_ah:g} Ah ({factor:g} x "
                f"pack.capacity_ah {self.cfg.pack.capacity_ah:g}): cells {cells.tolist()} still count with "
                f"{float(np.median(est.capacity_ah[cells])):.4g} Ah, a capacity nobody stated")

    def _resume_sox_only(self, saved: Any, meta: dict[str, Any]) -> None:
        """The SOP/SOE/SOH part of a state whose SOC part is set aside for its capacity alone
        (:meth:`_legacy_clipped_capacity`): the commissioning R0 the resistance SOH is measured against and
        the energy counters do not depend on the capacity the SOC was counted with. Rested over the state's
        age as a resumed state is (with the fresh SOC estimator's model: its RC voltages relax fully)."""
        self._restore_sox(saved)
        age = time.time() - _rested_until(meta, float(meta.get("saved_at", time.time())))
        if age > self.sampler.max_gap_s:
            self.pipeline.sox.rest(age, est=self.estimator)
        r0_c = self.pipeline.sox.resistance.r0_commissioning_ohm
        log.info("the SOP/SOE/SOH part of the state set aside is resumed (the commissioning R0 of the resistance "
                 "SOH, the energy counters): it does not depend on the capacity",
                 cells_commissioned=int(np.count_nonzero(np.isfinite(r0_c))), rested_s=round(max(age, 0.0), 1))

    def _rest_since_saved(self, saved_at: float) -> float:
        """The resumed state is ``now - saved_at`` seconds behind (``saved_at``: the wall time of its newest
        sample, or the time a state saved without a sample since its restore was rested up to): the estimator
        rests over that time (the pack parked while the service was down) when it is longer than the
        sampler's ``max_gap_s``, the gap it would bridge with stale samples rather than call a time jump (a
        quick restart resumes exactly as saved). A wall clock now behind ``saved_at`` (set back, or the state
        file's clock ahead) rests over nothing, logged. Returns the wall time the state is rested up to."""
        now = time.time()
        age = now - saved_at
        if age > self.sampler.max_gap_s:
            self.pipeline.rest(age, "restart")
            return now
        if age < 0:
            log.warning("wall clock is behind the saved state's time: the resumed state does not rest",
                        behind_s=round(-age, 3))
        return saved_at

    def _restore_sox(self, saved: Any) -> None:
        """The SOX part of a resumed state (the commissioning R0, energy counters); a state without
        it (older files) or one that does not fit starts these afresh, the SOC state stays resumed."""
        self.pipeline.sox = resume_sox(self._new_sox, saved)

    # ---------------------------------------------------------------- outputs
    def _on_snapshot(self, snap: Snapshot) -> None:
        """The daemon's hook: MQTT, CAN, save scheduling, heartbeat."""
        self._last_sample_mono = time.monotonic()
        self.metrics.set_state(snap.state)
        if self.cfg.mqtt.enabled:
            self.publisher.submit_snapshot(snap)
        self._send_can(snap)
        self._maybe_save(snap.t_s)
        self.heartbeat.beat()

    def _send_can(self, snap: Snapshot) -> None:
        enc, bus = self.encoder, self.bus
        if enc is None or bus is None:
            return
        bucket = math.floor(snap.t_s / self.cfg.can.output.period_s + 1e-9)
        if bucket == self._out_bucket:
            return
        self._out_bucket = bucket
        bus.send_many(enc.encode_snapshot(snap))

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
        state, meta, saved_at = self._state_to_save()
        self._save_task = asyncio.get_running_loop().create_task(self._write(state, meta, saved_at))

    def _state_to_save(self) -> tuple[dict[str, Any], dict[str, Any], float]:
        est = self.estimator
        last = self.pipeline.last
        meta = {
            "pack_id": self.cfg.pack.pack_id,
            "n_cells": self.n_cells,
            "fingerprint": self.fingerprint,
            "t_s": last.t_s if last is not None else None,
            "samples": est.samples,
            "sample_period_s": self.period_s,
            "capacity_ah": self.cfg.pack.capacity_ah,
            "n_parallel": self.cfg.estimator.sop.n_parallel,
            "capacity_from_ocv": self.soc_config.capacity_from_ocv,  # the count started on the tables' capacity
        }
        if last is not None:
            saved_at = last.wall_time
        elif self._restored_saved_at is not None:
            # no sample since the restore: the estimate is as old as its newest sample, but it has been
            # rested up to the restore; a restart rests it only over the time since (restore)
            saved_at = self._restored_saved_at
            meta["rested_until"] = self._rested_until
        else:
            saved_at = time.time()
        # own copies: the worker thread writes them while the estimator moves on
        state = estimator_state(est, self.pipeline.sox)
        return state, meta, saved_at

    async def _write(self, state: dict[str, Any], meta: dict[str, Any], saved_at: float) -> bool:
        path = self.cfg.state.path
        try:
            await asyncio.to_thread(save_state, path, state, meta, saved_at=saved_at)
        except Exception as exc:  # noqa: BLE001 - a failed save must not stop the service
            self.metrics.state_save_errors.inc()
            log.error("state save failed", path=str(path), error=f"{type(exc).__name__}: {exc}")
            return False
        self.metrics.state_saves.inc()
        log.debug("state saved", path=str(path), t_s=meta.get("t_s"))
        return True

    def _unsaved_state(self) -> StateDict:
        """The current state as :func:`load_state` would return it had it been saved now (for :func:`serve`)."""
        state, meta, saved_at = self._state_to_save()
        out = StateDict(state)
        out.meta = {**meta, "saved_at": saved_at, "age_s": max(0.0, time.time() - saved_at)}
        return out

    def takes_over(self, old: Service) -> bool:
        """Whether this service, started by a reload after ``old``, resumes ``old``'s state from memory: its
        final save failed (the file on disk is older, or absent), and it has this pack, size and estimator
        configuration (the :meth:`_fingerprint` a state file must have been made with)."""
        unsaved = old.unsaved
        if unsaved is None or (old.cfg.pack.pack_id, old.n_cells, old.fingerprint) != (
                self.cfg.pack.pack_id, self.n_cells, self.fingerprint):
            return False
        self.handover = unsaved
        return True

    async def save_now(self) -> bool:
        """Wait for a save in progress, then write the current state. Never raises."""
        task = self._save_task
        if task is not None and not task.done():
            with contextlib.suppress(Exception):
                await asyncio.shield(task)
        if self.restored and self.pipeline.last is None:
            return True  # nothing new since the restore: the file on disk is that state
        state, meta, saved_at = self._state_to_save()
        self._save_task = asyncio.get_running_loop().create_task(self._write(state, meta, saved_at))
        return await asyncio.shield(self._save_task)

    # ------------------------------------------------------------------- run
    def _health_status(self) -> str:
        bus = self.bus.describe() if self.bus is not None else "not started"
        return (f"state {self.pipeline.state.label}; CAN {bus}; MQTT {'connected' if self.publisher.connected else 'not connected'}"
                + self._capacity_note("; "))

    def _capacity_note(self, sep: str) -> str:
        """``sep`` + how many cells' capacity estimates sit at a bound (a wrong pack.capacity_ah), or nothing."""
        snap = self.pipeline.last
        n = snap.cells_capacity_at_bound if snap is not None else 0
        return f"{sep}{n} cell(s) with the capacity at a bound: check pack.capacity_ah" if n else ""

    @property
    def health_port(self) -> int | None:
        return self.health.port if self.health is not None else None

    async def _consume(self) -> None:
        """Frames from the bus's receive thread, a batch at a time, through the pipeline.

        The thread keeps reading while a tick runs here; this loop yields after every
        sample and every 256 frames, so a burst does not starve MQTT, health and the watchdog.
        """
        bus = self.bus
        assert bus is not None
        while True:
            try:
                batch = await bus.recv_batch()
            except RuntimeError:  # closed
                return
            except asyncio.CancelledError:
                raise
            except Exception as exc:  # noqa: BLE001 - never let the receive loop die
                self.pipeline.failed("receive", exc)
                await asyncio.sleep(0.1)
                continue
            since_yield = 0
            for msg in batch:
                produced = self._take(msg)
                since_yield += 1
                if produced or since_yield >= _YIELD_EVERY:
                    since_yield = 0
                    await asyncio.sleep(0)

    def _take(self, msg: can.Message) -> int:
        """One frame into the pipeline (every frame source's path); returns the samples it completed."""
        self._last_frame_mono = time.monotonic()
        step = self.clock_guard.check(msg.timestamp)
        if step is not None:
            self.pipeline.clock_stepped(msg.timestamp, step)
        return self.pipeline.process_frame(msg)

    async def feed(self, frames: Iterable[Any]) -> int:
        """Frames from an in-process source instead of the bus (the demo): each takes the path
        of a received frame after :meth:`ResilientBus.recv` (:meth:`_take`: decoder, sampler,
        estimator, the outputs), and the loop is yielded to as the receive loop does. The
        frames need ``arbitration_id``, ``is_extended_id``, ``is_error_frame``,
        ``is_remote_frame``, ``data`` and ``timestamp`` (a ``can.Message`` has them). Returns
        the number of samples completed."""
        made = since_yield = 0
        take = self._take
        for msg in frames:
            produced = take(msg)
            made += produced
            since_yield += 1
            if produced or since_yield >= _YIELD_EVERY:
                since_yield = 0
                await asyncio.sleep(0)
        return made

    def _status_line(self) -> str:
        """The ``systemctl status`` line: samples, SOC, CAN bus and MQTT state."""
        soc = self.estimator.soc
        bus = self.bus.describe() if self.bus is not None else "not started"
        return (f"{self.pipeline.counters.samples} samples, SOC mean "
                + (f"{100 * float(np.nanmean(soc)):.1f} %" if np.isfinite(soc).any() else "n/a")
                + f", CAN {bus}, MQTT {'connected' if self.publisher.connected else 'not connected'}"
                + self._capacity_note(", "))

    async def _ready_when_open(self) -> None:
        """``ready`` (in-process users) once the bus is first open; READY=1 went out before."""
        assert self.bus is not None
        await self.bus.wait_open()
        self.ready.set()
        log.info("can bus open: receiving", can=f"{self.cfg.can.interface}:{self.cfg.can.channel}")
        systemd.notify_status(self._status_line())

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
        silent_after = max(self.staleness_s, 3.0 * self.period_s)
        out_period = self.cfg.can.output.period_s
        next_status = time.monotonic() + silent_after
        next_sd_status = time.monotonic() + 10.0
        while True:
            t0 = time.monotonic()
            await asyncio.sleep(interval)
            now = time.monotonic()
            self.metrics.loop_lag_seconds.observe(max(0.0, now - t0 - interval))
            if self.bus is not None:
                self.bus.refresh_kernel_drops()
            if now >= next_sd_status:  # `systemctl status` line
                next_sd_status = now + 10.0
                systemd.notify_status(self._status_line())
            last = self._last_sample_mono if self._last_sample_mono is not None else self._started_mono
            if now - last <= silent_after:
                self._no_input_logged = False
                next_status = now + out_period
                continue
            if not self._no_input_logged:
                self._no_input_logged = True
                self.pipeline.state = EstimatorState.NO_INPUT
                self.metrics.set_state(EstimatorState.NO_INPUT)
                log.warning("no input samples", silent_s=round(now - last, 1))
                systemd.notify_status(f"no input samples for {now - last:.0f} s")
            if now >= next_status:
                next_status = now + out_period
                self.pipeline.state = EstimatorState.NO_INPUT
                if self.encoder is not None and self.bus is not None and self.bus.is_open:
                    try:
                        self.bus.send_many(self.encoder.encode_status(
                            self.pipeline.status_counters(EstimatorState.NO_INPUT, self.n_cells)))
                    except Exception as exc:  # noqa: BLE001
                        self.pipeline.failed("status", exc)

    async def run(self, stop_event: asyncio.Event | None = None) -> None:
        """Run until ``stop_event`` is set or the task is cancelled; then shut down cleanly."""
        stop_event = stop_event if stop_event is not None else asyncio.Event()
        self._started_mono = time.monotonic()
        self.restore()
        background: list[asyncio.Task[Any]] = []
        consume: asyncio.Task[None] | None = None
        try:
            if self.cfg.health.enabled:
                self.health = HealthServer.from_config(self.cfg.health, self.heartbeat, self.metrics,
                                                       status=self._health_status)
                try:
                    await self.health.start()
                except OSError as exc:
                    log.error("health server not started", host=self.cfg.health.host,
                              port=self.cfg.health.port, error=str(exc))
                    self.health = None
            background.append(asyncio.create_task(self.publisher.run(), name="bms-mqtt"))
            self.bus = ResilientBus(self.bus_cfg, bus_factory=self._bus_factory)
            await self.bus.start()
            # READY=1 now: the bus opens (and reopens) in the background, so an absent interface
            # shows as "CAN ... down" in the status, /healthz and the metrics instead of a unit
            # that never starts and is restarted every TimeoutStartSec.
            systemd.notify_ready(f"estimating {self.n_cells} cells; CAN {self.bus.describe()}")
            log.info("service ready", n_cells=self.n_cells, restored=self.restored,
                     can=f"{self.cfg.can.interface}:{self.cfg.can.channel}")
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
        if self.reloading:
            systemd.notify_reloading("reloading the configuration: saving state")
        else:
            systemd.notify_stopping("stopping: saving state")
        log.info("service stopping", reload=self.reloading)
        if consume is not None and not consume.done():
            consume.cancel()
            with contextlib.suppress(BaseException):
                await consume
        ok = await self.save_now()
        if ok:
            log.info("estimator state saved", path=str(self.cfg.state.path))
        else:  # the count since the last save is lost at exit (kept in memory across a reload)
            log.warning("final state save failed", path=str(self.cfg.state.path))
        if not ok and self.reloading:
            self.unsaved = self._unsaved_state()
        if self.cfg.mqtt.enabled and self.pipeline.last is not None:
            # with publish_period_s/soc_deadband the newest state may not have gone out yet
            self.publisher.submit_snapshot(self.pipeline.last, final=True)
        with contextlib.suppress(Exception):
            await self.publisher.close(timeout_s=5.0, offline=not self.stays_online)
        if self.bus is not None:
            with contextlib.suppress(Exception):
                await self.bus.drain(1.0)
            with contextlib.suppress(Exception):
                await self.bus.close()
        for task in background:
            task.cancel()
        for task in background:
            with contextlib.suppress(BaseException):
                await aio.wait_for(task, 2.0)
        if self.health is not None:
            with contextlib.suppress(Exception):
                await self.health.close()
        log.info("service stopped", samples=self.pipeline.counters.samples)


#: ``state.max_age_s`` as the example configuration of versions before the 366-day default spelt it out
LEGACY_MAX_AGE_S = 7 * 86400.0


def staleness_for(estimator: EstimatorConfig, cell_cycle_s: float | None) -> float:
    """The cells' staleness limit: ``estimator.staleness_s`` where the configuration sets it, else its
    default (5 s) or, for a mapping whose cell frames come round slower (``cell_cycle_s``: foxBMS' 5.4 s),
    twice that cycle, so that a healthy bus never reads stale between two frames of a cell."""
    if "staleness_s" in estimator.model_fields_set or cell_cycle_s is None:
        return estimator.staleness_s
    return max(estimator.staleness_s, 2.0 * cell_cycle_s)


def _rested_until(meta: dict[str, Any], saved_at: float) -> float:
    """The wall time a saved state is rested up to: its meta's ``rested_until`` (a state saved after a
    restore without a sample since), else ``saved_at`` (older files, and every state saved after a sample)."""
    r = meta.get("rested_until")
    if isinstance(r, (int, float)) and not isinstance(r, bool) and math.isfinite(r):
        return max(float(r), saved_at)
    return saved_at


class ClockStepGuard:
    """Tells a step of this host's wall clock from a silence on the bus.

    socketcan stamps frames with the kernel's wall clock (CLOCK_REALTIME). A gateway without a
    real-time clock boots with a wrong time, and NTP (chrony, systemd-timesyncd) steps it by hours
    or years while the vehicle drives: the frames' time jumps though no frame was missed, and the
    sampler and pipeline, seeing more than ``max_gap_s`` between two frames, would rest the
    estimator over it as over a park. :meth:`check` calls a jump a step when the receive clock,
    ``CLOCK_BOOTTIME`` (unlike ``CLOCK_MONOTONIC`` it counts a suspended gateway's sleep), moved
    less than ``max_gap_s`` since the previous frame while the frames' time moved more, and the new
    frame's time is this host's wall clock now (within ``max_gap_s``: stamped here, not a log's
    time, so a replayed log keeps its gaps). Cost: one clock read a frame."""

    __slots__ = ("boot_clock", "max_gap_s", "wall_clock", "_b", "_t")

    def __init__(self, max_gap_s: float, *, boot_clock: Callable[[], float] | None = None,
                 wall_clock: Callable[[], float] = time.time) -> None:
        self.max_gap_s = float(max_gap_s)
        self.boot_clock = boot_clock if boot_clock is not None else _boot_clock()
        self.wall_clock = wall_clock
        self._t: float | None = None  # the previous frame's time
        self._b = 0.0  # the receive clock at it

    def check(self, t: float) -> float | None:
        """The step (seconds) if the frame of time ``t`` follows a wall clock step, else None."""
        b = self.boot_clock()
        prev, prev_b = self._t, self._b
        if not math.isfinite(t):
            return None
        self._t, self._b = t, b
        if prev is None or not t - prev > self.max_gap_s or b - prev_b >= self.max_gap_s:
            return None
        if abs(t - self.wall_clock()) > self.max_gap_s:
            return None
        return t - prev


def _boot_clock() -> Callable[[], float]:
    """``CLOCK_BOOTTIME`` where there is one (Linux), else ``time.monotonic``."""
    clock_id = getattr(time, "CLOCK_BOOTTIME", None)
    if clock_id is None:  # pragma: no cover - not Linux
        return time.monotonic
    return functools.partial(time.clock_gettime, clock_id)


async def serve(svc: Service, stop: asyncio.Event, reload: asyncio.Event, rebuild: Callable[[], Service], *,
                config: str | None = None, reloaded: Callable[[Service], None] | None = None) -> Service:
    """Run ``svc`` until ``stop`` is set, reloading each time ``reload`` is set (module docstring):
    ``rebuild()`` (run in a thread of its own, which a stop does not wait for) makes the new service
    from ``config`` (the file, named in the log) or raises; ``reloaded(new)`` is called before the new one runs (the logging settings).
    Returns the service that ran last; raises what its :meth:`Service.run` raised."""
    while True:
        run_stop = asyncio.Event()
        task = asyncio.create_task(svc.run(run_stop), name="bms-service")
        new: Service | None = None
        while new is None and not stop.is_set():
            stopped = asyncio.create_task(stop.wait())
            hup = asyncio.create_task(reload.wait())
            try:
                await asyncio.wait({task, stopped, hup}, return_when=asyncio.FIRST_COMPLETED)
            finally:
                stopped.cancel()
                hup.cancel()
            if task.done():
                task.result()
                return svc
            if stop.is_set():
                break
            reload.clear()
            log.info("reloading the configuration")
            build = asyncio.ensure_future(aio.in_thread(rebuild, name="bms-reload"))
            stopped = asyncio.create_task(stop.wait())
            try:
                await asyncio.wait({build, stopped}, return_when=asyncio.FIRST_COMPLETED)
            finally:
                stopped.cancel()
            if not build.done():  # a stop while the files are read: it does not wait for them
                build.cancel()
                break
            try:
                new = build.result()
            except BmsEstimatorError as exc:
                log.error("configuration not reloaded: the service goes on with the one it has",
                          config=config, error=exc.header, problems=exc.problems)
            except Exception as exc:  # noqa: BLE001 - a reload must never end a running service
                log.error("configuration not reloaded: the service goes on with the one it has",
                          config=config, error=one_line_error(exc))
        svc.reloading = new is not None and not stop.is_set()
        svc.stays_online = svc.reloading and new.publisher.same_availability(svc.publisher)
        run_stop.set()
        await task
        if not svc.reloading:
            return svc
        if new.takes_over(svc):
            log.warning("the state was not saved: the reloaded service resumes it from memory",
                        path=str(svc.cfg.state.path))
        svc = new
        if reloaded is not None:
            reloaded(svc)
        log.info("configuration reloaded", config=config, settings=svc.cfg.redacted())


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
