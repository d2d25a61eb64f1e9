"""Batch models (diagnose/extensions.py) and the generator (diagnose/generator.py)."""

from __future__ import annotations

import numpy as np
import pytest

from bms_estimator.core.ecm import EcmParams, simulate_ecm
from bms_estimator.diagnose import CAUSES, Model, Series, fit_model, generate, load_profile
from bms_estimator.diagnose.extensions import rc_mean

LG = "lg-hg2/25degC/la92"


@pytest.fixture(scope="module")
def lg():
    return load_profile(LG)


def test_rc_columns_are_the_simulator_branches(lg):
    i = lg[0][:3000]
    p = EcmParams.from_rc(0.02, [0.01, 0.03], [12.0, 250.0])
    v = simulate_ecm(i, 1.0, p, output="mean").voltage_v
    np.testing.assert_allclose(0.02 * i + 0.01 * rc_mean(i, 12.0) + 0.03 * rc_mean(i, 250.0), v, atol=1e-12)


def test_baseline_fit_recovers_the_clean_cell(lg):
    i, _, _, ocv = lg
    g = generate(i, 1.0, "none", seed=3, ocv=ocv)
    f = fit_model(Model(), g.series())
    b = g.truth["base"]
    assert f.train_rmse_mv == pytest.approx(1.0, abs=0.05)
    for k in ("r0_ohm", "r1_ohm", "r2_ohm"):
        assert f.beta[k] == pytest.approx(b[k], rel=0.1)
    assert f.theta["tau1_s"] == pytest.approx(b["tau1_s"], rel=0.15)
    assert f.theta["tau2_s"] == pytest.approx(b["tau2_s"], rel=0.15)


@pytest.mark.parametrize("cause", CAUSES)
def test_each_extension_fits_its_effect_and_sizes_it(cause, lg):
    i, _, _, ocv = lg
    g = generate(i, 1.0, cause, 4.0, seed=11, ocv=ocv)
    s = g.series()
    base = fit_model(Model(), s)
    m = Model(cause)
    f = fit_model(m, s, start=dict(base.theta))
    assert f.train_rmse_mv < 1.5  # the noise is 1 mV; the baseline leaves 4 mV
    assert base.train_rmse_mv > 3.0
    assert m.components(s, f)[cause] == pytest.approx(4.0, rel=0.15)


def test_generator_is_seeded_and_sizes_effects(lg):
    i, _, _, ocv = lg
    a = generate(i, 1.0, "hysteresis", 3.0, seed=5, ocv=ocv)
    b = generate(i, 1.0, "hysteresis", 3.0, seed=5, ocv=ocv)
    c = generate(i, 1.0, "hysteresis", 3.0, seed=6, ocv=ocv)
    np.testing.assert_array_equal(a.voltage_v, b.voltage_v)
    assert not np.array_equal(a.voltage_v, c.voltage_v)
    assert a.truth["effects"]["hysteresis"]["residual_rms_mv"] == pytest.approx(3.0, rel=0.01)
    raw = generate(i, 1.0, "hysteresis", 3.0, seed=5, ocv=ocv, size_mode="raw")
    assert raw.truth["effects"]["hysteresis"]["raw_rms_mv"] == pytest.approx(3.0, rel=0.01)
    # the stated capacity leaves the profile at 4-12 % SOC
    soc_end = a.series().soc[-1]
    assert 0.03 < soc_end < 0.13
    two = generate(i, 1.0, {"temperature": 5.0, "slow_diffusion": 3.0}, seed=5, ocv=ocv)
    assert two.dominant == "temperature"
    assert set(two.truth["effects"]) == {"temperature", "slow_diffusion"}


def test_capacity_and_offset_are_what_diagnose_sees(lg):
    i, _, _, ocv = lg
    g = generate(i, 1.0, "capacity_error", 3.0, seed=2, ocv=ocv)
    ratio = g.truth["effects"]["capacity_error"]["stated_over_true"]
    assert g.capacity_ah == pytest.approx(g.truth["base"]["capacity_ah"] * ratio)
    o = generate(i, 1.0, "current_offset", 3.0, seed=2, ocv=ocv, noise_a=0.0)
    b = o.truth["effects"]["current_offset"]["offset_a"]
    np.testing.assert_allclose(o.current_a - i, b, atol=1e-12)


def test_generator_refuses_what_a_profile_cannot_show():
    i = -np.abs(np.sin(np.arange(5000) / 50.0)) * 3.0  # discharge only: no charge current
    with pytest.raises(ValueError, match="invisible"):
        generate(i, 1.0, "direction_asymmetry", 3.0, seed=1)
    with pytest.raises(ValueError, match="unknown cause"):
        generate(i, 1.0, "gremlins", 3.0, seed=1)


def test_series_rejects_bad_arrays(lg):
    i, _, _, ocv = lg
    with pytest.raises(ValueError):
        Series(i[:10], np.zeros(9), ocv, 3.0)
    with pytest.raises(ValueError):
        Series(np.array([0.0, np.nan]), np.zeros(2), ocv, 3.0)
