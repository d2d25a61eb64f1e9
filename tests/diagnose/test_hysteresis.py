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




def test_the_rest_threshold_is_a_c_rate_and_the_start_sign_is_held():
    """Below ``rest_fraction_c * Q`` (C/50: 0.2 A on a 10 Ah cell) a current is rest and the sign is held,
    online as offline; before the first move the sign is ``s0``."""
    i = np.array([0.0, -3.0, 0.1, -0.1, 0.3, 0.1, 0.0])  # 0.1 A is rest on 10 Ah, 0.3 A is not
    params = HysteresisParams(m_v=0.01, m0_v=0.003, gamma=30.0)
    st = HysteresisState(1, 10.0, params)
    s_online = []
    for x in i:
        st.update(np.array([x]))
        s_online.append(st.s[0])
    _, s = hysteresis_trajectory(i, 1.0, 10.0, 30.0)
    np.testing.assert_array_equal(s, [0, -1, -1, -1, 1, 1, 1])
    np.testing.assert_array_equal(s_online, s)
    _, s = hysteresis_trajectory(np.array([0.0, 0.0, 2.0]), 1.0, 3.0, 10.0, s0=-1.0)
    np.testing.assert_array_equal(s, [-1, -1, 1])


def test_an_unknown_current_is_rest_for_the_online_state():
    """A NaN current (a lost frame) moves neither the state nor the held sign: no charge is known to have passed."""
    st = HysteresisState(2, 3.0, HysteresisParams(m_v=0.01, m0_v=0.003, gamma=30.0, h0=-0.5))
    st.update(np.array([-3.0, -3.0]))
    h, s = st.h.copy(), st.s.copy()
    v = st.update(np.array([np.nan, -3.0]))
    assert st.h[0] == h[0] and st.s[0] == s[0] == -1.0
    assert v[0] == pytest.approx(0.01 * h[0] - 0.003)
    assert st.h[1] < h[1]  # the other cell moved on


def test_the_unit_h0_split_is_the_trajectory_from_zero_whatever_h0_is_given():
    """``unit_h0=True`` returns ``h(h0=0)`` and ``P`` (``h = h(h0=0) + h0 P``), also when an ``h0`` is passed."""
    i = _profile(n=2000, seed=4)
    h_zero, _ = hysteresis_trajectory(i, 1.0, 3.0, 30.0)
    h_half, _ = hysteresis_trajectory(i, 1.0, 3.0, 30.0, h0=0.5)
    hz, _, p = hysteresis_trajectory(i, 1.0, 3.0, 30.0, h0=0.5, unit_h0=True)
    np.testing.assert_allclose(hz, h_zero, atol=1e-12)
    np.testing.assert_allclose(hz + 0.5 * p, h_half, atol=1e-9)
