"""The core at the edges of what a vehicle gateway feeds it: each test here failed on the code before its fix."""

import numpy as np

from bms_estimator.core.ocv import OcvCurve
from bms_estimator.core.soc import SocEstimator
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
