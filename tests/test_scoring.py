"""The independent SOC reference on constructed recordings with a known answer."""

import numpy as np
import pytest

from bms_estimator.core.ocv import OcvCurve
from bms_estimator.scoring import counted_soc, soc_error_figures, soc_on_branch, soc_reference


@pytest.fixture
def c20_table():
    s = np.linspace(0.0, 1.0, 11)
    return OcvCurve(s, 3.2 + 0.9 * s + 0.1 * s**2, np.full(11, 0.02))


def _drive(ocv, q_true, soc_end, rest_s, relax_mv_per_ln=0.0):
    """A constant 1 A discharge from full to ``soc_end`` of ``q_true``, then a rest on the discharge branch."""
    n_dis = int(round((1.0 - soc_end) * q_true * 3600))
    i = np.concatenate([-np.ones(n_dis), np.zeros(rest_s)])
    v_rest = ocv.ocv(soc_end) - ocv.hysteresis(soc_end)
    t_rest = np.arange(1, rest_s + 1, dtype=float)
    # a voltage that still recovers as a ln t: it reads v_rest at the end
    rest = v_rest + relax_mv_per_ln * 1e-3 * (np.log(t_rest) - np.log(t_rest[-1]))
    v = np.concatenate([np.full(n_dis, 3.5), rest])
    return i, v, n_dis


@pytest.mark.parametrize("soc", [0.15, 0.5, 0.85])
def test_a_rest_voltage_reads_its_own_branch(c20_table, soc):
    """The same voltage is a higher SOC on the discharge branch (mean - H) than on the charge branch (mean + H)."""
    mean, h = float(c20_table.ocv(soc)), float(c20_table.hysteresis(soc))
    assert soc_on_branch(mean - h, c20_table, side=-1.0)[0] == pytest.approx(soc, abs=1e-3)
    assert soc_on_branch(mean + h, c20_table, side=1.0)[0] == pytest.approx(soc, abs=1e-3)
    on_discharge, on_charge = (soc_on_branch(mean, c20_table, side=side)[0] for side in (-1.0, 1.0))
    assert on_discharge > soc > on_charge


def test_reference_reads_the_end_rest_on_the_discharge_branch(c20_table):
    i, v, n_dis = _drive(c20_table, q_true=2.5, soc_end=0.1, rest_s=600)
    ref = soc_reference(i, v, 1.0, c20_table)
    ah_out = n_dis / 3600.0
    assert ref.soc_end == pytest.approx(0.1, abs=1e-3)
    assert ref.capacity_ah == pytest.approx(ah_out / (1 - ref.soc_end), rel=1e-12)
    assert ref.capacity_ah == pytest.approx(2.5, rel=2e-3)
    assert ref.relaxed and ref.pct_per_doubling < 1e-6
    np.testing.assert_allclose(ref.soc, counted_soc(i, 1.0, ref.capacity_ah, 1.0))
    assert ref.soc[n_dis - 1] == pytest.approx(0.1, abs=2e-3)


def test_a_rest_still_recovering_is_reported_but_not_scored(c20_table):
    # 10 mV per ln(t) on a 1.1 V per SOC slope: 0.63 % SOC per doubling - relaxed enough
    i, v, _ = _drive(c20_table, 2.5, 0.1, 600, relax_mv_per_ln=10.0)
    assert soc_reference(i, v, 1.0, c20_table).relaxed
    # 60 mV per ln(t): 3.8 % per doubling - the -10 degC LG files look like this
    i, v, _ = _drive(c20_table, 2.5, 0.1, 600, relax_mv_per_ln=60.0)
    ref = soc_reference(i, v, 1.0, c20_table)
    assert not ref.relaxed
    assert ref.pct_per_doubling == pytest.approx(100 * 0.06 * np.log(2) / float(c20_table.docv_dsoc(0.1)), rel=0.05)
    assert "not relaxed" in ref.why


def test_reference_errors_name_what_is_missing(c20_table):
    i, v, _ = _drive(c20_table, 2.5, 0.1, 60)
    with pytest.raises(ValueError, match="final rest"):
        soc_reference(i, v, 1.0, c20_table)
    i, v, _ = _drive(c20_table, 2.5, 0.1, 600)
    with pytest.raises(ValueError, match="net discharge"):
        soc_reference(-i, v, 1.0, c20_table)


def test_error_figures_count_from_the_start(c20_table):
    t = np.arange(7200.0)
    ref = np.linspace(1.0, 0.2, t.size)
    est = ref + np.where(t < 2400, 0.10, 0.01)
    figs = soc_error_figures(est, ref, t, start_s=600.0)
    # 30 min after a start at 600 s is 2400 s: from there the error is 1 %
    assert figs["rmse_30min_pct"] == pytest.approx(1.0)
    assert figs["rmse_1h_pct"] == pytest.approx(1.0)
    assert figs["max_abs_pct"] == pytest.approx(1.0)
    assert figs["rmse_all_pct"] > 1.0


def test_the_end_rest_is_counted_in_samples_and_read_at_its_end(c20_table):
    """soc_end is read from the *last* (most relaxed) rest sample, the rest's length is the quiet samples
    after the last loaded one, and a rest of exactly 120 s is long enough (the error says 'at least')."""
    # still recovering 10 mV per ln t (relaxed): the first rest sample is 64 mV below the end, 6 % SOC
    i, v, _ = _drive(c20_table, 2.5, 0.1, 600, relax_mv_per_ln=10.0)
    ref = soc_reference(i, v, 1.0, c20_table)
    assert ref.soc_end == pytest.approx(0.1, abs=1e-3)
    assert ref.rest_s == 600.0
    assert soc_reference(*_drive(c20_table, 2.5, 0.1, 120)[:2], 1.0, c20_table).rest_s == 120.0
    with pytest.raises(ValueError, match="final rest"):
        soc_reference(*_drive(c20_table, 2.5, 0.1, 119)[:2], 1.0, c20_table)


def test_the_recovery_fit_starts_after_the_first_minute(c20_table):
    """The ln t fit is over the rest after its first 60 s: a 100 mV RC relaxation of tau 10 s, gone by then
    (0.25 mV left at 60 s), is not diffusion still recovering and moves the figure by < 0.01 % per doubling
    (fitted from t = 1 s it reads 0.4 %)."""
    i, v, n_dis = _drive(c20_table, 2.5, 0.1, 600)
    v[n_dis:] -= 0.1 * np.exp(-np.arange(1, 601) / 10.0)
    ref = soc_reference(i, v, 1.0, c20_table)
    assert ref.relaxed and ref.pct_per_doubling < 0.01


def test_a_rest_that_cannot_show_it_is_relaxed_is_not_scored(c20_table):
    """Fewer than 10 samples after the first minute (a 130 s rest sampled every 10 s: 7) cannot fit the
    recovery: the figure is infinite and the reference is not relaxed."""
    i = np.concatenate([-np.ones(810), np.zeros(13)])  # 10 s samples: 2.25 Ah out, then 130 s of rest
    v = np.concatenate([np.full(810, 3.5), np.full(13, float(c20_table.ocv(0.1) - c20_table.hysteresis(0.1)))])
    ref = soc_reference(i, v, 10.0, c20_table)
    assert ref.rest_s == 130.0 and ref.pct_per_doubling == np.inf and not ref.relaxed
    assert ref.capacity_ah == pytest.approx(2.25 / (1 - ref.soc_end), rel=1e-12)


def test_a_rest_voltage_still_falling_is_as_unrelaxed_as_one_rising(c20_table):
    """The bound is on |b|: a rest still falling 60 mV per ln t (after a charge) is 3.8 % per doubling too."""
    up = soc_reference(*_drive(c20_table, 2.5, 0.1, 600, relax_mv_per_ln=60.0)[:2], 1.0, c20_table)
    down = soc_reference(*_drive(c20_table, 2.5, 0.1, 600, relax_mv_per_ln=-60.0)[:2], 1.0, c20_table)
    assert not down.relaxed
    assert down.pct_per_doubling == pytest.approx(up.pct_per_doubling, rel=1e-9)


def test_the_callers_relaxation_bound_is_the_one_applied(c20_table):
    """10 mV per ln t reads 0.63 % per doubling: relaxed under the default 2 %, not under a caller's 0.5 %."""
    i, v, _ = _drive(c20_table, 2.5, 0.1, 600, relax_mv_per_ln=10.0)
    assert soc_reference(i, v, 1.0, c20_table).relaxed
    ref = soc_reference(i, v, 1.0, c20_table, max_pct_per_doubling=0.5)
    assert 0.5 < ref.pct_per_doubling < 2.0 and not ref.relaxed


def test_an_end_voltage_at_the_top_of_the_discharge_branch_is_refused(c20_table):
    """An end voltage at or above the full discharge branch reads soc_end = 1: no capacity (Q_ref = Ah / 0)."""
    i, v, _ = _drive(c20_table, 2.5, 0.1, 600)
    v[-600:] = float(c20_table.ocv(1.0) - c20_table.hysteresis(1.0)) + 0.01
    with pytest.raises(ValueError, match="reads full"):
        soc_reference(i, v, 1.0, c20_table)


def test_counted_soc_is_read_at_mid_sample():
    """-3.6 A on 1 Ah, 1 s samples: 0.1 % SOC per sample; sample k (a period mean) reads 1 - 0.001 (k + 1/2)."""
    np.testing.assert_allclose(counted_soc(np.full(4, -3.6), 1.0, 1.0), 1.0 - 0.001 * (np.arange(4) + 0.5), rtol=1e-12)


def test_each_error_window_starts_where_it_says():
    """start 600 s; the error is 5 % until 30 min after it, 3 % until 1 h after it, then -1 %, and the estimator
    has no SOC (NaN) for its first 100 s: rmse_1h is the -1 % part's 1 %, rmse_30min the rms of the 3 % and
    -1 % halves, max |error| 3 %; the NaN samples are left out of every figure."""
    t = np.arange(600.0, 600.0 + 3 * 3600)
    ref = np.linspace(1.0, 0.2, t.size)
    after = t - 600.0
    err = np.where(after < 1800, 0.05, np.where(after < 3600, 0.03, -0.01))
    est = np.where(after < 100, np.nan, ref + err)
    figs = soc_error_figures(est, ref, t, start_s=600.0)
    assert figs["rmse_1h_pct"] == pytest.approx(1.0)
    assert figs["rmse_30min_pct"] == pytest.approx(np.sqrt((1800 * 9.0 + 7200 * 1.0) / 9000))
    assert figs["max_abs_pct"] == pytest.approx(3.0)
    assert figs["rmse_all_pct"] == pytest.approx(np.sqrt((1700 * 25.0 + 1800 * 9.0 + 7200 * 1.0) / 10700))


def test_the_largest_error_is_the_largest_in_size():
    """max_abs_pct is max |error|: a -4 % error is larger than a +1 % one."""
    t = np.arange(7200.0)
    ref = np.full(t.size, 0.5)
    est = ref + np.where(t < 5000, 0.01, -0.04)
    assert soc_error_figures(est, ref, t)["max_abs_pct"] == pytest.approx(4.0)
