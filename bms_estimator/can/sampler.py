"""Assemble decoded CAN events into fixed-period samples on FRAME time.

Timing model
------------
* The only clock is the frames' own timestamps (``msg.timestamp``: kernel
  receive time on socketcan, the log's time on replay). The event-loop clock is
  never read, so replaying a log at any speed - or feeding it all at once -
  gives bit-identical samples.
* The grid is ``t_k = k * period_s`` (absolute multiples of the period). The
  first frame at time ``t0`` anchors it: the first period is
  ``[ceil(t0/period)*period, +period)``, so every emitted period is complete;
  frames before that only prime the latest values.
* A period ``[t_k, t_k + period)`` is emitted as a :class:`Sample` with
  ``t_s = t_k + period`` (its END) as soon as a frame with timestamp
  ``>= t_k + period`` arrives. A frame exactly on a boundary belongs to the new
  period. So a sample appears with the first frame after its period ends; if
  the bus goes silent, no sample appears (nothing is made up from the wall clock).

Current
-------
Zero-order hold, weighted by time: each current value holds from its frame's
timestamp until the next current frame (or at most ``current_hold_s``), and
the held current is integrated exactly across the period boundaries. The
sample's ``current_a`` is ``charge / covered time`` (= ``charge / period`` when
the whole period is covered, so the sum of ``current_a * period`` over
samples equals the integral of the held current: charge-exact).
``current_valid`` is False if less than ``min_current_coverage`` of the
period was covered (current frames missing for longer than
``current_hold_s``); then every cell's ``valid`` is False too.

Cell voltages, temperatures, pack voltage
-----------------------------------------
``voltage_mode="latest"``: the latest value at the end of the period;
``"mean"``: the mean of the values received within the period (the latest
value if none arrived). A cell whose latest voltage is older than
``staleness_s`` at the end of the period (or that never had one) is flagged
``valid=False`` and counted; its ``cell_voltage_v`` keeps the last known value
(NaN if none). Temperatures and the pack voltage are NaN when older than their
own staleness limits.

Time anomalies (counted in :class:`SamplerCounters`, logged)
------------------------------------------------------------
* Gap: a frame more than ``max_gap_s`` after the previous frame emits the
  period that was in progress, then re-anchors the grid at the new frame
  (``time_jumps``). So at most ``max_gap_s / period_s + 1`` samples are ever
  emitted for a stretch without frames, and those are flagged stale.
* Backward timestamp by up to ``rewind_s``: the frame is ignored
  (``backward_frames``; logged at the 1st, 10th, 100th, ... such frame).
* Backward by more than ``rewind_s``: a new log or a clock reset; all state is
  dropped and the grid re-anchored at that frame (``rewinds``).
* Non-finite timestamps, timestamps so large that a double no longer resolves a
  thousandth of the period (beyond about 1e13 s: the grid could not advance),
  non-finite values and cell indices outside ``[0, n_cells)`` are ignored and counted.
:meth:`SampleAssembler.feed` never raises.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass, fields
from typing import Literal

import numpy as np
import structlog

from ..gaps import MAX_GAP_S, gap_before_s  # the gap rule is shared with the offline commands
from .decoder import Event, EventKind

__all__ = ["MAX_GAP_S", "Sample", "SampleAssembler", "SamplerCounters", "first_current", "gap_before_s", "sample_current"]

log = structlog.get_logger(__name__)

_CURRENT = int(EventKind.CURRENT)
_PACK_VOLTAGE = int(EventKind.PACK_VOLTAGE)
_CELL_VOLTAGE = int(EventKind.CELL_VOLTAGE)
_CELL_TEMPERATURE = int(EventKind.CELL_TEMPERATURE)

@dataclass(frozen=True, eq=False)
class Sample:
    """One period of input data, ``[t_s - period, t_s)``."""

    t_s: float  # END of the period, on the frames' time base
    current_a: float  # mean current, A, positive = charge; NaN if unknown
    cell_voltage_v: np.ndarray  # (N,) latest (or mean) value; NaN if never received
    cell_temperature_c: np.ndarray  # (N,) NaN if unknown or stale
    valid: np.ndarray  # (N,) bool: fresh voltage AND current_valid
    pack_voltage_v: float  # NaN if unknown or stale
    current_valid: bool = True
    current_coverage: float = 1.0  # fraction of the period with a known (held) current
    period_s: float = 1.0


def sample_current(current_a, current_valid, n_parallel: int = 1):
    """The current the estimator takes for a sample (or an array of them): ``current_a`` where it is
    valid and finite, else NaN, which the estimator counts with the current's running mean
    (:meth:`~bms_estimator.core.soc.SocEstimator.update`, "A lost current"). The service and the
    fleet's re-estimation both take it from here.

    ``current_a`` is the pack's; the estimator models one cell, which carries ``1 / n_parallel`` of it
    (``estimator.sop.n_parallel`` cells in parallel per series element, ``pack.capacity_ah`` one
    cell's: core.sop's module docstring).  Fed the pack current undivided, k cells in parallel counted
    their SOC k times too fast and their pack limits and energy came out k times the truth."""
    if np.ndim(current_a) == 0:
        c = float(current_a)
        return c / n_parallel if current_valid and math.isfinite(c) else math.nan
    c = np.asarray(current_a, dtype=float)
    return np.where(np.asarray(current_valid, dtype=bool) & np.isfinite(c), c / n_parallel, np.nan)


def first_current(current_a: np.ndarray, current_valid: np.ndarray) -> int:
    """The index of the first sample with a valid current (``len`` if none): the estimator is fed from
    there on (before it there is nothing to count; after it a lost current is held, :func:`sample_current`)."""
    ok = np.asarray(current_valid, dtype=bool) & np.isfinite(np.asarray(current_a, dtype=float))
    return int(np.argmax(ok)) if ok.any() else len(ok)


@dataclass
class SamplerCounters:
    samples: int = 0  # samples emitted
    stale_cell_samples: int = 0  # sum over samples of cells with a stale/missing voltage
    current_invalid_samples: int = 0  # samples whose current coverage was too low
    backward_frames: int = 0  # frames ignored: timestamp went back by <= rewind_s
    rewinds: int = 0  # timestamp went back by > rewind_s: state reset
    time_jumps: int = 0  # gap > max_gap_s: grid re-anchored
    bad_timestamps: int = 0  # NaN/inf timestamps
    non_finite_values: int = 0
    bad_cell_index: int = 0
    internal_errors: int = 0

    def as_dict(self) -> dict[str, int]:
        return {f.name: getattr(self, f.name) for f in fields(self)}


class SampleAssembler:
    """Build samples of ``n_cells`` cells every ``period_s`` seconds of frame time."""

    def __init__(
        self,
        n_cells: int,
        period_s: float = 1.0,
        staleness_s: float = 2.5,
        *,
        temperature_staleness_s: float = 30.0,
        pack_voltage_staleness_s: float | None = None,
        current_hold_s: float = 0.5,
        min_current_coverage: float = 0.9,
        voltage_mode: Literal["latest", "mean"] = "latest",
        max_gap_s: float = MAX_GAP_S,
        rewind_s: float = 5.0,
    ) -> None:
        if n_cells < 1:
            raise ValueError("n_cells must be >= 1")
        for name, v in (
            ("period_s", period_s),
            ("staleness_s", staleness_s),
            ("temperature_staleness_s", temperature_staleness_s),
            ("current_hold_s", current_hold_s),
            ("max_gap_s", max_gap_s),
            ("rewind_s", rewind_s),
        ):
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be finite and > 0")
        if voltage_mode not in ("latest", "mean"):
            raise ValueError("voltage_mode must be 'latest' or 'mean'")
        if not 0.0 <= min_current_coverage <= 1.0:
            raise ValueError("min_current_coverage must be in [0, 1]")
        self.n_cells = int(n_cells)
        self.period_s = float(period_s)
        self.staleness_s = float(staleness_s)
        self.temperature_staleness_s = float(temperature_staleness_s)
        self.pack_voltage_staleness_s = float(
            staleness_s if pack_voltage_staleness_s is None else pack_voltage_staleness_s
        )
        self.current_hold_s = float(current_hold_s)
        self.min_current_coverage = float(min_current_coverage)
        self.voltage_mode = voltage_mode
        self.max_gap_s = float(max_gap_s)
        self._time_resolution_s = 1e-3 * float(period_s)  # timestamps coarser than this are refused
        self._max_closes = int(math.ceil(self.max_gap_s / float(period_s))) + 2
        self.rewind_s = float(rewind_s)
        self.counters = SamplerCounters()
        self._reset()

    # ----------------------------------------------------------------- state
    def _reset(self) -> None:
        n = self.n_cells
        self._k: int | None = None  # current period is [k*p, (k+1)*p)
        self._t_start = 0.0
        self._t_next = math.inf
        self._t_last = -math.inf  # latest accepted frame time
        self._v = [math.nan] * n
        self._v_t = [-math.inf] * n
        self._v_sum = [0.0] * n
        self._v_cnt = [0] * n
        self._temp = [math.nan] * n
        self._temp_t = [-math.inf] * n
        self._pv = math.nan
        self._pv_t = -math.inf
        self._i = 0.0  # held current
        self._i_t = -math.inf  # time of the held current's frame
        self._acc_t = -math.inf  # current integrated up to here
        self._q = 0.0  # charge of the current period, A*s
        self._cov = 0.0  # covered time of the current period, s

    def _anchor(self, t: float) -> None:
        p = self.period_s
        k = math.ceil(t / p)
        self._set_period(k)

    def _set_period(self, k: int) -> None:
        p = self.period_s
        self._k = k
        self._t_start = k * p
        self._t_next = (k + 1) * p
        self._q = 0.0
        self._cov = 0.0
        if self.voltage_mode == "mean":
            self._v_sum = [0.0] * self.n_cells
            self._v_cnt = [0] * self.n_cells

    def _integrate_to(self, t: float) -> None:
        """Integrate the held current from where we are up to ``t`` (within the period)."""
        s = self._acc_t if self._acc_t > self._t_start else self._t_start
        hold_end = self._i_t + self.current_hold_s
        e = t if t < hold_end else hold_end
        if e > s:
            self._q += self._i * (e - s)
            self._cov += e - s
        if t > self._acc_t:
            self._acc_t = t

    def _close(self) -> Sample:
        """Emit the period ending at ``self._t_next`` and move to the next one."""
        p = self.period_s
        end = self._t_next
        self._integrate_to(end)
        cov = self._cov
        coverage = min(1.0, cov / p)
        if cov >= p * (1.0 - 1e-9):
            current = self._q / p
        elif cov > 0.0:
            current = self._q / cov
        else:
            current = math.nan
        current_valid = cov > 0.0 and coverage >= self.min_current_coverage
        v_t = np.fromiter(self._v_t, dtype=float, count=self.n_cells)
        fresh = (end - v_t) <= self.staleness_s
        volts = np.fromiter(self._v, dtype=float, count=self.n_cells)
        if self.voltage_mode == "mean":
            cnt = np.fromiter(self._v_cnt, dtype=float, count=self.n_cells)
            sums = np.fromiter(self._v_sum, dtype=float, count=self.n_cells)
            has = cnt > 0
            volts[has] = sums[has] / cnt[has]
        temp_t = np.fromiter(self._temp_t, dtype=float, count=self.n_cells)
        temps = np.fromiter(self._temp, dtype=float, count=self.n_cells)
        temps[(end - temp_t) > self.temperature_staleness_s] = math.nan
        pv = self._pv if (end - self._pv_t) <= self.pack_voltage_staleness_s else math.nan
        valid = fresh & current_valid
        c = self.counters
        c.samples += 1
        c.stale_cell_samples += int(self.n_cells - np.count_nonzero(fresh))
        if not current_valid:
            c.current_invalid_samples += 1
        sample = Sample(
            t_s=end,
            current_a=float(current),
            cell_voltage_v=volts,
            cell_temperature_c=temps,
            valid=valid,
            pack_voltage_v=float(pv),
            current_valid=bool(current_valid),
            current_coverage=float(coverage),
            period_s=p,
        )
        assert self._k is not None
        self._set_period(self._k + 1)
        return sample

    # ------------------------------------------------------------------ feed
    def feed(self, event: Event, timestamp: float) -> list[Sample]:
        """Add one event received at ``timestamp``; returns the samples completed by it."""
        return self.feed_frame((event,), timestamp)

    def feed_frame(self, events: Iterable[Event], timestamp: float) -> list[Sample]:
        """Add all events of one frame (same timestamp); returns completed samples. Never raises."""
        out: list[Sample] = []
        try:
            t = float(timestamp)
            if not math.isfinite(t) or math.ulp(t) > self._time_resolution_s:
                # beyond about 1e13 s (300,000 years) a double cannot tell the sample grid apart:
                # t + period == t, and the grid would never advance (a sender's garbage clock)
                self.counters.bad_timestamps += 1
                return out
            if self._k is None:
                self._anchor(t)
            elif t < self._t_last:
                if self._t_last - t > self.rewind_s:
                    self.counters.rewinds += 1
                    log.warning("can.sampler.rewind", t_last=self._t_last, t=t)
                    self._reset()
                    self._anchor(t)
                else:
                    self._count_backward(self._t_last - t)
                    return out
            elif t >= self._t_next:
                if t - self._t_last > self.max_gap_s:
                    # emit the period in progress (it holds real data), then re-anchor
                    out.append(self._close())
                    self.counters.time_jumps += 1
                    log.warning("can.sampler.time_jump", gap_s=t - self._t_last, t=t)
                    self._anchor(t)
                else:
                    for _ in range(self._max_closes):  # bounded: the gap is at most max_gap_s
                        if t < self._t_next:
                            break
                        out.append(self._close())
            self._apply(events, t)
            self._t_last = t
        except Exception:  # pragma: no cover - defensive: feed must never raise
            self.counters.internal_errors += 1
            log.exception("can.sampler.internal_error")
        return out

    def _count_backward(self, behind_s: float) -> None:
        """Count a frame dropped for being older than the newest one; say it at the 1st, 10th, 100th,
        1000th... (one line a decade: two senders whose clocks disagree drop every frame of one of them)."""
        n = self.counters.backward_frames = self.counters.backward_frames + 1
        if n == 10 ** (len(str(n)) - 1):
            log.warning("can.sampler.backward_frames", behind_s=round(behind_s, 6), backward_frames=n,
                        hint="frames older than the newest one are dropped: two senders (gateways) whose "
                             "clocks disagree, or one frame stamped ahead of the others")

    def _apply(self, events: Iterable[Event], t: float) -> None:
        n = self.n_cells
        c = self.counters
        mean = self.voltage_mode == "mean"
        for ev in events:
            kind, cell, value = ev[0], ev[1], ev[2]
            try:
                value = float(value)
            except (TypeError, ValueError, OverflowError):
                c.non_finite_values += 1
                continue
            if not math.isfinite(value):
                c.non_finite_values += 1
                continue
            if kind == _CELL_VOLTAGE:
                if not (0 <= cell < n):
                    c.bad_cell_index += 1
                    continue
                self._v[cell] = value
                self._v_t[cell] = t
                if mean and t >= self._t_start:
                    self._v_sum[cell] += value
                    self._v_cnt[cell] += 1
            elif kind == _CURRENT:
                self._integrate_to(t)  # nothing is counted before the first period starts
                self._i = value
                self._i_t = t
            elif kind == _CELL_TEMPERATURE:
                if not (0 <= cell < n):
                    c.bad_cell_index += 1
                    continue
                self._temp[cell] = value
                self._temp_t[cell] = t
            elif kind == _PACK_VOLTAGE:
                self._pv = value
                self._pv_t = t

    # ------------------------------------------------------------ inspection
    @property
    def next_boundary_s(self) -> float | None:
        """Frame time at which the period in progress will be emitted (None before the first frame)."""
        return None if self._k is None else self._t_next
