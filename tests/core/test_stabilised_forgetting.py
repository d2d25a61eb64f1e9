"""Stabilised (regularised) forgetting in the RLS / RIV machinery (core/rls.py, ``prior_share``;
``IdentifierConfig.stabilised_forgetting``).

The collinear pair: a 2-RC cell (R0 20, R1 10, R2 15 mOhm, tau 10 / 200 s, c0 = 0) of 3 Ah, 1.5 C
pulses for 1500 s then a steady 2 A discharge for 2500 s, with the drive's ripple (0.3 A RMS) and
2 mV voltage noise, 8 seeds as 8 cells; the identifier's prior is the true cell with c0 = 0. Under the
steady current c0 and R2 i move together (v_o ~ (R0 + R1 + R2) i + c0), and plain forgetting lets
them drift. At the end (measured):

    method      share   R2 (mOhm)                   c0 (mV)         R0 (mOhm)
    lif         0       16.2..18.9                  +4.2..+11.3     20.10..20.42
    lif         0.15    14.7..15.0                  -0.1..+0.1      19.88..20.10
    lif-iv-bv   0       14.3..17.3, one seed 40.8   -0.7..+2.3, that seed +65.4
    lif-iv-bv   0.15    13.3..15.0                  -0.1..+0.1      19.88..20.04

Least squares drifts on every seed (its bias has a direction); the IV is unbiased but its
estimate random-walks along the pair, far on one seed in eight.
"""

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from bms_estimator.core.identifier import IdentifierConfig
from bms_estimator.core.identifier_methods import make_identifier
from bms_estimator.core.rls import RlsConfig, WeightedRls
from tests.conftest import assert_physical_and_finite, hostile_strategies, hostile_stream, pulse_current, state_round_trip

Q_AH = 3.0
CELL = dict(r0_ohm=0.020, r1_ohm=0.010, tau1_s=10.0, r2_ohm=0.015, tau2_s=200.0)
# the identifier's prior is the cell itself (ohm * Ah), c0 = 0
PRIOR = dict(prior_r0_ohm_ah=CELL["r0_ohm"] * Q_AH, prior_r1_ohm_ah=CELL["r1_ohm"] * Q_AH,
             prior_tau1_s=CELL["tau1_s"], prior_r2_ohm_ah=CELL["r2_ohm"] * Q_AH, prior_tau2_s=CELL["tau2_s"])


def _cell_v(i: np.ndarray) -> np.ndarray:
    """v_o of the 2-RC cell, exact ZOH period means, branch by branch (no project code)."""
    v = CELL["r0_ohm"] * i
    for r, tau in ((CELL["r1_ohm"], CELL["tau1_s"]), (CELL["r2_ohm"], CELL["tau2_s"])):
        p = np.exp(-1.0 / tau)
        g = tau * (1.0 - p)
        x = 0.0
        for n, w in enumerate(r * i):
            v[n] += x * g + w * (1.0 - g)
            x = p * x + (1.0 - p) * w
    return v


def _steady_drive(cells: int = 8, n: int = 4000):
    cur, v = [], []
    for s in range(cells):
        rng = np.random.default_rng(s)
        i = np.where((np.arange(n) // 300) % 2 == 0, -1.5 * Q_AH, 0.0)
        i[1500:] = -2.0  # a steady discharge
        i = i + rng.normal(0.0, 0.3, n)  # the drive's ripple
        cur.append(i)
        v.append(_cell_v(i) + rng.normal(0.0, 0.002, n))
    return np.array(cur).T, np.array(v).T


@pytest.fixture(scope="module")
def steady_ends():
    cur, v = _steady_drive()
    out = {}
    for method in ("lif", "lif-iv-bv"):
        for share in (0.0, 0.15):
            est = make_identifier(cur.shape[1], 1.0, Q_AH,
                                  IdentifierConfig(method=method, stabilised_forgetting=share, **PRIOR))
            for k in range(len(cur)):
                est.update(cur[k], v[k])
            out[method, share] = est.params
    return out


@pytest.mark.parametrize("method", ["lif", "lif-iv-bv"])
def test_it_holds_c0_and_the_slow_branch_where_plain_forgetting_lets_them_drift(steady_ends, method):
    plain, held = steady_ends[method, 0.0], steady_ends[method, 0.15]
    # plain forgetting: c0 and R2 have drifted together, away from the (true) prior, on some cell
    worst = np.argmax(np.abs(plain.c0_v))
    assert plain.c0_v[worst] > 0.008 and plain.r2_ohm[worst] > CELL["r2_ohm"] * 1.15, (plain.c0_v, plain.r2_ohm)
    # stabilised: every cell's c0 within 2 mV and R2 within 15 % of the truth
    assert np.all(np.abs(held.c0_v) < 0.002), held.c0_v
    assert np.all(np.abs(held.r2_ohm / CELL["r2_ohm"] - 1) < 0.15), held.r2_ohm
    # and the well-excited R0 as well as without it
    assert np.all(np.abs(held.r0_ohm / CELL["r0_ohm"] - 1) < 0.03), held.r0_ohm


def _started_rls(share: float, lam: float = 0.99, every: int = 10, seed: int = 3) -> WeightedRls:
    rng = np.random.default_rng(seed)
    rls = WeightedRls(2, 3, RlsConfig(forgetting=lam, init_samples=50, trace_max=1e6, prior_share=share,
                                      prior_every=every))
    rls.theta_ref = np.array([[1.0, -2.0, 0.5], [0.3, 0.0, 4.0]])
    true = np.array([[2.0, -1.0, 0.0], [0.0, 1.0, 3.0]])
    for _ in range(50):
        phi = rng.normal(size=(2, 3)) * np.array([1.0, 10.0, 0.1])
        rls.update(phi, np.einsum("np,np->n", phi, true))
    assert rls.initialised.all()
    return rls


def test_the_prior_step_is_the_information_form_update():
    """P^-1 <- P^-1 + A, P^-1 theta <- P^-1 theta + A theta_ref, A = (1 - lambda^M) Pi^-1."""
    rls = _started_rls(0.15)
    P, theta = rls.P.copy(), rls.theta.copy()
    a = (1.0 - 0.99**10) * rls.prior_information(np.arange(2))
    assert np.all(a > 0)
    rls._prior_step(np.ones(2, dtype=bool))
    for n in range(2):
        info = np.linalg.inv(P[n]) + np.diag(a[n])
        np.testing.assert_allclose(rls.P[n], np.linalg.inv(info), rtol=1e-9)
        np.testing.assert_allclose(rls.theta[n], np.linalg.solve(info, np.linalg.inv(P[n]) @ theta[n]
                                                                 + a[n] * rls.theta_ref[n]), rtol=1e-9, atol=1e-12)


def test_without_data_the_information_settles_at_the_prior_and_theta_at_its_mean():
    """A regressor that stops (phi = 0): plain forgetting winds P up to the trace limit with theta where it
    was; stabilised forgetting settles P at Pi and theta at theta_ref."""
    plain, held = _started_rls(0.0), _started_rls(0.15)
    theta_plain = plain.theta.copy()
    for _ in range(3000):
        for rls in (plain, held):
            rls.update(np.zeros((2, 3)), np.zeros(2))
    np.testing.assert_allclose(np.einsum("nii->n", plain.P), 1e6, rtol=1e-9)
    np.testing.assert_array_equal(plain.theta, theta_plain)
    np.testing.assert_allclose(held.theta, held.theta_ref, rtol=1e-6, atol=1e-9)
    pi = 1.0 / held.prior_information(np.arange(2))
    np.testing.assert_allclose(np.einsum("nii->ni", held.P), pi, rtol=0.02)


def test_off_is_the_plain_recursion_bit_for_bit():
    """share 0 whatever its period: no step runs (a step with A = 0 would still move P's last bits)."""
    i = pulse_current(1500, seed=4)
    v = _cell_v(i) + np.random.default_rng(4).normal(0.0, 0.002, i.size)
    runs = []
    for cfg in (IdentifierConfig(method="lif-iv-bv"), IdentifierConfig(method="lif-iv-bv", stabilised_every=1)):
        est = make_identifier(2, 1.0, Q_AH, cfg)
        for k in range(len(i)):
            est.update(np.full(2, i[k]), np.full(2, v[k]))
        runs.append(est)
    np.testing.assert_array_equal(runs[0].rls.theta, runs[1].rls.theta)
    np.testing.assert_array_equal(runs[0].rls.P, runs[1].rls.P)
    on = make_identifier(2, 1.0, Q_AH, IdentifierConfig(method="lif-iv-bv", stabilised_forgetting=0.15))
    for k in range(len(i)):
        on.update(np.full(2, i[k]), np.full(2, v[k]))
    assert not np.array_equal(on.rls.theta, runs[0].rls.theta)  # (and on, it does something)


def test_state_round_trip_continues_bit_for_bit_with_it_on():
    i = pulse_current(900, seed=11)
    cfg = IdentifierConfig(method="lif-iv-bv", stabilised_forgetting=0.15, stabilised_every=7)
    a, b = state_round_trip(lambda: make_identifier(2, 1.0, Q_AH, cfg), i, _cell_v(i), 600)
    np.testing.assert_array_equal(a.theta_good, b.theta_good)
    np.testing.assert_array_equal(a.rls.P, b.rls.P)


@settings(max_examples=20, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(**hostile_strategies(), method=st.sampled_from(["lif", "lif-iv-bv"]),
       share=st.sampled_from([0.03, 0.15, 1.0, 10.0]), every=st.integers(1, 60), window=st.integers(1, 40))
def test_no_nan_and_no_inadmissible_parameters_leave_it(seed, amp, noise_v, noise_a, dropout, method, share, every,
                                                        window):
    cells = 3
    cfg = IdentifierConfig(method=method, window=window, init_samples=100, stabilised_forgetting=share,
                           stabilised_every=every, c0_prior_weight=0.1 * (seed % 2))
    est = make_identifier(cells, 1.0, 2.5, cfg)
    for i, v, valid in hostile_stream(seed, amp, noise_v, noise_a, dropout, step_v=0.05 * (seed % 3 == 0)):
        est.update(i, v, valid)
        assert_physical_and_finite(est, cells)


def test_the_config_names_a_bad_strength_or_period():
    from bms_estimator.service.config import ConfigError, soc_config_from_core

    cfg = soc_config_from_core({"identifier": {"stabilised_forgetting": 0.15, "stabilised_every": 10}})
    assert cfg.identifier.rls().prior_share == 0.15 and cfg.identifier.rls().prior_every == 10
    for key, bad in (("stabilised_forgetting", -0.1), ("stabilised_every", 0)):
        with pytest.raises(ConfigError) as exc:
            soc_config_from_core({"identifier": {key: bad}})
        assert [p.split(":")[0].rsplit(".", 1)[-1] for p in exc.value.problems] == [key], exc.value.problems
    with pytest.raises(ValueError, match="prior_share"):
        RlsConfig(prior_share=-1.0)


def test_a_restarted_cell_counts_its_prior_period_afresh():
    """The prior step comes every ``prior_every`` learning samples of a cell: a cell whose start is
    undone (extend_block / restart) begins the count again, as a fresh cell does; 9 learning samples
    after its new block (every = 10) are then the plain recursion's, no prior step among them."""
    rng = np.random.default_rng(8)
    block = [rng.normal(size=(2, 3)) for _ in range(50)]
    after = [rng.normal(size=(2, 3)) for _ in range(9)]
    true = np.array([2.0, -1.0, 0.5])
    restarted, fresh = _started_rls(0.15), _started_rls(0.15)
    for phi in block[:5]:  # 5 learning samples: half a period counted
        restarted.update(phi, phi @ true)
    restarted.restart(np.ones(2, dtype=bool))
    fresh.restart(np.ones(2, dtype=bool))
    fresh._since_prior[:] = 0  # (what a cell that never learned has)
    for rls in (restarted, fresh):
        for phi in block + after:
            rls.update(phi, phi @ true)
    np.testing.assert_array_equal(restarted.theta, fresh.theta)
    np.testing.assert_array_equal(restarted.P, fresh.P)


def test_the_prior_information_is_the_share_of_a_full_memory_of_the_block_energy():
    """Pi^-1 = share / (1 - lambda) diag(e), e_j = sum lambda^(n-k) phi_kj^2 / sum lambda^(n-k) (the
    block's forgetting-weighted mean energy), floored at 1e-3 of the columns' mean: computed here from
    the block's regressors themselves. lambda = 0.9 over 50 samples: the weights' sum (6.95) is far
    from the count."""
    lam, share, n = 0.9, 0.15, 50
    phis = np.random.default_rng(6).normal(size=(n, 2, 3)) * np.array([1.0, 10.0, 0.01])
    rls = WeightedRls(2, 3, RlsConfig(forgetting=lam, init_samples=n, prior_share=share))
    for phi in phis:
        rls.update(phi, phi.sum(axis=1))
    w = lam ** np.arange(n - 1, -1, -1)
    e = np.einsum("k,knp->np", w, phis**2) / w.sum()
    floor = e.mean(axis=1, keepdims=True) * 1e-3
    assert np.all(e[:, 2] < floor[:, 0])  # the third column is floored
    np.testing.assert_allclose(rls.prior_information(np.arange(2)), share / (1 - lam) * np.maximum(e, floor),
                               rtol=1e-10)
