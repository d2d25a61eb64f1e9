"""What a vehicle does besides the discharge drive cycles: charge (CC-CV), park with the gateway awake, and a
current sensor with an offset.

A synthetic cell (2-RC plus a 1500 s diffusion branch, Plett's one-state hysteresis on the Panasonic 18650PF
25 degC table's half gap, capped as the estimator reads it) is driven, parked and charged; a CV phase holds the
terminal voltage at ``v_max`` in closed loop, ``i = (v_max - OCV - sum_j a_j x_j) / (R0 + sum_j R_j (1 - a_j))``.
"""

import numpy as np
import pytest

from bms_estimator.core.soc import SocEstimator
from bms_estimator.core.sox import SoxConfig
from bms_estimator.ocv_table import read_ocv_table
from bms_estimator.samples import sample_path

Q_TRUE_AH = 2.997  # the table's own C/20 capacity: the count's scale is right, a capacity learnt off it is wrong
Q_STATED_AH = 2.9
V_MAX = 4.2


def _table():
    return read_ocv_table(sample_path("panasonic-18650pf_25degC_ocv.csv"))


class _Cell:
    """The truth: R0, two RC pairs, a diffusion branch and Plett's hysteresis (state h, rate 30)."""

    def __init__(self, soc0: float, h0: float = 1.0, seed: int = 0):
        self.ocv = _table().with_half_gap_cap(0.05)
        self.z, self.h = soc0, h0
        self.r0 = 0.025
        self.r = np.array([0.012, 0.015, 0.012])
        self.tau = np.array([15.0, 300.0, 1500.0])
        self.x = np.zeros(3)
        self.rng = np.random.default_rng(seed)

    def _ocv(self) -> float:
        z = min(max(self.z, 0.0), 1.0)
        return float(self.ocv.ocv(z) + self.h * self.ocv.hysteresis(z))

    def step(self, i: float) -> float:
        a = np.exp(-1.0 / self.tau)
        self.x = a * self.x + self.r * (1.0 - a) * i
        dz = i / (3600.0 * Q_TRUE_AH)
        self.z += dz
        self.h = np.sign(i) + (self.h - np.sign(i)) * np.exp(-30.0 * abs(dz))
        return self._ocv() + self.r0 * i + self.x.sum() + 1e-3 * self.rng.standard_normal()

    def cv_current(self) -> float:
        a = np.exp(-1.0 / self.tau)
        return (V_MAX - self._ocv() - (a * self.x).sum()) / (self.r0 + (self.r * (1.0 - a)).sum())


def _drive(n: int, seed: int, mean_a: float = -1.5) -> np.ndarray:
    seg = np.random.default_rng(seed).uniform(-3.0, 2.1, size=n // 10 + 1)
    i = np.repeat(seg, 10)[:n]
    return i - i.mean() + mean_a


def _run_day(offset_a: float):
    """Drive 30 min from full, park 6 h with the gateway awake (1 s samples of the offset alone), charge at 1C
    for 40 min; the measured current carries ``offset_a``.  Returns (estimator, cell, SOC error at the park's
    end)."""
    cell = _Cell(1.0)
    est = SocEstimator(1, _table(), Q_STATED_AH, 1.0, initial_soc=1.0)

    def step(i_true):
        v = cell.step(i_true)
        est.update(i_true + offset_a, np.array([v]))

    for i in _drive(1800, 1):
        step(i)
    for _ in range(6 * 3600):
        step(0.0)
    err_park = est.soc[0] - cell.z
    for _ in range(2400):
        step(min(2.9, cell.cv_current()))
    return est, cell, err_park


@pytest.mark.parametrize("offset_a", [-0.05, 0.05])
def test_a_park_with_the_gateway_awake_does_not_read_a_current_offset_as_capacity(offset_a):
    """A current sensor's offset over a park whose samples go on (the gateway awake) moved the count by
    ``i_0 t / (3600 Q)`` (-50 mA over 6 h: 10 % SOC); the filter corrected that drift every sample through the
    SOC's correlation with the capacity and read it as a capacity error (before: -50 mA 3.31 Ah learnt for 3.00
    and the charge after it ending 4.9 % low with a sigma of 0.8 %; +50 mA 3.19 Ah).  Now the voltage is read
    as after a rest every rest_relaxation_s of it (-50 / +50 mA: 3.01 / 2.95 Ah, the charge's end 0.3 / 0.4 %)."""
    est, cell, err_park = _run_day(offset_a)
    assert abs(est.capacity_ah[0] / Q_TRUE_AH - 1.0) < 0.03
    assert abs(err_park) < 0.025
    assert abs(est.soc[0] - cell.z) < 0.02
    assert abs(est.soc[0] - cell.z) < 2.0 * est.soc_sigma[0] + 0.005


def _cccv_charge(soc0: float = 0.6, told: float | None = None, out: dict | None = None):
    """A CC-CV charge at 1C to V_MAX, ending at C/20, from ``soc0`` after 10 min of rest, then 10 min of rest;
    the estimator told ``told`` (default: the SOC).  Returns (time to full per sample, true seconds left per
    charging sample, index of the CC end, index of the charger's stop); ``out`` gets the net energy delivered
    and the SOC per sample, and the true SOC at the end."""
    from bms_estimator.core.sox import SoxEstimator

    cell = _Cell(soc0, h0=-1.0)
    est = SocEstimator(1, _table(), Q_STATED_AH, 1.0, initial_soc=soc0 if told is None else told)
    sox = SoxEstimator(1, 1.0)
    ttf, currents = [], []
    out = {} if out is None else out
    out.update(energy_delivered_wh=[], soc=[])

    def step(i):
        v = np.array([cell.step(i)])
        est.update(i, v)
        sox.update(est, i, v)
        ttf.append(float(sox.outputs["time_to_full_s"][0]))
        currents.append(i)
        out["energy_delivered_wh"].append(float(sox.outputs["energy_delivered_wh"][0]))
        out["soc"].append(float(est.soc[0]))

    for _ in range(600):
        step(0.0)
    start = len(ttf)
    while True:
        i = min(2.9, cell.cv_current())
        if i < 0.05 * Q_STATED_AH:
            break
        step(i)
    stop = len(ttf)
    for _ in range(600):
        step(0.0)
    c = np.array(currents)
    out["true_soc"] = cell.z
    cc_end = start + int(np.argmax(c[start:stop] < 2.9 - 1e-9))
    return np.array(ttf), stop - np.arange(stop), cc_end, stop


def test_time_to_full_follows_the_cv_taper_reaches_zero_and_stops_with_the_charger():
    """Time to full was 3600 Q (1 - s) / I_m: the CV taper ignored (at the end of CC it said 30 % of the time
    left), never 0 at the charger's end, and after the charger stopped it rose with the
    decaying 300 s mean current before it turned infinite (here: 644 s at the CC end for 1664 s left, the CV
    phase's median error 503 s, 772 s at the stop, 1707 s 5 min after it).  Now a CC-CV charge to v_max from
    the cell's voltage and current now (core.soe): 1559 s, 164 s, 0, infinite."""
    ttf, left, cc_end, stop = _cccv_charge()
    assert 0.6 < ttf[cc_end] / left[cc_end] < 1.3
    assert ttf[stop - 1] < 60.0
    assert np.all(np.isinf(ttf[stop + 10:]))  # (the slow outputs are recomputed every 10 s)
    cv = slice(cc_end, stop)
    assert np.median(np.abs(ttf[cv] - left[cv])) < 0.15 * (stop - cc_end)


def test_the_net_energy_delivered_restarts_at_the_end_of_a_cc_cv_charge():
    """A CC-CV charge to C/20 ends at 98-99 % of the tables' scale; the net energy delivered restarted only at
    ``full_soc`` (0.99), so a full charge whose SOC ended under it (here from 30 %, told 10 % low)
    left the count at the charge's energy, negative, for good (SOC 0.977 at the stop, true 0.988: -8.2 Wh).
    Now the end of the CV phase is full."""
    out = {}
    _, _, _, stop = _cccv_charge(0.3, told=0.2, out=out)
    assert out["true_soc"] > 0.98
    assert out["soc"][stop - 1] < SoxConfig().full_soc  # the case: the SOC alone does not say full
    assert out["energy_delivered_wh"][stop - 1] == 0.0
    assert out["energy_delivered_wh"][-1] == 0.0  # (at rest after it: nothing delivered since)
