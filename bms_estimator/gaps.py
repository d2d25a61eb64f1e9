"""A recording's logging gaps as the service sees them: which samples are fed, how long to rest before each.

A recording on a resampled grid marks the bins that held no sample of the file
(``unlogged``: :attr:`CellRecording.filled <bms_estimator.data.CellRecording.filled>`;
``load_recording`` holds the current and interpolates the voltage there).  The
service never sees such bins: its sampler (:mod:`bms_estimator.can.sampler`) bridges
a stretch without frames of up to :data:`MAX_GAP_S` (the sampler's default ``max_gap_s``) with
stale samples, and calls a longer one a time jump, over which the estimator rests
(``SocEstimator.rest``, ``core.sox.rest_estimators``).  The offline paths that run
the estimator over a file (``soc``, the SOC matrix, the SOP back-test) do the same
from one :class:`RestPlan`:

* a run of unlogged bins longer than ``MAX_GAP_S`` (:func:`logging_gaps`; for a file logged coarser
  than 2.5 s, two of its steps, as the service's sampler at that period bridges) is not fed
  (``fed[k] = False``); shorter runs (the HPPC files' 1.2 s holes at pulse edges) are
  fed as ``load_recording`` filled them, as the sampler's stale samples would be;
* before every fed sample, the time without samples since the previous fed one,
  :func:`gap_before_s` of the fed samples' period ends
  ``t_k + Ts`` (the sampler's own rule), is rested over when it exceeds ``MAX_GAP_S`` (two
  steps of a file logged coarser than 2.5 s):
  ``rest_before_s[k] = T``.  For a run of ``g`` unlogged bins between fed samples,
  ``T = g Ts``; a file not resampled (logged at the grid's step or coarser) has no
  unlogged bins, and a jump of its time axis longer than ``MAX_GAP_S`` is rested over
  the same way.

``rest_over_gaps=False`` feeds every sample and rests nowhere (the gaps as if
contiguous samples, as before the offline paths rested).

The same drive logged at 0.1 s and at 1 s gives one plan: ``load_recording`` puts
a 1 s file with holes in its time axis on the grid too (its holes become unlogged
bins), so both are fed, rested and traced alike.  What a file cannot say is the
charge inside a gap: the recording holds the last logged current there (its
coulomb count, and the reference counted from it), the estimator rests (parked,
zero current).  :func:`held_charge_in_gaps` gives that charge per gap rested
over, for the commands to say so.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["MAX_GAP_S", "RestPlan", "gap_before_s", "held_charge_in_gaps", "logging_gaps", "recording_rest_plan",
           "rest_plan"]

#: the default ``max_gap_s``: a stretch without frames up to this long is bridged with stale samples,
#: a longer one is a time jump (the estimator rests over it); the service's is max(this, staleness_s,
#: 2 periods), this at its defaults
MAX_GAP_S = 5.0


def gap_before_s(t_s, t_prev_s, period_s: float):
    """Seconds without samples before a sample that ends at ``t_s`` when the previous one ended at
    ``t_prev_s``: ``t_s - period_s - t_prev_s`` where that is more than half a period (the grid was
    re-anchored on a time jump), else 0.  Scalars or arrays (elementwise): the service's pipeline asks
    it per sample, the fleet's bulk path for a whole drive at once."""
    d = np.asarray(t_s, dtype=float) - period_s - t_prev_s
    return np.where(d > 0.5 * period_s, d, 0.0)


def logging_gaps(unlogged, dt_s: float, bridged_s: float = MAX_GAP_S) -> list[tuple[int, int]]:
    """``[start, end)`` of the runs of samples without a logged sample (``unlogged``, one bool per
    sample of a grid of step ``dt_s``) longer than ``bridged_s``, ``(end - start) dt_s > bridged_s``:
    the stretches the service's sampler calls a time jump rather than bridge with stale samples."""
    d = np.diff(np.r_[0, np.asarray(unlogged, dtype=np.int8), 0])
    return [(int(a), int(b)) for a, b in zip(np.flatnonzero(d == 1), np.flatnonzero(d == -1))
            if (b - a) * dt_s > bridged_s]


@dataclass(frozen=True, eq=False)
class RestPlan:
    """Per sample of a recording: whether it is fed to the estimator, and the seconds to rest before it."""

    fed: np.ndarray  # (n,) bool
    rest_before_s: np.ndarray  # (n,) float, 0 = no rest (always 0 where not fed)

    @property
    def gaps(self) -> int:
        """The number of rests (the time jumps the service would rest over)."""
        return int(np.count_nonzero(self.rest_before_s))

    @property
    def rested_s(self) -> float:
        """Their total length, seconds."""
        return float(self.rest_before_s.sum())

    @property
    def not_fed(self) -> int:
        """The samples not fed (inside the gaps)."""
        return int(self.fed.size - np.count_nonzero(self.fed))

    def first_fed(self, k: int) -> int | None:
        """The first fed sample at or after ``k`` (None: none is)."""
        later = np.flatnonzero(self.fed[max(int(k), 0):])
        return int(k) + int(later[0]) if later.size else None


def rest_plan(n: int, dt_s: float, *, unlogged=None, time_s=None, rest_over_gaps: bool = True,
              bridged_s: float | None = None) -> RestPlan:
    """The :class:`RestPlan` of ``n`` samples of step ``dt_s`` (module docstring).

    ``unlogged``: per sample, True where the file logged nothing (None: every sample logged);
    ``time_s``: the samples' times (None: ``k dt_s``).  ``rest_over_gaps=False``: every sample fed,
    no rest.  ``bridged_s``: the longest stretch bridged, by default the service's rule at a period of
    ``dt_s``, ``max(MAX_GAP_S, 2 dt_s)`` (5 s at the data set's 1 s; a 10 s log's one missing record, 10 s
    unlogged, was rested over as parked, and its drive with 15 % of the records missing ran the capacity
    estimate to 2.48 Ah, against 2.83 Ah fed).
    """
    if bridged_s is None:
        bridged_s = max(MAX_GAP_S, 2.0 * dt_s)
    for name, x in (("time_s", time_s), ("unlogged", unlogged)):
        if x is not None and np.shape(x) != (n,):
            raise ValueError(f"{name} has shape {np.shape(x)}, the recording {n} samples")
    fed = np.ones(n, dtype=bool)
    rest_before = np.zeros(n)
    if not rest_over_gaps:
        return RestPlan(fed, rest_before)
    for a, b in ([] if unlogged is None else logging_gaps(unlogged, dt_s, bridged_s)):
        fed[a:b] = False
    # the sampler's rule on the fed samples' period ends (a skipped run's length, or a jump of the time axis)
    k_fed = np.flatnonzero(fed)
    t = np.arange(n) * dt_s if time_s is None else np.asarray(time_s, dtype=float)
    t_end = t[k_fed] + dt_s
    gap = gap_before_s(t_end[1:], t_end[:-1], dt_s)
    rest_before[k_fed[1:]] = np.where(gap > bridged_s, gap, 0.0)  # a shorter one the sampler bridges
    return RestPlan(fed, rest_before)


def recording_rest_plan(rec, rest_over_gaps: bool = True) -> RestPlan:
    """:func:`rest_plan` of a :class:`~bms_estimator.data.CellRecording` (its ``filled`` bins, times, step)."""
    return rest_plan(len(rec), rec.dt_s, unlogged=rec.filled, time_s=rec.time_s, rest_over_gaps=rest_over_gaps)


def held_charge_in_gaps(rec, plan: RestPlan) -> list[tuple[float, float, float]]:
    """Per run of samples ``plan`` does not feed (the gaps rested over): ``(start time s, length s, Ah)``,
    the charge the recording's held current counts there (positive = charge), which the estimator,
    resting, does not: the file does not say what flowed."""
    d = np.diff(np.r_[0, (~plan.fed).astype(np.int8), 0])
    dt = rec.dt_s
    return [(float(rec.time_s[a]), (b - a) * dt, float(np.sum(rec.current_a[a:b])) * dt / 3600.0)
            for a, b in zip(np.flatnonzero(d == 1), np.flatnonzero(d == -1))]
