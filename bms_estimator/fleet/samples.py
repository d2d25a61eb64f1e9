"""The service's samples of one drive as arrays: what bulk decode produces and the estimator consumes."""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field

import numpy as np

from ..can.sampler import Sample

__all__ = ["SampleArrays"]


@dataclass(frozen=True, eq=False)
class SampleArrays:
    """K samples of N cells, field for field the :class:`~bms_estimator.can.sampler.Sample` stream.

    Row k is the k-th sample :class:`~bms_estimator.can.sampler.SampleAssembler`
    would emit for the same frames (period ``[t_s - period_s, t_s)``).
    """

    t_s: np.ndarray  # (K,) end of each period, on the log's time base
    current_a: np.ndarray  # (K,) mean current, A, positive = charge; NaN if unknown
    current_valid: np.ndarray  # (K,) bool
    current_coverage: np.ndarray  # (K,) fraction of the period with a known (held) current
    cell_voltage_v: np.ndarray  # (K, N)
    cell_temperature_c: np.ndarray  # (K, N) NaN if unknown or stale
    valid: np.ndarray  # (K, N) bool: fresh voltage and current_valid
    pack_voltage_v: np.ndarray  # (K,) NaN if unknown or stale
    period_s: float = 1.0
    counters: dict[str, int] = field(default_factory=dict)  # decoder and sampler counters, summed

    def __len__(self) -> int:
        return int(self.t_s.shape[0])

    @property
    def n_cells(self) -> int:
        return int(self.cell_voltage_v.shape[1])

    @classmethod
    def from_samples(cls, samples: Iterable[Sample], n_cells: int, period_s: float = 1.0,
                     counters: dict[str, int] | None = None) -> SampleArrays:
        """Stack a stream of :class:`Sample` (the service's path) into arrays."""
        s = list(samples)
        k = len(s)
        return cls(
            t_s=np.array([x.t_s for x in s], dtype=float),
            current_a=np.array([x.current_a for x in s], dtype=float),
            current_valid=np.array([x.current_valid for x in s], dtype=bool),
            current_coverage=np.array([x.current_coverage for x in s], dtype=float),
            cell_voltage_v=np.array([x.cell_voltage_v for x in s], dtype=float).reshape(k, n_cells),
            cell_temperature_c=np.array([x.cell_temperature_c for x in s], dtype=float).reshape(k, n_cells),
            valid=np.array([x.valid for x in s], dtype=bool).reshape(k, n_cells),
            pack_voltage_v=np.array([x.pack_voltage_v for x in s], dtype=float),
            period_s=float(period_s),
            counters=dict(counters or {}),
        )

    @classmethod
    def from_recording(cls, rec, period_s: float = 1.0) -> SampleArrays:
        """A single-cell recording (the project's CSV layout, :func:`bms_estimator.data.load_recording`)
        as one cell's samples: sample ``k`` holds the bin ``[t_k, t_k + period)`` (the bin's mean
        current, voltage and temperature), so ``t_s = t_k + period`` (the period's end, as the sampler
        stamps). Raises ``ValueError`` when the recording's step is not ``period_s``."""
        t = np.asarray(rec.time_s, dtype=float)
        if len(t) > 1 and not np.allclose(np.diff(t), period_s, rtol=0, atol=1e-9 * period_s):
            step = np.diff(t)
            raise ValueError(f"{rec.source}: the recording's step ({np.min(step):g}..{np.max(step):g} s, median "
                             f"{np.median(step):g} s after averaging to the period) is not the estimator's sample "
                             f"period {period_s:g} s: batch takes recordings logged at that period or finer")
        k = t.shape[0]
        v = np.asarray(rec.voltage_v, dtype=float).reshape(k, 1)
        temp = (np.full((k, 1), np.nan) if rec.temperature_c is None
                else np.asarray(rec.temperature_c, dtype=float).reshape(k, 1))
        i = np.asarray(rec.current_a, dtype=float)
        ok_i = np.isfinite(i)
        return cls(t_s=t + period_s, current_a=i.copy(), current_valid=ok_i, current_coverage=ok_i.astype(float),
                   cell_voltage_v=v.copy(), cell_temperature_c=temp, valid=np.isfinite(v) & ok_i[:, None],
                   pack_voltage_v=v[:, 0].copy(), period_s=float(period_s), counters={"samples": k})

    def sample(self, k: int) -> Sample:
        """Row k as a :class:`Sample`."""
        return Sample(float(self.t_s[k]), float(self.current_a[k]), self.cell_voltage_v[k],
                      self.cell_temperature_c[k], self.valid[k], float(self.pack_voltage_v[k]),
                      bool(self.current_valid[k]), float(self.current_coverage[k]), self.period_s)
