"""The service's estimator over :class:`~.samples.SampleArrays`: per-cell SOC and parameters of one drive, or a vehicle's drives chained.

Each sample goes through :meth:`bms_estimator.service.pipeline.Pipeline.tick`, the
service's own step (``SocEstimator.update`` when the current is valid, else skipped; the
snapshot's per-cell values), so the results are the service's by construction: the
estimator is vectorised over the cells and fed sample by sample, in time order.

Chaining: a vehicle's drives in time order, the estimator state carried from one drive to
the next as the service carries it across a restart: ``SocEstimator.state_dict()`` at the
end of a drive (what ``service/state.py`` saves), ``load_state_dict`` into a fresh
estimator for the next (what the daemon's ``restore`` does); decoder and sampler start
fresh, as after a restart.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from ..can.decoder import FrameDecoder
from ..can.sampler import SampleAssembler
from ..core.soc import SocEstimator
from ..service.pipeline import Pipeline, Snapshot
from .samples import SampleArrays

__all__ = ["DriveEstimate", "estimate_drive", "carry_state"]


@dataclass(frozen=True, eq=False)
class DriveEstimate:
    """The snapshots of one drive as arrays: ``cells[key]`` is (K, N) for every per-cell key of the snapshot."""

    t_s: np.ndarray  # (K,)
    current_a: np.ndarray  # (K,)
    valid: np.ndarray  # (K, N) bool
    cells: dict[str, np.ndarray]
    state: dict[str, np.ndarray] = field(repr=False)  # estimator state at the end (for the next drive)

    def __len__(self) -> int:
        return int(self.t_s.shape[0])


def carry_state(make_estimator: Callable[[], SocEstimator], state: dict[str, np.ndarray] | None) -> SocEstimator:
    """A fresh estimator, resumed from ``state`` (a ``state_dict``) when given: the daemon's restore."""
    est = make_estimator()
    if state is not None:
        est.load_state_dict({k: np.array(v, copy=True) for k, v in state.items()})
    return est


def estimate_drive(samples: SampleArrays, estimator: SocEstimator, decoder: FrameDecoder,
                   sampler: SampleAssembler) -> DriveEstimate:
    """Run ``estimator`` over every sample of one drive (``decoder``/``sampler`` only feed the status counters)."""
    pipe = Pipeline(decoder, sampler, estimator, clock=lambda: 0.0, wall_clock=lambda: 0.0)
    k, n = len(samples), samples.n_cells
    store: dict[str, np.ndarray] = {}
    row = [0]

    def keep(snap: Snapshot) -> None:
        i = row[0]
        for key, value in snap.cells.items():
            arr = store.get(key)
            if arr is None:
                arr = store[key] = np.full((k, n), np.nan)
            arr[i] = value
        row[0] = i + 1

    pipe.add_hook(keep)
    for i in range(k):
        before = row[0]
        pipe.tick(samples.sample(i))
        if row[0] == before:  # the tick failed (logged by the pipeline): keep the row aligned, NaN
            row[0] += 1
    return DriveEstimate(t_s=samples.t_s.copy(), current_a=samples.current_a.copy(), valid=samples.valid.copy(),
                         cells=store, state={key: np.array(v, copy=True) for key, v in pipe.estimator.state_dict().items()})
