"""Pulse resistance: one R(t) for every current on a linear cell, falling with current on a kinetic one."""

import numpy as np
import pytest

from bms_estimator.core.lif_bv import kinetic_input
from bms_estimator.core.pulse_resistance import pulse_resistance

R0, R1, TAU1, R2, TAU2 = 0.02, 0.01, 3.0, 0.015, 60.0
DT = 0.1
PULSES_A = (-1.5, -3.0, -6.0, -12.0, 6.0)


def _hppc(k1_ohm: float = 0.0, i0_a: float = 3.0):
    """Pulses of 10 s from rest (120 s between), logged every 0.1 s, the first record 0.1 s after the start.

    The voltage is the step response in closed form, so R(t) is known exactly.
    """
    t, i, v = [], [], []
    start = 0.0
    for amp in PULSES_A:
        rest = start + DT * np.arange(1, 1201)
        t += list(rest)
        i += [0.0] * len(rest)
        v += [3.7] * len(rest)
        t_on = rest[-1]  # the pulse starts at the last rest record
        tp = t_on + DT * np.arange(1, 101)
        e = tp - t_on
        u = kinetic_input(amp, i0_a)
        dv = (R0 * amp + (R1 * amp + k1_ohm * u) * (1 - np.exp(-e / TAU1)) + R2 * amp * (1 - np.exp(-e / TAU2)))
        t += list(tp)
        i += [amp] * len(tp)
        v += list(3.7 + dv)
        start = tp[-1]
    return np.array(t), np.array(i), np.array(v)


def test_a_linear_cell_has_one_resistance_at_every_current():
    t, i, v = _hppc()
    p = pulse_resistance(t, i, v, threshold_a=0.1, rest_s=60.0, at_s=(0.2, 1.0, 9.5))
    np.testing.assert_allclose(p.current_a, PULSES_A)
    np.testing.assert_allclose(p.duration_s, 10.0, atol=1e-9)
    expect = [R0 + R1 * (1 - np.exp(-s / TAU1)) + R2 * (1 - np.exp(-s / TAU2)) for s in (0.2, 1.0, 9.5)]
    np.testing.assert_allclose(p.resistance_ohm, np.tile(expect, (len(PULSES_A), 1)), rtol=1e-9)


def test_a_kinetic_cell_shows_a_resistance_falling_with_current():
    t, i, v = _hppc(k1_ohm=0.008)
    p = pulse_resistance(t, i, v, threshold_a=0.1, at_s=(1.0, 9.5))
    cur = np.array(PULSES_A)
    e1, e2 = 1 - np.exp(-9.5 / TAU1), 1 - np.exp(-9.5 / TAU2)
    expect = R0 + (R1 + 0.008 * kinetic_input(cur, 3.0) / cur) * e1 + R2 * e2
    np.testing.assert_allclose(p.resistance_ohm[:, 1], expect, rtol=1e-9)
    r = p.resistance_ohm[np.argsort(np.abs(cur)), 1]
    assert np.all(np.diff(r[[0, 1, 2, 4]]) < 0) and r[-1] < 0.9 * r[0], r  # 1.5, 3, 6, 12 A


def test_pulses_without_rest_before_and_times_beyond_the_pulse_are_left_out():
    t, i, v = _hppc()
    p = pulse_resistance(t, i, v, threshold_a=0.1, rest_s=200.0, at_s=(1.0, 20.0))
    assert len(p.current_a) == 0 and p.resistance_ohm.shape == (0, 2)
    p = pulse_resistance(t, i, v, threshold_a=0.1, at_s=(1.0, 20.0))
    assert np.all(np.isfinite(p.resistance_ohm[:, 0])) and np.all(np.isnan(p.resistance_ohm[:, 1]))


@pytest.mark.parametrize("bad, match", [
    (dict(threshold_a=0.0), "threshold_a"),
    (dict(time_s=np.zeros(5)), "time must increase"),
    (dict(current_a=np.zeros(3)), "one length"),
])
def test_bad_input_is_named(bad, match):
    args = dict(time_s=np.arange(5.0), current_a=np.zeros(5), voltage_v=np.full(5, 3.7), threshold_a=0.1)
    args.update(bad)
    with pytest.raises(ValueError, match=match):
        pulse_resistance(**args)
