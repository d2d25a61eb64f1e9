"""Frame -> sample -> estimate -> :class:`Snapshot`: the service's data path, synchronous and free of I/O.

One hop per file::

    can.Message
      -> can/decoder.py   FrameDecoder.decode(msg)              signal events (cell voltages, current, ...)
      -> can/sampler.py   SampleAssembler.feed_frame(events, t) Samples on the frames' own time grid
      -> core/soc.py      SocEstimator.update(i, v, valid, T)   SOC, its sigma + 2-RC parameters of every cell
      -> core/sox.py      SoxEstimator.update(est, i, v, valid) power limits, energy, health (when given)
      -> service/pipeline.py  Snapshot                          one immutable record per sample
      -> on_snapshot hooks, each an output adapter formatting the Snapshot with service/schema.py:
           service/mqtt.py    MqttPublisher.submit_snapshot     cell + pack JSON (latest-value buffer)
           can/encoder.py     StateEncoder.encode_snapshot      CellState/Pack/Status frames
           service/metrics.py ServiceMetrics.observe_snapshot   Prometheus gauges
         and the daemon's own (state save scheduling, heartbeat).

The daemon (service/daemon.py) owns everything with I/O or a clock of its own: the bus, the
tasks, the state file, the no-input monitor. The demo, the benchmarks and the tests attach
hooks with :meth:`Pipeline.add_hook` instead of subclassing the daemon.

Time: everything here runs on the frames' time base (``msg.timestamp``); the clocks passed
in are read only for the snapshot's ``wall_time`` (state files) and the uptime counter.

A wrong stated capacity: when a cell's capacity estimate comes to sit at one of its bounds
(:attr:`~bms_estimator.core.soc.SocEstimator.capacity_at_bound`: ``pack.capacity_ah`` is wrong for
it, its SOC unreliable), one WARNING line names the cells, the bound and the stated capacity (and, on
the c0 method, the capacity its voltage line reads, ``voltage_line_ah``), once per transition (as the MQTT publisher re-sends a cell when its stale flag changes, not every sample);
an INFO line when they are back inside. The snapshot counts them (``cells_capacity_at_bound``).

Gaps: a sample that does not follow the previous one (the sampler re-anchored its grid on a
time jump: the bus was silent, the gateway asleep) has ``t_s - period_s - t_prev`` seconds
without samples before its period; the estimator rests over them
(:meth:`~bms_estimator.core.soc.SocEstimator.rest`: the pack parked; with it
:meth:`~bms_estimator.core.sox.SoxEstimator.rest`) before the sample, logged in one line and
counted (``counters.rests``, ``counters.rest_s``). Except where the daemon said the jump was the
wall clock stepped (:meth:`Pipeline.clock_stepped`): no frame was missed, nothing is rested.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
import can
import numpy as np
import structlog

from ..can.decoder import FrameDecoder
from ..can.sampler import Sample, SampleAssembler, sample_current
from ..core.soc import SocEstimator
from ..core.sox import SoxEstimator, rest_estimators
from ..gaps import gap_before_s
from .schema import CELL_FIELDS, EstimatorState, SocStats, soc_stats

__all__ = ["Pipeline", "PipelineCounters", "Snapshot", "StatusCounters"]

log = structlog.get_logger("bms.pipeline")

_LOG_EVERY = 1000  # after the first few, log every n-th repeated error
_STALE_LINES = 20  # changes of the stale cells logged before only every _LOG_EVERY-th is


@dataclass(frozen=True, slots=True)
class StatusCounters:
    """What the CAN status frames carry (see schema.CAN_STATUS_SIGNALS)."""

    uptime_s: float
    samples: int
    decode_errors: int
    rejections: int
    stale_cells: int
    time_jumps: int
    backward_frames: int
    estimator_state: int


@dataclass(frozen=True, slots=True)
class Snapshot:
    """The estimator's result for one sample: everything an output needs, nothing it must compute.

    ``cells`` maps each per-cell key of :data:`~bms_estimator.service.schema.CELL_FIELDS`
    (except ``stale``, which is ``~valid``) to an array of ``n_cells`` values.
    """

    t_s: float  # end of the sample period, on the frames' time base
    wall_time: float  # epoch seconds when the sample was estimated
    current_a: float  # NaN when unknown
    current_valid: bool
    pack_voltage_v: float  # NaN when unknown
    cells: Mapping[str, np.ndarray]
    valid: np.ndarray  # (n,) bool: the cell's inputs were fresh
    soc: SocStats
    capacity_ah_mean: float
    state: EstimatorState
    counters: StatusCounters
    sample: Sample = field(repr=False)
    #: pack SOP/SOE/SOH figures (schema.PACK_SOX_FIELDS keys); empty without a SoxEstimator
    pack_sox: Mapping[str, float] = field(default_factory=dict)

    @property
    def n_cells(self) -> int:
        return int(self.valid.shape[0])

    @property
    def cells_valid(self) -> int:
        return int(np.count_nonzero(self.valid))

    @property
    def cells_capacity_at_bound(self) -> int:
        """Cells whose capacity estimate sits at a bound (``cells["capacity_at_bound"]`` nonzero; 0 without it)."""
        flags = self.cells.get("capacity_at_bound")
        return 0 if flags is None else int(np.count_nonzero(flags))


@dataclass
class PipelineCounters:
    samples: int = 0  # samples estimated
    samples_current_invalid: int = 0  # samples without a valid current: its running mean counted (none before the first)
    tick_errors: int = 0  # exceptions in a frame, a tick or a hook (logged, skipped)
    rests: int = 0  # gaps without samples the estimator rested over (a time jump, a restart)
    rest_s: float = 0.0  # their total length, seconds
    clock_steps: int = 0  # time jumps that were the wall clock stepped, not a silence: not rested over
    stale_changes: int = 0  # samples whose set of stale cells differed from the previous one's (logged: the first 20)


class Pipeline:
    """Decoder + sampler + estimator, calling ``on_snapshot`` hooks once per sample.

    Never raises from :meth:`process_frame` or :meth:`tick`: an exception is logged (rate
    limited) and counted in ``counters.tick_errors``; one failing hook does not stop the others.
    """

    def __init__(
        self,
        decoder: FrameDecoder,
        sampler: SampleAssembler,
        estimator: SocEstimator,
        *,
        on_snapshot: Callable[[Snapshot], None] | None = None,
        sox: SoxEstimator | None = None,
        clock: Callable[[], float] = time.monotonic,
        wall_clock: Callable[[], float] = time.time,
        n_parallel: int | None = None,
    ) -> None:
        self.decoder = decoder
        # cells in parallel per series element: each carries the pack current / n_parallel (sample_current);
        # None: the SOX part's ``sop.n_parallel`` (1 without one)
        self.n_parallel = int(n_parallel if n_parallel is not None else
                              (sox.config.sop.n_parallel if sox is not None else 1))
        self.sampler = sampler
        self.estimator = estimator
        self.sox = sox
        self.n_cells = int(estimator.n_cells)
        self.hooks: list[Callable[[Snapshot], None]] = [] if on_snapshot is None else [on_snapshot]
        self.counters = PipelineCounters()
        self.state = EstimatorState.INIT
        self.last: Snapshot | None = None
        self.tick_seconds = 0.0  # processing time of the last tick, hooks included
        self.observe_tick: Callable[[float], None] | None = None
        self._clock = clock
        self._wall_clock = wall_clock
        self._started = clock()
        self._errors_logged = 0
        self._last_t_s: float | None = None  # the previous sample's end
        self._at_bound = np.zeros(self.n_cells, dtype=np.int8)  # capacity_at_bound last logged, per cell
        self._fed = False  # a valid current seen: the estimator is fed every sample from then on
        self._stepped_at: float | None = None  # frame time of a wall clock step whose gap is not yet seen
        self._stale = np.zeros(self.n_cells, dtype=bool)  # cells last logged stale
        self._lost_since: int | None = None  # samples_current_invalid when the current was logged lost

    def add_hook(self, hook: Callable[[Snapshot], None]) -> None:
        self.hooks.append(hook)

    # ----------------------------------------------------------------- frames
    def process_frame(self, msg: can.Message) -> int:
        """Decode one frame, assemble, and tick every completed sample; returns their number."""
        try:
            events = self.decoder.decode(msg)
            samples = self.sampler.feed_frame(events, msg.timestamp)
        except Exception as exc:  # noqa: BLE001 - one bad frame must not stop the service
            self.failed("frame", exc)
            return 0
        for sample in samples:
            self.tick(sample)
        return len(samples)

    def tick(self, sample: Sample) -> Snapshot | None:
        """One estimator step on ``sample``, then the hooks; returns the snapshot (None on error)."""
        t0 = time.perf_counter()
        snap = None
        try:
            c = self.counters
            c.samples += 1
            est = self.estimator
            last, self._last_t_s = self._last_t_s, sample.t_s
            gap = float(gap_before_s(sample.t_s, last, sample.period_s)) if last is not None else 0.0
            stepped = self._stepped_at
            if gap and stepped is None:
                self.rest(gap, "time jump")
            if stepped is not None and (gap or sample.t_s > stepped + 2.0 * sample.period_s):
                self._stepped_at = None  # its gap (the first sample after the step) is not rested over
            current = sample_current(sample.current_a, sample.current_valid, self.n_parallel)
            lost = math.isnan(current)
            if lost:
                c.samples_current_invalid += 1
            # fed from the first valid current on; a current lost after it is counted with its running
            # mean (SocEstimator.update), before it there is nothing to count (can.sampler.first_current)
            self._fed |= not lost
            if self._fed:
                est.update(current, sample.cell_voltage_v, sample.valid, temperature_c=sample.cell_temperature_c)
                if self.sox is not None:
                    self.sox.update(est, current, sample.cell_voltage_v, sample.valid)
            self._log_capacity_bounds()
            self._log_input_losses(sample, lost)
            snap = self._snapshot(sample)
            self.last = snap
            for hook in self.hooks:
                try:
                    hook(snap)
                except Exception as exc:  # noqa: BLE001
                    self.failed(getattr(hook, "__qualname__", "hook"), exc)
        except Exception as exc:  # noqa: BLE001
            self.failed("tick", exc)
        finally:
            self.tick_seconds = dt = time.perf_counter() - t0
            if self.observe_tick is not None:
                self.observe_tick(dt)
        return snap

    def _log_capacity_bounds(self) -> None:
        """One WARNING per bound for the cells whose capacity estimate newly sits at it, one INFO for those back
        inside; nothing while no cell changes (module docstring)."""
        est = self.estimator
        side = getattr(est, "capacity_at_bound", None)
        if side is None or np.array_equal(side, self._at_bound):
            return
        changed = side != self._at_bound
        self._at_bound = np.array(side, dtype=np.int8, copy=True)
        lo, hi = est.config.capacity_bounds
        for flag, name, factor in ((-1, "low", lo), (1, "high", hi)):
            cells = np.flatnonzero(changed & (side == flag))
            if cells.size:
                stated = float(est.capacity_stated_ah[cells[0]])
                # the c0 method's voltage line, where it has a capacity: what the voltage says the cell holds
                q_v = getattr(est, "capacity_voltage_ah", None)
                extra = ({"voltage_line_ah": round(float(q_v[cells[0]]), 6)}
                         if q_v is not None and np.isfinite(q_v[cells[0]]) else {})
                log.warning(f"capacity estimate at its {name} bound: the stated capacity is wrong for these cells "
                            "and their SOC is unreliable; check pack.capacity_ah",
                            cells=cells[:20].tolist(), n_cells=int(cells.size), bound=name,
                            bound_ah=round(factor * stated, 6), stated_ah=stated, config_key="pack.capacity_ah",
                            **extra)
        back = np.flatnonzero(changed & (side == 0))
        if back.size:
            log.info("capacity estimate back inside its bounds", cells=back[:20].tolist(), n_cells=int(back.size))

    def _log_input_losses(self, sample: Sample, lost: bool) -> None:
        """One WARNING when the pack current is lost (counted with its running mean) and one when cells go
        stale (naming them), one INFO when each comes back; nothing while nothing changes. A sample without
        a current marks every cell invalid, so the stale cells are followed on samples with one."""
        c = self.counters
        if lost and self._lost_since is None:
            self._lost_since = c.samples_current_invalid - 1
            log.warning("pack current lost: the SOC is counted with the current's running mean and the cell "
                        "voltages are not read until it is back", t_s=sample.t_s,
                        samples_current_invalid=c.samples_current_invalid)
        elif not lost and self._lost_since is not None:
            log.info("pack current back", t_s=sample.t_s, lost_samples=c.samples_current_invalid - self._lost_since)
            self._lost_since = None
        if lost:
            return
        stale = ~np.asarray(sample.valid, dtype=bool)
        if np.array_equal(stale, self._stale):
            return
        gone, back = np.flatnonzero(stale & ~self._stale), np.flatnonzero(~stale & self._stale)
        self._stale = stale
        c.stale_changes += 1
        if c.stale_changes > _STALE_LINES and c.stale_changes % _LOG_EVERY:
            return  # a cell at the edge of its staleness flips every few samples: not a line each time
        if gone.size:
            log.warning("cells stale: no usable voltage within estimator.staleness_s; their SOC is counted "
                        "without the voltage's correction", cells=gone[:20].tolist(), n_cells=int(gone.size),
                        staleness_s=self.sampler.staleness_s, config_key="estimator.staleness_s", t_s=sample.t_s,
                        stale_changes=c.stale_changes)
        if back.size:
            log.info("cells no longer stale", cells=back[:20].tolist(), n_cells=int(back.size), t_s=sample.t_s,
                     stale_changes=c.stale_changes)

    def clock_stepped(self, t: float, step_s: float) -> None:
        """The frames' time jumped by ``step_s`` at the frame of time ``t`` because the wall clock that
        stamps them was stepped, not because frames stopped (the daemon's
        :class:`~bms_estimator.service.daemon.ClockStepGuard` tells): the gap before the next sample is
        not rested over (the pack was not parked). One log line, counted (``counters.clock_steps``)."""
        self._stepped_at = float(t)
        self.counters.clock_steps += 1
        log.warning("wall clock stepped: the frames' time jumped with no frame missed; not rested over",
                    step_s=round(step_s, 3), t=t, clock_steps=self.counters.clock_steps)

    def rest(self, gap_s: float, why: str) -> None:
        """The estimator (and the SOP/SOE/SOH part, when given) rests over ``gap_s`` seconds without
        samples (the pack parked); one log line, counted."""
        rest_estimators(self.estimator, self.sox, gap_s)
        self.counters.rests += 1
        self.counters.rest_s += gap_s
        log.info("estimator rested over a gap without samples", gap_s=round(gap_s, 3), why=why,
                 rests=self.counters.rests)

    def _snapshot(self, sample: Sample) -> Snapshot:
        est = self.estimator
        valid = np.array(sample.valid, dtype=bool, copy=True)
        n_valid = int(np.count_nonzero(valid))
        soc = np.array(est.soc, dtype=float, copy=True)
        params = est.params
        if not np.isfinite(soc).any():
            self.state = EstimatorState.INIT
        elif n_valid < self.n_cells or not sample.current_valid:
            self.state = EstimatorState.DEGRADED
        else:
            self.state = EstimatorState.RUNNING
        capacity = np.array(est.capacity_ah, dtype=float, copy=True)
        with np.errstate(all="ignore"):
            cells = {
                "soc": soc,
                **params,
                "tau1_s": params["r1_ohm"] * params["c1_f"],
                "tau2_s": params["r2_ohm"] * params["c2_f"],
                "voltage_v": sample.cell_voltage_v,
                "temperature_c": sample.cell_temperature_c,
                "capacity_ah": np.broadcast_to(capacity, (self.n_cells,)),
            }
        sox = self.sox
        pack_sox: dict[str, float] = {}
        if sox is not None and sox.outputs:
            cells.update({k: np.array(v, dtype=float, copy=True) for k, v in sox.outputs.items()})
            pack_sox = sox.pack_outputs()
        for f in CELL_FIELDS:  # further per-cell outputs the estimator offers (schema.CellField.estimator)
            if f.estimator is not None and f.key not in cells and hasattr(est, f.estimator):
                value = np.array(getattr(est, f.estimator), dtype=float, copy=True)
                cells[f.key] = np.broadcast_to(value, (self.n_cells,))
        return Snapshot(
            t_s=sample.t_s,
            wall_time=self._wall_clock(),
            current_a=sample.current_a,
            current_valid=bool(sample.current_valid),
            pack_voltage_v=sample.pack_voltage_v,
            cells=cells,
            valid=valid,
            soc=soc_stats(soc),
            capacity_ah_mean=float(np.mean(capacity)),
            state=self.state,
            counters=self.status_counters(self.state, self.n_cells - n_valid),
            sample=sample,
            pack_sox=pack_sox,
        )

    def status_counters(self, state: EstimatorState, stale_cells: int) -> StatusCounters:
        dc, sc = self.decoder.counters, self.sampler.counters
        return StatusCounters(
            uptime_s=self._clock() - self._started,
            samples=sc.samples,
            decode_errors=dc.errors,
            rejections=int(np.sum(self.estimator.identifier.rejections)),
            stale_cells=int(stale_cells),
            time_jumps=sc.time_jumps + sc.rewinds,
            backward_frames=sc.backward_frames,
            estimator_state=int(state),
        )

    def failed(self, where: str, exc: BaseException) -> None:
        """Count and log (rate limited) an exception caught in the data path."""
        self.counters.tick_errors += 1
        n = self.counters.tick_errors
        if self._errors_logged < 5 or n % _LOG_EVERY == 0:
            self._errors_logged += 1
            log.error("estimator tick failed", where=where, error=f"{type(exc).__name__}: {exc}",
                      errors=n, exc_info=exc)

