import numpy as np

from bms_estimator.core.lif import LifHistory, lif_kernels, lif_regressors


def test_kernels_are_the_papers_filters():
    k = lif_kernels(3, 2.0)
    f1 = np.array([1, 0, 0, -1.0])
    f2 = 2.0 * np.array([0.5, 1, 1, 0.5])
    np.testing.assert_allclose(k[:, 0], np.convolve(f1, f1))
    np.testing.assert_allclose(k[:, 2], np.convolve(f2, f2))
    # f2 integrates a ramp exactly: f2 applied to t gives the trapezoid of t over the window
    t = np.arange(20.0) * 2.0
    assert np.isclose(np.dot(f2, t[10::-1][:4]), (t[10] ** 2 - t[7] ** 2) / 2)


def test_streaming_equals_batch_and_shift_moves_only_the_constant_column():
    rng = np.random.default_rng(3)
    n, cells, L = 200, 3, 7
    v = rng.normal(size=(n, cells))
    i = rng.normal(size=(n, cells))
    y_b, phi_b = lif_regressors(v, i, L, 1.0, 2.5)
    hist = LifHistory(cells, L, 1.0, 2.5)
    for k in range(n):
        y, phi = hist.push(v[k], i[k])
        np.testing.assert_allclose(y, y_b[k], atol=1e-11)
        np.testing.assert_allclose(phi, phi_b[k], atol=1e-11)
    hist.shift_v_o(np.full(cells, 0.1))
    y2, phi2 = hist.push(v[0], i[0])
    y3, phi3 = lif_regressors(np.vstack([v - 0.1, v[:1]]), np.vstack([i, i[:1]]), L, 1.0, 2.5)
    np.testing.assert_allclose(phi2, phi3[-1], atol=1e-11)


def test_regression_holds_exactly_for_the_true_theta():
    """On bin-averaged data of a 2-RC cell, phi' theta reproduces y to < 0.2 % of its scale."""
    from bms_estimator.core.params import ct_theta_from_physical
    from bms_estimator.core.lif import lif_scale
    from tests.conftest import TRUE, synthetic_overpotential

    i, v = synthetic_overpotential(3000)
    L = 20
    y, phi = lif_regressors(v, i, L, 1.0, 3.0)
    theta_s = ct_theta_from_physical(**TRUE) * lif_scale(L, 1.0, 3.0)
    resid = y[2 * L:] - phi[2 * L:] @ theta_s
    assert np.sqrt(np.mean(resid**2)) < 2e-3 * np.sqrt(np.mean(y[2 * L:] ** 2))


def test_scaled_columns_are_one_for_a_1c_step_and_ramp_over_any_window():
    """scale = [T, T^2, I_ref, T I_ref, T^2 I_ref, T^2]: f2^2 of a constant c is c T^2 and f1 f2 of a
    ramp of slope a is a T^2 (f2 integrates linear signals exactly), so a constant 1C current, a ramp
    reaching 1C (or 1 V) over one window and the constant column all read exactly 1 once the window
    is full, whatever the window and the cell size."""
    for L, dt, i_ref in ((10, 0.5, 3.0), (40, 1.0, 50.0)):
        big_t = L * dt
        t = np.arange(6 * L) * dt
        _, step = lif_regressors(np.full(t.size, 1.0), np.full(t.size, i_ref), L, dt, i_ref)
        _, ramp = lif_regressors(t / big_t, i_ref * t / big_t, L, dt, i_ref)
        np.testing.assert_allclose(step[2 * L:, [1, 4, 5]], 1.0, rtol=1e-12)
        np.testing.assert_allclose(ramp[2 * L:, [0, 3]], 1.0, rtol=1e-9)


def test_history_is_ready_once_it_holds_2l_plus_1_samples():
    """The FIR filters are 2L + 1 long: before that many samples they see the zero initial state."""
    hist = LifHistory(2, 3, 1.0)
    for k in range(7):
        assert not hist.ready
        hist.push(np.ones(2), np.ones(2))
    assert hist.ready
