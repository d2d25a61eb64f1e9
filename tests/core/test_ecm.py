import numpy as np
import pytest

from bms_estimator.core.ecm import EcmParams, simulate_ecm


def test_zoh_step_response_is_exact():
    n, i0 = 600, -2.0
    p = EcmParams.from_rc(0.02, [0.01, 0.015], [10.0, 200.0])
    v = simulate_ecm(np.full(n, i0), 1.0, p).voltage_v
    t = np.arange(n)
    exact = i0 * (0.02 + 0.01 * (1 - np.exp(-t / 10.0)) + 0.015 * (1 - np.exp(-t / 200.0)))
    np.testing.assert_allclose(v, exact, atol=1e-12)


def test_varying_parameters_match_constant_ones_and_cells_vectorise():
    rng = np.random.default_rng(0)
    i = rng.normal(0, 2, 300)
    p = EcmParams.from_rc(0.02, [0.01, 0.015], [10.0, 200.0], 0.003)
    const = simulate_ecm(i, 1.0, p, output="mean").voltage_v
    pv = EcmParams.from_rc(np.full(300, 0.02), np.tile([0.01, 0.015], (300, 1)), np.tile([10.0, 200.0], (300, 1)), 0.003)
    np.testing.assert_allclose(simulate_ecm(i, 1.0, pv, output="mean").voltage_v, const, atol=1e-12)
    two = simulate_ecm(np.stack([i, 2 * i], axis=1), 1.0, EcmParams.from_rc(0.02, [0.01, 0.015], [10.0, 200.0]))
    np.testing.assert_allclose(two.voltage_v[:, 1], 2 * two.voltage_v[:, 0], atol=1e-12)


def test_ocv_and_coulomb_counting(nmc_like_ocv):
    i = np.full(3600, -3.0)  # 3 Ah out of a 3 Ah cell: full to empty
    sim = simulate_ecm(i, 1.0, EcmParams.from_rc(0.0, [0.0], [1.0]), nmc_like_ocv.ocv, soc0=1.0, capacity_ah=3.0)
    assert sim.soc[0] == 1.0 and np.isclose(sim.soc[-1], 1 / 3600, atol=1e-9)
    np.testing.assert_allclose(sim.voltage_v, nmc_like_ocv.ocv(sim.soc))


def test_bad_input_is_named():
    p = EcmParams.from_rc(0.02, [0.01], [10.0])
    with pytest.raises(ValueError, match="NaN"):
        simulate_ecm(np.array([0.0, np.nan]), 1.0, p)
    with pytest.raises(ValueError, match="tau_s"):
        simulate_ecm(np.zeros(3), 1.0, EcmParams.from_rc(0.02, [0.01], [-1.0]))
