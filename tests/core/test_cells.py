"""bms_estimator.core.cells: the hot path's stand-ins for np.broadcast_to and np.clip give the same values."""

from __future__ import annotations

import numpy as np
import pytest

from bms_estimator.core.cells import all_cells, any_cell, cell_vector, clip


def test_cell_vector_passes_a_vector_through_and_broadcasts_anything_else() -> None:
    v = np.arange(4.0)
    assert cell_vector(v, 4) is v
    filled = cell_vector(2.5, 4)
    assert filled.shape == (4,) and np.array_equal(filled, np.full(4, 2.5))
    for x in (np.float64(1.5), 3, np.array([1.0]), np.arange(4, dtype=np.float32), [1, 2, 3, 4]):
        ref = np.broadcast_to(np.asarray(x, dtype=float), (4,))
        out = cell_vector(x, 4)
        assert out.dtype == np.float64 and np.array_equal(out, ref)
    assert cell_vector(np.arange(3.0), 4 - 1).shape == (3,)
    try:
        cell_vector(np.arange(3.0), 4)
    except ValueError:
        pass
    else:  # a vector of another length is an error, as broadcasting makes it
        raise AssertionError("a 3-vector for 4 cells was accepted")


def test_clip_is_np_clip_bit_for_bit() -> None:
    a = np.array([-0.0, 0.0, np.nan, -np.inf, np.inf, -1.0, 0.5, 2.0, 1.0])
    lo, hi = np.array([0.0] * 8 + [1.5]), 1.0
    for args in ((a, 0.0, 1.0), (a, lo, hi), (a, -1e-3, 0.25)):
        assert clip(*args).tobytes() == np.clip(*args).tobytes()
    out = np.empty_like(a)
    assert clip(a, 0.0, 1.0, out=out) is out and out.tobytes() == np.clip(a, 0.0, 1.0).tobytes()


@pytest.mark.parametrize("x", [
    np.zeros(5, bool), np.ones(5, bool), np.array([False, True, False]), np.array([0.0, -0.0]), np.array([0.0, np.nan]),
    np.array([0.0, 1e-300]), np.array([0.0, -np.inf]), np.zeros(0, bool), np.zeros((3, 2)), np.eye(3),
])
def test_any_cell_and_all_cells_are_any_and_all(x):
    assert any_cell(x) is bool(x.any()) and all_cells(x) is bool(x.all())
