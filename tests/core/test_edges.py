"""The core at the edges of what a vehicle gateway feeds it: each test here failed on the code before its fix."""

import numpy as np
import pytest

from bms_estimator.core.arrhenius import arrhenius_factor
from bms_estimator.core.ocv import OcvCurve
from bms_estimator.core.soc import SocConfig, SocEstimator
from bms_estimator.core.soh import SohConfig, r0_at_reference
from bms_estimator.core.sop import SopConfig, derate
from bms_estimator.core.sox import SoxEstimator

_S = np.linspace(0.0, 1.0, 51)
CURVE = OcvCurve(_S, 3.0 + 1.2 * _S)  # one OCV table: the service's built-in curve, or a single pack.ocv_csv


def test_one_ocv_table_still_derates_the_sop_and_corrects_r0_at_the_cells_temperature():
    """With one OCV table the OCV does not depend on temperature, but the cells still have one: the SOP's
    temperature derating and the resistance SOH's Arrhenius step read each cell's last valid temperature.
    (Before, a single table left ``temperature_c`` at 25 degC for good: a cell at 80 degC kept its full
    discharge and charge currents, one at -30 degC a charge current the derating forbids.)"""
    t = np.array([80.0, 25.0, -30.0])
    est = SocEstimator(3, CURVE, 3.0, 1.0, initial_soc=0.6)
    sox = SoxEstimator(3, 1.0)
    cfg = SopConfig()
    for k in range(20):
        t_now = np.where(k % 2, np.nan, t) if k > 10 else t  # lost readings keep the last
        est.update(0.0, np.full(3, 3.72), temperature_c=t_now)
        sox.update(est, 0.0, np.full(3, 3.72))
    np.testing.assert_array_equal(est.temperature_c, t)
    dis, chg = derate(t, cfg.derate_temperatures_c, cfg.discharge_derate), derate(t, cfg.derate_temperatures_c,
                                                                                   cfg.charge_derate)
    for h in cfg.horizons_s:
        i_dis, i_chg = sox.outputs[f"i_discharge_max_{h:g}s_a"], sox.outputs[f"i_charge_max_{h:g}s_a"]
        assert np.all(i_dis <= cfg.i_discharge_max_a * dis + 1e-9), (h, i_dis)
        assert np.all(i_chg <= cfg.i_charge_max_a * chg + 1e-9), (h, i_chg)
        assert i_dis[0] == 0.0 and i_chg[0] == 0.0 and i_chg[2] == 0.0  # too hot for either, too cold to charge
        assert i_dis[1] > 0.0 and i_chg[1] > 0.0


def _pulsed_cell(n: int):
    """(current, voltage) samples of a 2-RC cell on CURVE, pulses of up to 2C on 3 Ah, from 60 % SOC."""
    soc, v1, v2 = 0.6, 0.0, 0.0
    for k in range(n):
        i = 6.0 * np.sin(k / 23.0) * (1.0 if (k // 60) % 3 else -1.5)
        v1 = 0.905 * v1 + 0.01 * (1 - 0.905) * i
        v2 = 0.995 * v2 + 0.015 * (1 - 0.995) * i
        soc += i / (3600.0 * 3.0)
        yield i, np.full(2, float(CURVE.ocv(soc)) + 0.02 * i + v1 + v2), soc


@pytest.mark.parametrize("soc_method", ["ekf", "c0"])
@pytest.mark.parametrize("first_c", [-250.0, -100.0, 300.0])
def test_a_first_temperature_no_cell_can_have_is_a_missing_one(soc_method, first_c):
    """The prior's resistances (identifier, EKF diffusion branch) follow the first temperature reading by the
    Arrhenius line; a reading no cell can have (a thermistor fault) is no reading: the run is the one whose
    first reading is missing, bit for bit.  (Before, -250 degC left R0 at 3.6e41 ohm for good, -100 degC moved
    the EKF's SOC 37 % low in 10 min.)"""
    runs = []
    for first in (first_c, np.nan):
        cfg = SocConfig(soc_method=soc_method)
        est = SocEstimator(2, CURVE, 3.0, 1.0, initial_soc=0.6, config=cfg)
        for k, (i, v, soc_true) in enumerate(_pulsed_cell(600)):
            est.update(i, v, temperature_c=np.array([first if k < 3 else 20.0, 20.0]))
        assert np.all(np.abs(est.soc - soc_true) < 0.02), est.soc
        runs.append((est.soc.copy(), {key: val.copy() for key, val in est.params.items()}))
    (soc_a, p_a), (soc_b, p_b) = runs
    np.testing.assert_array_equal(soc_a, soc_b)
    for key in p_b:
        np.testing.assert_array_equal(p_a[key], p_b[key], err_msg=key)


def test_arrhenius_factor_and_r0_soh_skip_a_temperature_no_cell_can_have():
    f = arrhenius_factor(np.array([-250.0, -61.0, -60.0, 120.0, 121.0, 1e6]), 25.0, 2500.0)
    np.testing.assert_array_equal(f[[0, 1, 4, 5]], 1.0)
    assert f[2] > 20.0 and f[3] < 0.2  # inside the range, the line itself
    r = r0_at_reference(np.full(3, 0.02), np.array([-100.0, 25.0, 200.0]), SohConfig())
    assert np.isnan(r[0]) and r[1] == 0.02 and np.isnan(r[2])
