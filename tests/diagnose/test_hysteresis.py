"""The one-state hysteresis model (core/hysteresis.py): offline and online."""

from __future__ import annotations

import math

import numpy as np
import pytest

from bms_estimator.core.hysteresis import HysteresisParams, HysteresisState, hysteresis_trajectory, hysteresis_voltage


def _scalar_reference(current_a, dt_s, capacity_ah, gamma, h0=0.0) -> np.ndarray:
    """Plain loop of the recursion, to compare the vectorised solution with."""
    h, out = float(h0), []
    for x in np.asarray(current_a, dtype=float):
        out.append(h)
        a = math.exp(-abs(x) * gamma * dt_s / (3600.0 * capacity_ah))
        h = a * h + (1.0 - a) * (1.0 if x > 0 else (-1.0 if x < 0 else 0.0))
    return np.asarray(out)


def _profile(n=4000, seed=0, lo=-15.0, hi=8.0):
    rng = np.random.default_rng(seed)
    i = np.repeat(rng.uniform(lo, hi, n // 20 + 1), 20)[:n]
    i[rng.random(n) < 0.15] = 0.0
    return i


@pytest.mark.parametrize("gamma", [1.0, 30.0, 300.0, 1e5])
def test_vectorised_recursion_matches_the_plain_loop(gamma):
    i = _profile()
    h, s = hysteresis_trajectory(i, 1.0, 3.0, gamma, h0=0.7)
    np.testing.assert_allclose(h, _scalar_reference(i, 1.0, 3.0, gamma, 0.7), atol=1e-9)
    assert np.all(np.abs(h) <= 1.0 + 1e-12)
    hz, _, p = hysteresis_trajectory(i, 1.0, 3.0, gamma, unit_h0=True)
    np.testing.assert_allclose(hz + 0.7 * p, h, atol=1e-9)


def test_held_sign_and_direction_convention():
    i = np.array([0.0, 2.0, 0.0, 0.0, -3.0, 0.01, 0.0])
    _, s = hysteresis_trajectory(i, 1.0, 3.0, 10.0)
    np.testing.assert_array_equal(s, [0, 1, 1, 1, -1, -1, -1])  # rest keeps the last direction
    h, _ = hysteresis_trajectory(np.full(3600, 3.0), 1.0, 3.0, 20.0)  # 1C charge for an hour
    assert h[-1] > 0.99  # charging drives the state to +1: the voltage sits on the charge branch


def test_online_state_equals_offline_for_many_cells():
    i = _profile()
    params = HysteresisParams(m_v=0.012, m0_v=0.003, gamma=40.0, h0=1.0)
    st = HysteresisState(3, 3.0, params)
    out = np.array([st.update(np.array([x, 0.5 * x, -x])) for x in i])
    np.testing.assert_allclose(out[:, 0], hysteresis_voltage(i, 1.0, 3.0, params), atol=1e-12)
    np.testing.assert_allclose(out[:, 2], hysteresis_voltage(-i, 1.0, 3.0, params), atol=1e-12)
    st2 = HysteresisState(3, 3.0, params)
    st2.load_state_dict(st.state_dict())
    np.testing.assert_array_equal(st2.h, st.h)


