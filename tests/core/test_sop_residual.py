"""The learnt R_D correction (core.sop_residual): what it learns, when, and where it applies."""

import numpy as np
import pytest

from bms_estimator.core.sop_residual import ResidualConfig, ResidualResistance

Q = np.array([3.0, 3.0])


def _feed(res, currents, *, base, r_d, ocv0, true_extra, soc=0.5, ocv_end=None):
    """Feed samples; the voltage each sample is what a cell with R_D + true_extra shows under a
    current held since the window's start (the window's end value is the one scored)."""
    seen = []
    basis = (base, r_d, ocv0)
    i_w = np.mean([c for c in currents if np.any(c)], axis=0)  # the window's mean current
    for i in currents:
        i = np.asarray(i, dtype=float)
        v = base[0] + (ocv_end - ocv0) + (r_d[0] + true_extra) * i_w
        res.sample(i, v, ocv_end, soc, Q, basis)
        seen.append(res.dr_ohm[:, 0].copy())
    return seen


def test_a_held_step_teaches_the_missed_resistance_after_the_window_only():
    res = ResidualResistance(2, 1.0, (10.0,))
    base = np.array([[3.70, 3.65]])
    r_d = np.array([[0.030, 0.040]])
    ocv0 = np.array([3.68, 3.64])
    ocv_end = ocv0 - 0.002
    rest = [np.zeros(2)] * 61  # a minute at rest before the step
    # cell 0 discharges, cell 1 charges; the logger spreads the step over two samples (a ramp-in
    # sample, itself a step): the window starts there and holds
    pulse = [np.array([-1.0, 1.0])] + [np.array([-3.0, 2.0])] * 9
    seen = _feed(res, rest + pulse, base=base, r_d=r_d, ocv0=ocv0, true_extra=np.array([0.004, -0.006]),
                 ocv_end=ocv_end)
    assert np.all(np.isnan(seen[-2]))  # 9 samples of the window: nothing learnt yet (causal)
    np.testing.assert_allclose(res.dr_ohm[0, 0, 0], 0.004, rtol=1e-9)  # discharge row of cell 0
    np.testing.assert_allclose(res.dr_ohm[1, 0, 1], -0.006, rtol=1e-9)  # charge row of cell 1
    assert np.isnan(res.dr_ohm[1, 0, 0]) and np.isnan(res.dr_ohm[0, 0, 1])
    corr = res.correction(np.array([0.52, 0.45]))
    np.testing.assert_allclose(corr, [[0.004, 0.0], [0.0, -0.006]], rtol=1e-9)
    assert res.correction(np.array([0.75, 0.2])) is None  # seen 0.25 SOC away: not used
    for _ in range(3601):
        res.sample(np.zeros(2), base[0], ocv_end, 0.5, Q, None)
    assert res.correction(np.array([0.5, 0.5])) is None  # older than an hour


def test_a_window_whose_current_did_not_hold_or_was_too_small_is_not_used():
    res = ResidualResistance(2, 1.0, (10.0,))
    kw = dict(base=np.array([[3.7, 3.7]]), r_d=np.array([[0.03, 0.03]]), ocv0=np.array([3.7, 3.7]),
              true_extra=np.array([0.01, 0.01]), ocv_end=np.array([3.7, 3.7]))
    pulse = [np.array([-3.0, -0.3])] * 5 + [np.array([-0.5, -0.3])] * 5  # cell 0 drops to 1/6; cell 1 below 0.25C
    _feed(res, [np.zeros(2)] * 61 + pulse, **kw)
    assert np.all(np.isnan(res.dr_ohm)) and res.windows_scored == 0
    # a step that holds but does not come out of a minute's rest (a drive's) is not learnt from
    res = ResidualResistance(2, 1.0, (10.0,))
    _feed(res, [np.zeros(2)] * 30 + [np.array([-3.0, 2.0])] * 10, **kw)
    assert res.windows_scored == 0
    assert ResidualResistance(2, 1.0, (10.0,), ResidualConfig(enabled=False)).correction(np.zeros(2)) is None


def test_rest_ages_the_learnt_resistance_closes_open_windows_and_counts_the_park_as_rest():
    """rest(T) is T / Ts samples at zero current: a dR learnt before a 2 h park is too old after it (kept,
    not used); a window open when the samples stopped is not scored; a step right after the park is a step
    out of rest; the cell not named keeps all of it."""
    kw = dict(base=np.array([[3.70, 3.65]]), r_d=np.array([[0.030, 0.040]]), ocv0=np.array([3.68, 3.64]),
              true_extra=np.array([0.004, -0.006]), ocv_end=np.array([3.678, 3.638]))
    res = ResidualResistance(2, 1.0, (10.0,))
    _feed(res, [np.zeros(2)] * 61 + [np.array([-3.0, 2.0])] * 10, **kw)
    learnt = res.dr_ohm.copy()
    assert np.isfinite(res.correction(np.array([0.5, 0.5]))).all()
    res.rest(2 * 3600.0, np.array([True, False]))
    np.testing.assert_array_equal(res.dr_ohm, learnt)  # kept
    corr = res.correction(np.array([0.5, 0.5]))
    assert corr[0, 0] == 0.0 and corr[1, 1] == pytest.approx(-0.006)  # cell 0's discharge dR aged out; cell 1's charge dR used
    # a window open at the gap is closed unscored
    res = ResidualResistance(2, 1.0, (10.0,))
    _feed(res, [np.zeros(2)] * 61 + [np.array([-3.0, 2.0])] * 5, **kw)
    res.rest(600.0, np.array([True, True]))
    _feed(res, [np.array([-3.0, 2.0])] * 5, **kw)
    assert res.windows_scored == 0
    # a step at the first sample after the park opens a window (the park counted as rest), scored as usual
    res = ResidualResistance(2, 1.0, (10.0,))
    res.rest(600.0, np.array([True, True]))
    _feed(res, [np.array([-3.0, 2.0])] * 10, **kw)
    assert res.windows_scored == 2


def test_what_was_learnt_survives_a_restart_with_its_age_and_an_open_window_does_not():
    """state_dict / load_state_dict into a fresh instance (a service restart): the dRs, their SOC and age
    (counted on from the new instance's samples), the time at rest and the last current come back, so the
    correction is the same at once and ages out at the same moment; a window open at the save is dropped;
    a field of the wrong shape is named."""
    kw = dict(base=np.array([[3.70, 3.65]]), r_d=np.array([[0.030, 0.040]]), ocv0=np.array([3.68, 3.64]),
              true_extra=np.array([0.004, -0.006]), ocv_end=np.array([3.678, 3.638]))
    res = ResidualResistance(2, 1.0, (10.0,))
    _feed(res, [np.zeros(2)] * 61 + [np.array([-3.0, 2.0])] * 10, **kw)
    for _ in range(100):  # back at rest a while: the dRs are 100 samples old
        res.sample(np.zeros(2), kw["base"][0], kw["ocv_end"], 0.5, Q, None)
    saved = res.state_dict()
    back = ResidualResistance(2, 1.0, (10.0,))
    back.load_state_dict(saved)
    soc = np.array([0.5, 0.5])
    np.testing.assert_array_equal(back.correction(soc), res.correction(soc))
    assert np.isfinite(back.correction(soc)).all() and np.any(back.correction(soc) != 0.0)
    steps = 0
    while res.correction(soc) is not None:  # both age out at the same sample: an hour after each dR was seen
        np.testing.assert_array_equal(back.correction(soc), res.correction(soc))
        for r in (res, back):
            r.sample(np.zeros(2), kw["base"][0], kw["ocv_end"], 0.5, Q, None)
        steps += 1
    assert back.correction(soc) is None and 3400 < steps <= 3600
    # the time at rest came back: a step at the first sample after the restart opens a window
    back = ResidualResistance(2, 1.0, (10.0,))
    back.load_state_dict(saved)
    _feed(back, [np.array([-3.0, 2.0])] * 10, **kw)
    assert back.windows_scored == 2
    # a window open at the save is not scored after the restart
    res = ResidualResistance(2, 1.0, (10.0,))
    _feed(res, [np.zeros(2)] * 61 + [np.array([-3.0, 2.0])] * 5, **kw)
    back = ResidualResistance(2, 1.0, (10.0,))
    back.load_state_dict(res.state_dict())
    _feed(back, [np.array([-3.0, 2.0])] * 5, **kw)
    assert back.windows_scored == 0
    with pytest.raises(ValueError, match="dr_soc"):
        back.load_state_dict(dict(saved, dr_soc=np.zeros(3)))
