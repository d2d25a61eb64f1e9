"""Arrhenius scaling of the 2-RC resistances (core/arrhenius.py) and its reuse by the resistance SOH."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bms_estimator.core.arrhenius import arrhenius_factor, resistances_at
from bms_estimator.core.soh import SohConfig, r0_at_reference


def _params(n=3):
    r = np.array([0.02, 0.03, 0.05])[:n]
    return {"r0_ohm": r, "r1_ohm": 0.5 * r, "c1_f": np.full(n, 800.0), "r2_ohm": 2 * r,
            "c2_f": np.full(n, 9000.0), "c0_v": np.full(n, 1e-3), "tau1_s": 0.5 * r * 800.0,
            "tau2_s": 2 * r * 9000.0}


def test_factor_is_the_arrhenius_law():
    f = arrhenius_factor([25.0, 32.0, 0.0], 25.0, 2500.0)
    expect = [1.0, math.exp(2500 * (1 / 305.15 - 1 / 298.15)), math.exp(2500 * (1 / 273.15 - 1 / 298.15))]
    np.testing.assert_allclose(f, expect, rtol=1e-12)
    assert f[1] < 1.0 < f[2]  # warmer: lower resistance; colder: higher


def test_missing_temperature_leaves_the_resistance_alone():
    f = arrhenius_factor([np.nan, 30.0, np.inf], [25.0, np.nan, 25.0], 2500.0)
    np.testing.assert_array_equal(f, [1.0, 1.0, 1.0])


@pytest.mark.parametrize("bad", [-1.0, np.nan, np.inf])
def test_bad_activation_temperature_is_named(bad):
    with pytest.raises(ValueError, match="activation temperature"):
        arrhenius_factor(30.0, 25.0, bad)


def test_resistances_scale_and_time_constants_stay():
    p = _params()
    q = resistances_at(p, np.array([35.0, 25.0, 10.0]), 25.0, 2500.0)
    f = arrhenius_factor(np.array([35.0, 25.0, 10.0]), 25.0, 2500.0)
    for key in ("r0_ohm", "r1_ohm", "r2_ohm"):
        np.testing.assert_allclose(q[key], p[key] * f)
    np.testing.assert_allclose(q["r1_ohm"] * q["c1_f"], p["r1_ohm"] * p["c1_f"])
    np.testing.assert_allclose(q["r2_ohm"] * q["c2_f"], p["r2_ohm"] * p["c2_f"])
    np.testing.assert_array_equal(q["tau2_s"], p["tau2_s"])
    np.testing.assert_array_equal(q["c0_v"], p["c0_v"])  # an OCV error, not a resistance
    assert p["r0_ohm"][0] == 0.02  # the input is not changed in place


def test_resistance_soh_uses_the_same_law():
    cfg = SohConfig()
    t = np.array([0.0, 25.0, 40.0, np.nan])
    got = r0_at_reference(np.full(4, 0.03), t, cfg)
    k = t + 273.15
    expect = 0.03 * np.exp(-cfg.r0_activation_k * (1 / k - 1 / (cfg.reference_temperature_c + 273.15)))
    np.testing.assert_allclose(got[:3], expect[:3], rtol=1e-12)
    assert np.isnan(got[3])


temps = st.floats(-40.0, 80.0) | st.just(float("nan"))


@settings(max_examples=200, deadline=None)
@given(t=st.lists(temps, min_size=1, max_size=6), t_ref=temps, b=st.floats(0.0, 10000.0),
       r=st.floats(1e-5, 1.0))
def test_no_nan_and_no_inadmissible_parameter_leaves_it(t, t_ref, b, r):
    n = len(t)
    p = {"r0_ohm": np.full(n, r), "r1_ohm": np.full(n, r / 2), "r2_ohm": np.full(n, r),
         "c1_f": np.full(n, 100.0), "c2_f": np.full(n, 5000.0), "k1_ohm": np.full(n, -r / 4)}
    q = resistances_at(p, np.array(t), t_ref, b)
    for key, x in q.items():
        assert np.all(np.isfinite(x)), key
    for key in ("r0_ohm", "r1_ohm", "r2_ohm", "c1_f", "c2_f"):
        assert np.all(q[key] > 0), key
    # the kinetic gain keeps its sign and its bound |K| <= R (core/lif_bv.py's guard)
    assert np.all(np.abs(q["k1_ohm"]) <= q["r1_ohm"])
    # there and back again
    back = resistances_at(q, t_ref, np.array(t), b)
    np.testing.assert_allclose(back["r2_ohm"], p["r2_ohm"], rtol=1e-9)


def test_both_kinetic_gains_scale_as_resistances():
    """K1 and K2 (lif_bv's kinetic terms) are resistances: both take the factor f."""
    p = {"k1_ohm": np.array([0.004]), "k2_ohm": np.array([-0.006])}
    q = resistances_at(p, 0.0, 25.0, 2500.0)
    f = float(arrhenius_factor(0.0, 25.0, 2500.0))
    assert q["k1_ohm"][0] == pytest.approx(0.004 * f) and q["k2_ohm"][0] == pytest.approx(-0.006 * f)
