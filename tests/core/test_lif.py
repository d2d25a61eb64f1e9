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
