import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bms_estimator.core.params import (
    PhysicalParams, ct_c0_from_theta, ct_physical_from_theta, ct_theta_from_physical, dt_physical_from_theta,
    dt_theta_from_physical,
)

pos = st.floats(1e-4, 0.2)


@settings(max_examples=200, deadline=None)
@given(r0=pos, r1=pos, r2=pos, t1=st.floats(1.0, 50.0), ratio=st.floats(1.5, 100.0), c0=st.floats(-0.3, 0.3))
def test_ct_and_dt_mappings_invert(r0, r1, r2, t1, ratio, c0):
    t2 = t1 * ratio
    for to_theta, from_theta, kw in ((ct_theta_from_physical, ct_physical_from_theta, {}),
                                     (dt_theta_from_physical, dt_physical_from_theta, {"dt_s": 1.0})):
        p = from_theta(to_theta(r0, r1, t1, r2, t2, c0, **kw), **kw)
        assert bool(p.admissible)
        got = [p.r0_ohm, p.r1_ohm, p.tau1_s, p.r2_ohm, p.tau2_s, p.c0_v]
        np.testing.assert_allclose(got, [r0, r1, t1, r2, t2, c0], rtol=1e-5, atol=1e-9)


def test_pairs_are_sorted_fast_first_and_non_physical_flagged():
    th = ct_theta_from_physical(0.02, 0.015, 200.0, 0.01, 10.0)  # slow pair given first
    p = ct_physical_from_theta(th)
    assert p.tau1_s < p.tau2_s and np.isclose(p.r1_ohm, 0.01)
    complex_poles = np.array([-0.1, -0.01, 0.02, 0.003, 2e-5, 0.0])  # th1^2 + 4 th2 < 0
    assert not ct_physical_from_theta(complex_poles).admissible
    negative_r0 = th.copy()
    negative_r0[2] = -0.02
    assert not ct_physical_from_theta(negative_r0).admissible
    assert not ct_physical_from_theta(th, tau_max_s=100.0).admissible


def test_with_c0_is_the_mapping_of_a_theta_that_differs_in_th6_alone():
    """PhysicalParams.with_c0 (what shift_bias uses) against the full mapping, also where the new c0 is
    not finite (then not admissible) or the dynamics are not (then nothing is)."""
    th = ct_theta_from_physical(np.array([0.02, 0.02, 0.02]), 0.01, np.array([10.0, 10.0, 600.0]), 0.01, 200.0, 0.01)
    p = ct_physical_from_theta(th, tau_min_s=1.0, tau_max_s=500.0)
    assert p.admissible.tolist() == [True, True, False]
    moved = th.copy()
    moved[:, 5] = [th[0, 5] * 1.5, np.inf, th[2, 5]]
    full = ct_physical_from_theta(moved, tau_min_s=1.0, tau_max_s=500.0)
    fast = p.with_c0(ct_c0_from_theta(moved[:, 5], moved[:, 1]))
    for key in ("r0_ohm", "r1_ohm", "c1_f", "r2_ohm", "c2_f", "c0_v", "admissible", "dynamics_ok"):
        assert np.array_equal(getattr(fast, key), getattr(full, key)), key
    assert fast.admissible.tolist() == [True, False, False]
    with pytest.raises(ValueError, match="dynamics_ok"):
        PhysicalParams(*p._arrays(), admissible=p.admissible).with_c0(p.c0_v)
