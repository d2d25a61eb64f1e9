"""Per-cell vectors in the estimators' hot paths, without numpy's Python-level call overhead.

At N = 96 cells an elementwise operation costs well under a microsecond of arithmetic, and
numpy's Python wrappers around some of them cost several: ``np.broadcast_to`` (~3 us) and
``np.clip`` (~4 us: argument checks in Python before the ``clip`` ufunc). The estimator
makes dozens of such calls per sample, so these two stand in for them with the same
results, bit for bit:

``cell_vector(x, n)``
    ``x`` itself when it already is an ``(n,)`` float64 array; a Python float filled into a
    new vector; else ``np.broadcast_to(np.asarray(x, dtype=float), (n,))`` (a read-only view).
    The caller must not write to the result.
``clip(a, lo, hi, out=None)``
    numpy's ``clip`` ufunc, the one ``np.clip`` ends in: ``min(max(a, lo), hi)``
    elementwise, NaN propagated.

And the arguments of every estimator's ``rest`` (a gap without samples), checked once:
``rest_arguments(gap_s, cells, n)``.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["all_cells", "any_cell", "cell_vector", "clip", "rest_arguments"]

try:  # numpy >= 2: the ufunc behind np.clip, and the C function behind np.count_nonzero(x)
    from numpy._core.multiarray import count_nonzero as _count_nonzero  # type: ignore[attr-defined]
    from numpy._core.umath import clip  # type: ignore[attr-defined]
except ImportError:  # pragma: no cover - numpy 1.x keeps them here
    from numpy.core.multiarray import count_nonzero as _count_nonzero  # type: ignore[no-redef]
    from numpy.core.umath import clip  # type: ignore[no-redef]

_F8 = np.dtype(np.float64)


def cell_vector(x, n: int) -> np.ndarray:
    """``x`` as an ``(n,)`` float64 vector (``x`` itself when it is one): not to be written to."""
    if type(x) is np.ndarray and x.shape == (n,) and x.dtype == _F8:
        return x
    if type(x) is float:  # one value for every cell (a pack current): filled, as broadcasting would read
        out = np.empty(n)
        out.fill(x)
        return out
    return np.broadcast_to(np.asarray(x, dtype=float), (n,))


def any_cell(x: np.ndarray) -> bool:
    """``x.any()`` for a per-cell array (bool, or numbers: nonzero and NaN count), in a quarter of its time:
    ``count_nonzero`` has a fast path where the reduction goes through the ufunc machinery (per-sample guards)."""
    return bool(_count_nonzero(x))


def all_cells(x: np.ndarray) -> bool:
    """``x.all()`` for a per-cell array, as :func:`any_cell`."""
    return bool(_count_nonzero(x) == x.size)


def rest_arguments(gap_s: float, cells, n: int) -> tuple[float, np.ndarray]:
    """``(gap, mask)`` of a rest over ``gap_s`` seconds for ``cells`` (a bool mask of ``n`` cells; None: all);
    ValueError naming the argument when the gap is not a finite number >= 0 or the mask does not fit."""
    gap = float(gap_s)
    if not (math.isfinite(gap) and gap >= 0.0):
        raise ValueError(f"gap_s must be finite and >= 0 seconds, got {gap_s!r}")
    sel = np.ones(n, dtype=bool) if cells is None else np.asarray(cells, dtype=bool)
    if sel.shape != (n,):
        raise ValueError(f"cells must be a bool mask of {n} cells, got shape {sel.shape}")
    return gap, sel
