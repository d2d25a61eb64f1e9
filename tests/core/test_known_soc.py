"""Identification along a given SOC path: several paths at once, the output-error capacity,
the known-SOC c0 prior, and the rest-based reference capacity.

The data hide two effects the 2-RC model does not have or is not told: a capacity other
than the stated one, and a slow third RC branch (diffusion, tau 3000 s) whose steady
state a 2-RC model can only mimic by trading c0 against its slow branch.
"""

import numpy as np
import pytest

from bms_estimator.analysis import (
    compare_methods,
    output_error_capacity,
    reference_capacity,
    reference_soc,
    run_identification,
    run_identification_paths,
)
from bms_estimator.core.ecm import EcmParams, simulate_ecm
from bms_estimator.core.identifier import IdentifierConfig, LifEstimator
from bms_estimator.core.rls import WeightedRls
from tests.conftest import pulse_current


def _discharge(n: int, seed: int, mean_c: float, q: float = 2.6) -> np.ndarray:
    """Pulses around a mean discharge of ``mean_c`` C (0.85 of the cell over the file for the default)."""
    i = pulse_current(n, seed, amp_a=3.0)
    return i - i.mean() - mean_c * q


def _cell(i, ocv, q_true, third_rc=False, rest_s=0, seed=0):
    r, tau = [0.01, 0.015], [10.0, 200.0]
    if third_rc:
        r, tau = r + [0.02], tau + [3000.0]
    i = np.concatenate([i, np.zeros(rest_s)])
    sim = simulate_ecm(i, 1.0, EcmParams.from_rc(0.02, r, tau), ocv.ocv, soc0=1.0, capacity_ah=q_true, output="mean")
    rng = np.random.default_rng(seed)
    return i, sim.voltage_v + 3e-4 * rng.standard_normal(len(i))


def test_paths_at_once_equal_one_path_at_a_time(nmc_like_ocv):
    i, v = _cell(_discharge(2400, 1, 0.5), nmc_like_ocv, 2.6)
    paths = np.stack([reference_soc(i, 1.0, q) for q in (2.5, 2.9)], axis=1)
    both = run_identification_paths(i, v, paths, nmc_like_ocv, 2.9)
    for j in range(2):
        one = run_identification(i, v, paths[:, j], nmc_like_ocv, 2.9)
        for key in ("r0_ohm", "tau2_s", "c0_v"):
            np.testing.assert_allclose(both[j].params[key], one.params[key], rtol=1e-9, atol=1e-12)
        assert both[j].rejections == one.rejections


@pytest.mark.parametrize("q_true", [2.45, 2.6, 2.85])
def test_output_error_capacity_finds_the_cells_capacity_not_the_stated_one(nmc_like_ocv, q_true):
    n = 3 * 3600
    i, v = _cell(_discharge(n, 3, 0.85 * q_true * 3600 / n / q_true, q_true), nmc_like_ocv, q_true, seed=3)
    q, profile = output_error_capacity(i, v, nmc_like_ocv, 2.9, config=IdentifierConfig(c0_prior_weight=0.1))
    assert abs(q / q_true - 1) < 0.015, (q, q_true)
    # the profile has its minimum inside the grid, and a wrong capacity simulates worse
    k = int(np.argmin(profile["sim_rmse_mv"]))
    assert 0 < k < len(profile["capacity_ah"]) - 1
    assert profile["sim_rmse_mv"][0] > 2 * profile["sim_rmse_mv"][k]


def test_pseudo_measurement_pulls_the_unexcited_direction_only():
    rls = WeightedRls(1, 2)
    rls.theta[:] = [1.0, 1.0]
    rls.P[:] = np.diag([1.0, 1.0])
    rls.initialised[:] = True
    rls.pseudo_update(np.array([[0.0, 1.0]]), np.array([0.0]), np.array([True]))
    assert rls.theta[0, 0] == 1.0  # the first parameter is not in the prior's row
    assert rls.theta[0, 1] == pytest.approx(0.5)  # equal weight of estimate and prior
    assert rls.P[0, 1, 1] == pytest.approx(0.5)


def test_c0_prior_keeps_c0_small_when_the_model_misses_a_slow_branch(nmc_like_ocv):
    """Train on a steady 0.5 C discharge, where c0 and the slow branch are collinear; validate at 0.15 C."""
    n = 2 * 3600
    q = 2.6
    i_tr, v_tr = _cell(_discharge(n, 5, 0.5, q), nmc_like_ocv, q, third_rc=True, seed=5)
    i_va, v_va = _cell(_discharge(n, 6, 0.15, q), nmc_like_ocv, q, third_rc=True, seed=6)
    out = {}
    for w in (0.0, 0.1):
        soc = reference_soc(i_tr, 1.0, q)
        run = run_identification(i_tr, v_tr, soc, nmc_like_ocv, q, config=IdentifierConfig(c0_prior_weight=w))
        late = slice(n // 2, None)
        out[w] = float(np.median(np.abs(run.params["c0_v"][late])))
        assert np.all(run.params["r2_ohm"] > 0)
    assert out[0.1] < 0.5 * out[0.0], out
    assert out[0.1] < 0.01
    # and the validation at another mean current is simulated better with the prior
    rmse = {}
    for w in (0.0, 0.1):
        m = compare_methods((i_tr, v_tr), (i_va, v_va), nmc_like_ocv, q, methods=("lif",), c0_prior_weight=w)
        rmse[w] = m.metrics["validate"]["lif"]["sim_rmse_mv"]
    assert rmse[0.1] < rmse[0.0], rmse


def test_c0_prior_weight_must_be_non_negative():
    with pytest.raises(ValueError, match="c0_prior_weight"):
        IdentifierConfig(c0_prior_weight=-1.0)
    with pytest.raises(ValueError, match="c0_prior_weight"):
        LifEstimator(1, 1.0, 3.0, IdentifierConfig(c0_prior_weight=float("nan")))


def test_reference_capacity_trusts_only_a_long_relaxed_rest(nmc_like_ocv):
    n = 3 * 3600
    i, v = _cell(_discharge(n, 7, 0.85 * 2.6 * 3600 / n / 2.6, 2.6), nmc_like_ocv, 2.6, rest_s=900, seed=7)
    q, source = reference_capacity(i, v, 1.0, nmc_like_ocv, 2.9)
    assert source == "end-of-test rest (OCV)"
    assert abs(q / 2.6 - 1) < 0.02
    # a 300 s rest is too short to trust here: the stated capacity is all this function has
    i3, v3 = i[: n + 300], v[: n + 300]
    assert reference_capacity(i3, v3, 1.0, nmc_like_ocv, 2.9)[1].startswith("stated")


def test_validation_resistances_follow_the_cell_temperature(nmc_like_ocv):
    """A warmer validation cell (self-heating on an aggressive cycle) has lower resistances.

    Trained at 25 degC, validated on the same cell at 33 degC whose R0, R1, R2 are the
    Arrhenius factor (B = 2500 K, 0.80) lower: the correction brings the validation
    error down to what identification leaves; without it the 25 degC resistances
    over-predict the polarisation.
    """
    from bms_estimator.core.arrhenius import arrhenius_factor

    n = 2 * 3600
    i_tr = _discharge(n, 5, 0.4)
    i_va = _discharge(n, 6, 0.4)
    f = float(arrhenius_factor(33.0, 25.0, 2500.0))
    rng = np.random.default_rng(7)
    v = []
    for i, scale in ((i_tr, 1.0), (i_va, f)):
        p = EcmParams.from_rc(0.02 * scale, [0.01 * scale, 0.015 * scale], [10.0, 200.0])
        sim = simulate_ecm(i, 1.0, p, nmc_like_ocv.ocv, soc0=1.0, capacity_ah=2.6, output="mean")
        v.append(sim.voltage_v + 3e-4 * rng.standard_normal(n))
    temps = (np.full(n, 25.0), np.full(n, 33.0))
    kw = dict(methods=("lif-iv",), soc_window=(0.3, 0.9))
    plain = compare_methods((i_tr, v[0]), (i_va, v[1]), nmc_like_ocv, 2.6, **kw)
    warm = compare_methods((i_tr, v[0]), (i_va, v[1]), nmc_like_ocv, 2.6, temperatures_c=temps, **kw)
    off = compare_methods((i_tr, v[0]), (i_va, v[1]), nmc_like_ocv, 2.6, temperatures_c=temps, activation_k=0.0,
                          **kw)
    e_plain = plain.metrics["validate"]["lif-iv"]["sim_rmse_mv"]
    e_warm = warm.metrics["validate"]["lif-iv"]["sim_rmse_mv"]
    e_train = warm.metrics["train"]["lif-iv"]["sim_rmse_mv"]
    assert off.metrics["validate"]["lif-iv"]["sim_rmse_mv"] == e_plain  # activation 0 = no correction
    assert e_warm < 0.5 * e_plain, (e_warm, e_plain)
    assert e_warm < 2.0 * e_train + 0.5, (e_warm, e_train)
    # the table holds where the parameters were identified
    assert np.allclose(warm.validate.params["lif-iv"]["temperature_c"], 25.0)


def test_validation_temperature_of_the_wrong_length_is_named(nmc_like_ocv):
    i, v = _cell(_discharge(1200, 1, 0.5), nmc_like_ocv, 2.6)
    with pytest.raises(ValueError, match="validation temperature has 3 samples"):
        compare_methods((i, v), (i, v), nmc_like_ocv, 2.6, methods=("lif",), temperatures_c=(None, np.ones(3)))
