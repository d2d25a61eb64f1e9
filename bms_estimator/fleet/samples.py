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

    def sample(self, k: int) -> Sample:
        """Row k as a :class:`Sample`."""
        return Sample(float(self.t_s[k]), float(self.current_a[k]), self.cell_voltage_v[k],
                      self.cell_temperature_c[k], self.valid[k], float(self.pack_voltage_v[k]),
                      bool(self.current_valid[k]), float(self.current_coverage[k]), self.period_s)
