"""Cells in consecutive groups: independent packs side by side in one vectorised estimator.

The batch stacks ``S`` drives of ``n`` cells as the cells of one ``S n``-cell estimator
(``fleet/stack.py``).  Whatever a one-pack estimator computes over *all* its cells (a pack
limit, a weakest cell, a refresh when any cell did something) must then be computed over
each group's cells alone.  :class:`CellGroups` gives those reductions per group with the
arithmetic a group of that size gets alone, so that the values are **bit for bit** the
solo ones: a min/max is exact in any order, and a sum of a group's ``n`` values is numpy's
pairwise sum over a contiguous run of ``n`` values, as ``x.sum()`` of the group alone (equal
groups as a ``(..., G, n)`` view summed over its last axis; unequal ones slice by slice).

Vectorised; no I/O.
"""

from __future__ import annotations

import numpy as np

__all__ = ["CellGroups"]


class CellGroups:
    """``sizes[g]`` consecutive cells per group ``g``; ``of[c]`` is the group of cell ``c``."""

    def __init__(self, sizes, n_cells: int) -> None:
        sizes = np.asarray(sizes, dtype=np.int64).reshape(-1)
        if sizes.size == 0 or sizes.sum() != n_cells or np.any(sizes < 1):
            raise ValueError(f"groups of {sizes.tolist()} cells do not make the {n_cells} cells")
        self.sizes = sizes
        self.n = sizes.size
        bounds = np.concatenate(([0], np.cumsum(sizes)))
        self.slices = [slice(int(a), int(b)) for a, b in zip(bounds[:-1], bounds[1:])]
        self.of = np.repeat(np.arange(self.n), sizes)
        self.equal = bool((sizes == sizes[0]).all())

    def reduce(self, func, x) -> np.ndarray:
        """``func(x_g, axis=-1)`` per group: ``(..., N)`` -> ``(..., G)`` (``func``: np.sum, np.min, np.max, np.any)."""
        x = np.asarray(x)
        if self.equal:
            return func(x.reshape(*x.shape[:-1], self.n, -1), axis=-1)
        return np.stack([func(x[..., s], axis=-1) for s in self.slices], axis=-1)

    def any(self, mask) -> np.ndarray:
        """Per cell: whether any cell of its group is in ``mask`` (N,)."""
        return self.reduce(np.any, np.asarray(mask, dtype=bool))[self.of]

    def nanmin(self, x) -> np.ndarray:
        """Per group ``np.nanmin`` of its cells where any is finite, else NaN (the pack figures' rule)."""
        return self._nan_extreme(np.min, np.inf, x)

    def nanmax(self, x) -> np.ndarray:
        """Per group ``np.nanmax`` of its cells where any is finite, else NaN."""
        return self._nan_extreme(np.max, -np.inf, x)

    def _nan_extreme(self, func, fill: float, x) -> np.ndarray:
        x = np.asarray(x, dtype=float)
        seen = self.reduce(np.any, np.isfinite(x))
        m = self.reduce(func, np.where(np.isnan(x), fill, x))
        return np.where(seen, m, np.nan)
