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
