"""Parameter recovery on the issue's synthetic 2-RC cell, the guard, vectorisation and state."""

import numpy as np
import pytest

from bms_estimator.core.identifier import ArxEstimator, IdentifierConfig, LifEstimator
from bms_estimator.core.lif import lif_regressors, lif_scale
from bms_estimator.core.lif_iv import LifIvEstimator
from bms_estimator.core.params import ct_physical_from_theta
from tests.conftest import TRUE, synthetic_overpotential

KEYS = ("r0_ohm", "r1_ohm", "tau1_s", "r2_ohm", "tau2_s", "c0_v")


def _rel_errors(p) -> dict:
    d = p if isinstance(p, dict) else {k: getattr(p, k) for k in KEYS}
    return {k: abs(float(np.ravel(d[k])[-1]) / TRUE[k] - 1) for k in KEYS}


@pytest.mark.parametrize("noise, tol", [((0.0, 0.0), 0.03), ((1e-3, 1e-2), 0.05)])
@pytest.mark.parametrize("window", [10, 20, 40])
def test_batch_lif_recovers_every_parameter(noise, tol, window):
    i, v = synthetic_overpotential(7200, seed=1, noise_v=noise[0], noise_a=noise[1])
    y, phi = lif_regressors(v, i, window, 1.0, 3.0)
    th = np.linalg.lstsq(phi[2 * window:], y[2 * window:], rcond=None)[0]
    p = ct_physical_from_theta(th / lif_scale(window, 1.0, 3.0))
    errs = _rel_errors(p)
    assert max(errs.values()) < tol, errs


@pytest.mark.parametrize("noise, tol", [((0.0, 0.0), 0.03), ((1e-3, 1e-2), 0.05)])
def test_online_lif_reaches_the_same_within_two_hours(noise, tol):
    i, v = synthetic_overpotential(7200, seed=2, noise_v=noise[0], noise_a=noise[1])
    est = LifEstimator(1, 1.0, 3.0)
    for k in range(len(i)):
        est.update(i[k : k + 1], v[k : k + 1])
    errs = _rel_errors(est.params)
    assert max(errs.values()) < tol, errs
    assert est.identified[0]


def test_arx_baseline_recovers_noise_free_parameters():
    """The ARX model is ZOH-exact for point samples, so recovery is checked on those."""
    from bms_estimator.core.ecm import EcmParams, simulate_ecm
    from tests.conftest import pulse_current

    i = pulse_current(7200, seed=4)
    p = EcmParams.from_rc(0.02, [0.01, 0.015], [10.0, 200.0], 0.005)
    v = simulate_ecm(i, 1.0, p, output="sample").voltage_v
    est = ArxEstimator(1, 1.0, 3.0)
    for k in range(len(i)):
        est.update(i[k : k + 1], v[k : k + 1])
    errs = _rel_errors(est.params)
    assert max(errs.values()) < 0.03, errs


def test_guard_keeps_parameters_physical_and_counts_rejections():
    """A tight time-constant bound forces rejections; what leaves the estimator stays admissible."""
    i, v = synthetic_overpotential(3000, seed=5, noise_v=2e-3)
    # true tau2 = 200 s is "too slow": no block start is admissible, so the cell starts from the prior
    est = LifEstimator(1, 1.0, 3.0, IdentifierConfig(tau_max_s=120.0, init_max_samples=600))
    for k in range(len(i)):
        est.update(i[k : k + 1], v[k : k + 1])
        p = est.params
        assert p.r0_ohm[0] > 0 and p.r1_ohm[0] > 0 and p.r2_ohm[0] > 0
        assert p.c1_f[0] > 0 and p.c2_f[0] > 0 and p.tau2_s[0] <= 120.0
    assert est.rejections[0] > 0


def test_vectorised_cells_match_single_cell_runs():
    data = [synthetic_overpotential(1500, seed=s, noise_v=5e-4) for s in (10, 11, 12)]
    i = np.stack([d[0] for d in data], axis=1)
    v = np.stack([d[1] * (1 + 0.1 * j) for j, d in enumerate(data)], axis=1)
    pack = LifEstimator(3, 1.0, 3.0)
    singles = [LifEstimator(1, 1.0, 3.0) for _ in range(3)]
    for k in range(len(i)):
        pack.update(i[k], v[k])
        for j, s in enumerate(singles):
            s.update(i[k, j : j + 1], v[k, j : j + 1])
    for j, s in enumerate(singles):
        np.testing.assert_allclose(pack.params.r0_ohm[j], s.params.r0_ohm[0], rtol=1e-9)
        np.testing.assert_allclose(pack.params.tau2_s[j], s.params.tau2_s[0], rtol=1e-7)


@pytest.mark.parametrize("cls", [LifEstimator, LifIvEstimator, ArxEstimator])
def test_state_round_trip_continues_identically(cls):
    i, v = synthetic_overpotential(1600, seed=7, noise_v=5e-4)
    a = cls(2, 1.0, 3.0)
    for k in range(900):
        a.update(np.full(2, i[k]), np.full(2, v[k]))
    b = cls(2, 1.0, 3.0)
    b.load_state_dict(a.state_dict())
    for k in range(900, 1600):
        a.update(np.full(2, i[k]), np.full(2, v[k]))
        b.update(np.full(2, i[k]), np.full(2, v[k]))
    np.testing.assert_array_equal(a.params.r0_ohm, b.params.r0_ohm)
    np.testing.assert_array_equal(a.rls.P, b.rls.P)


def test_invalid_samples_do_not_teach_and_flush_after_a_window():
    i, v = synthetic_overpotential(2400, seed=8)
    est = LifEstimator(2, 1.0, 3.0)
    for k in range(len(i)):
        valid = np.array([True, not (1000 <= k < 1010)])
        vv = np.array([v[k], v[k] if valid[1] else 99.0])  # garbage while invalid
        est.update(np.full(2, i[k]), vv, valid)
    np.testing.assert_allclose(est.params.r0_ohm[1], est.params.r0_ohm[0], rtol=0.01)


def test_shift_bias_moves_c0_and_history_together():
    """After shift_bias(dv) the model sees v_o - dv: c0 drops by dv and the next prediction is unchanged."""
    i, v = synthetic_overpotential(2000, seed=9)
    est = LifEstimator(1, 1.0, 3.0)
    for k in range(1500):
        est.update(i[k : k + 1], v[k : k + 1])
    c0 = est.params.c0_v[0]
    est.shift_bias(np.array([0.004]))
    assert np.isclose(est.params.c0_v[0], c0 - 0.004, atol=1e-9)
    for k in range(1500, 2000):
        est.update(i[k : k + 1], v[k : k + 1] - 0.004)
    assert abs(est.params.c0_v[0] - (TRUE["c0_v"] - 0.004)) < 2e-4
    assert abs(est.params.r0_ohm[0] / TRUE["r0_ohm"] - 1) < 0.02


def test_turn_off_adaptation_freezes_theta_and_p_while_the_error_is_small():
    """With turn-on/turn-off, a well-explained stretch does not move theta or wind up P."""
    from bms_estimator.core.rls import RlsConfig, WeightedRls

    rng = np.random.default_rng(0)
    true = np.array([0.5, -1.0, 2.0])
    rls = WeightedRls(2, 3, RlsConfig(forgetting=0.99, error_on=0.05, error_off=0.02, error_window=10, init_samples=50))
    for _ in range(300):  # learn with a rich regressor
        phi = rng.normal(size=(2, 3))
        rls.update(phi, phi @ true + 0.001 * rng.normal(size=2))
    theta, P = rls.theta.copy(), rls.P.copy()
    assert not rls.adapting.any()  # the error is far below error_off
    for _ in range(500):  # a weakly exciting, well-explained stretch: P would grow as 1/0.99^k
        phi = np.tile([1.0, 0.0, 0.0], (2, 1))
        rls.update(phi, phi @ true)
    np.testing.assert_array_equal(rls.theta, theta)
    np.testing.assert_array_equal(rls.P, P)
    phi = rng.normal(size=(2, 3))
    for _ in range(20):  # a changed system: the error exceeds error_on and learning resumes
        rls.update(phi, phi @ (true + 1.0))
    assert rls.adapting.all() and not np.allclose(rls.theta, theta)


def test_block_start_is_the_least_squares_solution_of_the_block():
    """theta0 solves the block exactly: its last sample is not used a second time with a stale error."""
    from bms_estimator.core.rls import RlsConfig, WeightedRls

    rng = np.random.default_rng(3)
    theta_true = np.array([1.5, -0.7, 0.02, 3.0])
    rls = WeightedRls(1, 4, RlsConfig(forgetting=1.0, init_samples=40))
    for _ in range(40):
        phi = rng.standard_normal((1, 4))
        rls.update(phi, phi @ theta_true)
    assert rls.initialised[0]
    np.testing.assert_allclose(rls.theta[0], theta_true, rtol=1e-6)


def test_ill_conditioned_block_is_solved_without_ridge_bias():
    """ARX columns differ by orders of magnitude (v_o, C-rate, 1): the ridge is per column energy."""
    from bms_estimator.core.ecm import EcmParams, simulate_ecm
    from tests.conftest import pulse_current

    i = pulse_current(900, seed=4)
    p = EcmParams.from_rc(0.02, [0.01, 0.015], [10.0, 200.0], 0.005)
    v = simulate_ecm(i, 1.0, p, output="sample").voltage_v
    est = ArxEstimator(1, 1.0, 3.0, IdentifierConfig(method="arx", init_samples=600))
    for k in range(len(i)):
        est.update(i[k : k + 1], v[k : k + 1])
    assert max(_rel_errors(est.params).values()) < 1e-4, _rel_errors(est.params)


def test_a_block_too_short_for_the_slow_pole_grows_until_it_is_physical():
    """With noise, a 60 s block cannot place the 200 s pole: it grows rather than falling back to the prior."""
    i, v = synthetic_overpotential(1500, seed=4, noise_v=1e-3, noise_a=1e-2)
    est = LifEstimator(1, 1.0, 3.0, IdentifierConfig(init_samples=60))
    for k in range(len(i)):
        est.update(i[k : k + 1], v[k : k + 1])
        if est.rls.initialised[0]:
            break
    assert est.rls.block_samples[0] > 60
    assert est.identified[0] and est.params.admissible[0]  # the block's own theta, not the prior
    # with no room to grow, the same cell starts from the prior (identified only once it learns one)
    capped = LifEstimator(1, 1.0, 3.0, IdentifierConfig(init_samples=60, init_max_samples=60))
    for k in range(len(i)):
        capped.update(i[k : k + 1], v[k : k + 1])
        if capped.rls.initialised[0]:
            break
    assert capped.rls.block_samples[0] == 60 and not capped.identified[0]


def test_a_cell_stuck_against_the_guard_restarts_its_identification():
    """An OCV error that grows with the charge (a 10 % capacity error) pushes the slow pole
    against tau_max sample after sample; the stuck cell restarts from a fresh block and
    learns again instead of staying frozen (the SOC compensation needs accepted estimates)."""
    from bms_estimator.core.ecm import EcmParams, simulate_ecm
    from tests.conftest import pulse_current

    n = 3 * 3600
    i = pulse_current(n, 2, amp_a=4.0)
    i = i - (i.mean() + 0.75)
    v = simulate_ecm(i, 1.0, EcmParams.from_rc(0.02, [0.01, 0.015], [10.0, 200.0]), output="mean").voltage_v
    v_o = v + np.cumsum(i) / 3600 * (1 / 2.7 - 1 / 3.0)  # OCV slope 1 V per unit SOC
    v_o += 5e-4 * np.random.default_rng(2).standard_normal(n)
    runs = {}
    for after in (0, 300):
        est = LifEstimator(1, 1.0, 3.0, IdentifierConfig(restart_after_rejections=after))
        longest = accepted = 0
        for k in range(n):
            est.update(i[k : k + 1], v_o[k : k + 1])
            longest = max(longest, int(est._rejected_run[0]))
            accepted += bool(est.accepted[0])
            assert est.params.admissible[0]
        runs[after] = (longest, accepted, int(est.restarts[0]))
    assert runs[0][0] > 300 and runs[0][2] == 0  # without the restart: stuck for > 5 min
    assert runs[300][0] < 300 and runs[300][2] >= 1
    assert runs[300][1] > 1.2 * runs[0][1]  # it learns on more samples
    with pytest.raises(ValueError, match="restart_after_rejections"):
        IdentifierConfig(restart_after_rejections=-1)


@pytest.mark.parametrize("cls, method", [(LifEstimator, "lif"), (LifIvEstimator, "lif-iv"), (ArxEstimator, "arx")])
@pytest.mark.parametrize("pack_cells", [(2, 3), (3, 3)], ids=["unequal", "equal"])
def test_groups_give_each_pack_the_results_it_has_alone(cls, method, pack_cells):
    """Two packs side by side in one identifier (set_groups) learn exactly as each does alone, although
    at many steps one pack's cells learn and the other's do not (invalid samples), and only one pack's
    OCV bias shifts: the error window, the trace limit, the parameters and the LIF product stay per pack.
    (Equal packs are the batch's stack: the LIF history is then kept group-major.)"""
    n = 1500
    packs = []
    for seed, cells in enumerate(pack_cells):
        i, v = synthetic_overpotential(n, seed=seed, noise_v=2e-4, noise_a=0.01)
        ok = np.ones((n, cells), dtype=bool)
        ok[200 + 300 * seed: 260 + 300 * seed] = False  # the pack's samples invalid for a minute
        ok[700:705, 0] = False
        packs.append((i, v[:, None] + 1e-3 * np.arange(cells), ok))
    cfg = IdentifierConfig(method=method, init_samples=60)
    sizes = [p[1].shape[1] for p in packs]
    both = cls(sum(sizes), 1.0, 3.0, cfg)
    both.set_groups(sizes)
    alone = [cls(s, 1.0, 3.0, cfg) for s in sizes]
    for k in range(n):
        for est, (i, v, ok) in zip(alone, packs):
            est.update(i[k], v[k], ok[k])
            if k % 97 == 0 and est is alone[0]:
                est.shift_bias(np.full(sizes[0], 1e-4))
        both.update(np.concatenate([np.full(s, p[0][k]) for s, p in zip(sizes, packs)]),
                    np.concatenate([p[1][k] for p in packs]), np.concatenate([p[2][k] for p in packs]))
        if k % 97 == 0:
            both.shift_bias(np.concatenate([np.full(sizes[0], 1e-4), np.zeros(sizes[1])]))
    cols = [slice(0, sizes[0]), slice(sizes[0], sum(sizes))]
    for est, c in zip(alone, cols):
        for key in ("r0_ohm", "r1_ohm", "c1_f", "r2_ohm", "c2_f", "c0_v"):
            assert np.array_equal(getattr(est.params, key), getattr(both.params, key)[c], equal_nan=True), key
        assert np.array_equal(est.rls.theta, both.rls.theta[c]) and np.array_equal(est.rls.P, both.rls.P[c])
        assert np.array_equal(est.rls.state_dict()["err2"], both.rls.state_dict()["err2"][c])
        if getattr(est, "history", None) is not None:  # the filter's history (v_o shifted by the bias)
            assert np.array_equal(est.history.buffer, both.history.buffer[:, c])
    assert both.identified.all()


@pytest.mark.parametrize("cls, method", [(LifEstimator, "lif"), (LifIvEstimator, "lif-iv")])
def test_shift_bias_params_are_the_full_mapping_of_the_shifted_theta(cls, method):
    """shift_bias redoes c0 alone (the rest of the parameters are those of theta_good's other columns):
    after every shift, for every cell, the parameters and the admissible flag are bit for bit what the
    full mapping of the shifted theta_good gives, through block starts, rejections (a tight tau bound),
    invalid samples and shifts of some cells only, some of them large enough to make c0 non-admissible."""
    n = 1500
    i, v = synthetic_overpotential(n, seed=3, noise_v=3e-4, noise_a=0.02)
    cells = 4
    volts = v[:, None] + 1e-3 * np.arange(cells)
    ok = np.ones((n, cells), dtype=bool)
    ok[300:340, 1] = False
    cfg = IdentifierConfig(method=method, init_samples=60, tau_max_s=150.0)
    est = cls(cells, 1.0, 3.0, cfg)
    rng = np.random.default_rng(0)
    shifted = 0
    for k in range(n):
        est.update(np.full(cells, i[k]), volts[k], ok[k])
        some = rng.random(cells) < 0.5
        dv = np.where(some, rng.normal(0.0, 2e-3 if k % 200 else 2.0, cells), 0.0)
        est.shift_bias(dv, some)
        shifted += bool(some.any())
        full = est._physical(est.theta_good)
        for key in ("r0_ohm", "r1_ohm", "c1_f", "r2_ohm", "c2_f", "c0_v", "admissible"):
            assert np.array_equal(getattr(est.params, key), getattr(full, key), equal_nan=True), (k, key)
    assert shifted > n // 2 and est.rejections.sum() > 0 and est.identified.any()


def test_one_rls_step_is_the_weighted_recursion_of_the_docstring():
    """k = P phi / (lambda + phi' P phi), theta += k e, P = (P - k phi' P) / lambda, for a learning cell;
    a masked cell (w = 0) keeps theta and P. lambda = 0.9 so that a 1 in place of lambda shows."""
    from bms_estimator.core.rls import RlsConfig, WeightedRls

    rng = np.random.default_rng(5)
    rls = WeightedRls(2, 3, RlsConfig(forgetting=0.9, init_samples=20, trace_max=1e9))
    true = np.array([0.5, -1.0, 2.0])
    for _ in range(20):
        phi = rng.normal(size=(2, 3))
        rls.update(phi, phi @ true + 0.05 * rng.normal(size=2))
    assert rls.initialised.all()
    theta, P = rls.theta.copy(), rls.P.copy()
    phi, y = rng.normal(size=(2, 3)), rng.normal(size=2)
    e = rls.update(phi, y, mask=np.array([True, False]))
    k = P[0] @ phi[0] / (0.9 + phi[0] @ P[0] @ phi[0])
    np.testing.assert_allclose(e, y - np.einsum("np,np->n", phi, theta), rtol=1e-12)
    np.testing.assert_allclose(rls.theta[0], theta[0] + k * e[0], rtol=1e-10)
    np.testing.assert_allclose(rls.P[0], (P[0] - np.outer(k, phi[0] @ P[0])) / 0.9, rtol=1e-10)
    np.testing.assert_array_equal(rls.theta[1], theta[1])
    np.testing.assert_array_equal(rls.P[1], P[1])


def test_rls_state_round_trip_keeps_the_error_window_count():
    """The error RMS divides by the samples the window holds so far (min(count, window)): a state
    saved before the window is full must carry that count, or the restored RMS reads sqrt(count)
    times too high and switches adaptation on where the uninterrupted run stays off."""
    from bms_estimator.core.rls import RlsConfig, WeightedRls

    cfg = RlsConfig(forgetting=0.99, error_on=0.05, error_off=0.02, error_window=30, init_samples=20)
    rng = np.random.default_rng(2)
    true = np.array([0.5, -1.0, 2.0])
    data = [(phi, phi @ true + 0.015 * rng.normal(size=1)) for phi in rng.normal(size=(60, 1, 3))]
    whole = WeightedRls(1, 3, cfg)
    for phi, y in data[:35]:  # the block, then 15 samples in the window
        whole.update(phi, y)
    assert not whole.adapting[0]  # rms ~0.015 < error_off
    resumed = WeightedRls(1, 3, cfg)
    resumed.load_state_dict(whole.state_dict())
    for phi, y in data[35:]:
        whole.update(phi, y)
        resumed.update(phi, y)
        assert resumed.adapting[0] == whole.adapting[0]
    np.testing.assert_array_equal(resumed.theta, whole.theta)
    np.testing.assert_array_equal(resumed.P, whole.P)


def test_rls_error_rms_is_over_the_samples_the_window_holds_so_far():
    """Before the window is full the RMS is over the samples it holds (min(count, window)): one
    a-priori error of 30 mV right after the block reads 30 mV, inside the hysteresis band
    (20..50 mV), so adaptation stays on and theta moves; over the whole window it would read 5 mV."""
    from bms_estimator.core.rls import RlsConfig, WeightedRls

    rng = np.random.default_rng(4)
    true = np.array([0.5, -1.0, 2.0])
    rls = WeightedRls(1, 3, RlsConfig(forgetting=0.99, error_on=0.05, error_off=0.02, error_window=30,
                                      init_samples=20))
    for _ in range(20):
        phi = rng.normal(size=(1, 3))
        rls.update(phi, phi @ true)
    theta = rls.theta.copy()
    phi = rng.normal(size=(1, 3))
    e = rls.update(phi, phi @ true + 0.03)
    np.testing.assert_allclose(e, 0.03, rtol=1e-6)
    assert rls.adapting[0] and not np.allclose(rls.theta, theta, rtol=0, atol=1e-6)


def test_the_prior_takes_the_start_temperature_on_cells_not_yet_identified():
    """R(T) = R(25 degC) exp(B (1/T - 1/T_ref)) on every resistance of the prior (x2.15 at 0 degC with
    B = 2500 K), the time constants kept; a cell already identified keeps its own model."""
    cfg = IdentifierConfig(prior_activation_k=2500.0)
    est = LifEstimator(3, 1.0, 3.0, cfg)
    warm = est.params
    est.identified[2] = True  # (as a restored state says)
    est.take_prior_at(np.array([0.0, 25.0, 0.0]), 25.0, np.array([True, True, True]))
    f = np.exp(2500.0 * (1 / 273.15 - 1 / 298.15))
    for key in ("r0_ohm", "r1_ohm", "r2_ohm"):
        np.testing.assert_allclose(getattr(est.params, key) / getattr(warm, key), [f, 1.0, 1.0], rtol=1e-9)
    for key in ("tau1_s", "tau2_s"):
        np.testing.assert_allclose(getattr(est.params, key), getattr(warm, key), rtol=1e-9)
    np.testing.assert_allclose(est.params.r0_ohm[0], cfg.prior_r0_ohm_ah / 3.0 * f, rtol=1e-9)


def test_the_prior_time_constants_are_moved_inside_the_guards_bounds():
    """tau2 <= 0.9 tau_max, tau1 >= max(1.1 tau_min, 1.5 Ts) and tau1 <= tau2 / 2: the prior passes the guard."""
    cfg = IdentifierConfig(prior_tau1_s=0.5, prior_tau2_s=1000.0, tau_min_s=1.0, tau_max_s=500.0)
    p = LifEstimator(1, 1.0, 3.0, cfg).params
    np.testing.assert_allclose([p.tau1_s[0], p.tau2_s[0]], [1.5, 450.0], rtol=1e-9)  # 1.5 Ts > 1.1 tau_min
    p = LifEstimator(1, 1.0, 3.0, cfg.with_(prior_tau1_s=400.0)).params
    np.testing.assert_allclose(p.tau1_s[0], 225.0, rtol=1e-9)
    assert p.admissible[0]


def test_the_guard_counts_rejections_in_a_row_per_cell():
    """restart_after_rejections counts a cell's rejections *in a row*: an accepted sample ends its run,
    also in a sample where another cell is rejected; the rejected cell's run grows by one."""
    est = LifEstimator(2, 1.0, 3.0, IdentifierConfig(restart_after_rejections=10))
    est._rejected_run[:] = [5, 7]
    est._guard(np.array([True, False]), np.array([False, True]))
    np.testing.assert_array_equal(est._rejected_run, [6, 0])
    np.testing.assert_array_equal(est.rejections, [1, 0])


def test_predict_static_is_the_steady_state_overpotential():
    est = LifEstimator(1, 1.0, 3.0)
    p = est.params
    np.testing.assert_allclose(est.predict_static(2.0), (p.r0_ohm + p.r1_ohm + p.r2_ohm) * 2.0 + p.c0_v, rtol=1e-12)


def test_a_rest_keeps_the_named_cells_from_learning_for_a_full_window():
    """After rest(gap) a cell's regressor window is restarted: it learns again only once 2L + 1 samples
    after the gap fill it; the cells not named go on learning; what was learnt stays."""
    i, v = synthetic_overpotential(700, seed=7, noise_v=5e-4)
    est = LifEstimator(2, 1.0, 3.0)
    for k in range(600):
        est.update(np.full(2, i[k]), np.full(2, v[k]))
    assert est.rls.initialised.all()
    est.rest(600.0, np.array([True, False]))
    theta = est.rls.theta.copy()
    n = est.history.length  # 2L + 1
    for k in range(600, 600 + n - 1):  # the window holds a sample from before the gap
        est.update(np.full(2, i[k]), np.full(2, v[k]))
        assert np.array_equal(est.rls.theta[0], theta[0]) and not est.accepted[0]
    assert not np.array_equal(est.rls.theta[1], theta[1])
    est.update(np.full(2, i[600 + n - 1]), np.full(2, v[600 + n - 1]))  # the (2L + 1)-th: all after it
    assert not np.array_equal(est.rls.theta[0], theta[0])


def test_the_guards_run_of_rejections_survives_a_state_round_trip():
    """A cell on its way to restart_after_rejections resumes its run where it was, not from 0."""
    est = LifEstimator(2, 1.0, 3.0)
    est._rejected_run[:] = [4, 0]
    other = LifEstimator(2, 1.0, 3.0)
    other.load_state_dict(est.state_dict())
    np.testing.assert_array_equal(other._rejected_run, [4, 0])


def test_the_c0_prior_is_one_pseudo_measurement_of_its_stated_weight():
    """The prior ``c0 = 0`` of weight w is a row h = sqrt(w) e_c0 / g of unit noise (h' theta = sqrt(w) c0):
    after the data step, one RLS step with it takes c0 (linearised at theta, c0 = theta_c0 / g) to
    c0 / (1 + w sigma2), sigma2 = P_c0c0 / g^2 its variance. So c0 moves by the share w sigma2 of where it
    lands: the prior's pull is its weight times c0's variance, not w^2 (a row of w in place of sqrt(w))."""
    import copy

    i, v = synthetic_overpotential(1600, seed=9)
    w = 0.1
    est = LifEstimator(1, 1.0, 3.0, IdentifierConfig(c0_prior_weight=w))
    for k in range(1500):
        est.update(i[k : k + 1], v[k : k + 1])
    assert est.rls.initialised[0] and abs(est.params.c0_v[0]) > 1e-3
    data_only = copy.deepcopy(est)
    data_only.config = est.config.with_(c0_prior_weight=0.0)
    est.update(i[1500:1501], v[1500:1501])
    data_only.update(i[1500:1501], v[1500:1501])
    theta, P = data_only.rls.theta[0], data_only.rls.P[0]  # after the data step: what the prior row meets
    g = -theta[1]  # LIF: c0 = -theta_6 / theta_2 (scaled)
    c0_before = theta[5] / g
    c0_after = est.rls.theta[0, 5] / g
    sigma2 = P[5, 5] / g**2
    assert w * sigma2 > 1e-9  # the pull is large enough to be told from w^2 sigma2 below
    np.testing.assert_allclose((c0_before - c0_after) / c0_after, w * sigma2, rtol=1e-6)
    # the whole step: theta -= P h (h' theta) / (1 + h' P h)
    h = np.zeros(theta.size)
    h[5] = np.sqrt(w) / g
    np.testing.assert_allclose(est.rls.theta[0], theta - P @ h * (h @ theta) / (1.0 + h @ P @ h), rtol=1e-9, atol=1e-15)
