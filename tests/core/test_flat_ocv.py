"""A cell with a flat OCV (LFP-like: 10-50 mV per 10 % SOC on its plateaus, steep ends, a 15 mV half gap).

The measured cells (NCA, NMC) have 0.3-1.3 V per unit SOC between 20 and 90 %; this one 0.1-0.35,
so the voltage says 3-10 times less about the SOC there, and a C/20 knot 0.5 % apart moves by
0.5-2 mV, the size of a logger's noise.  2.5 Ah, 2-RC, 20 mA / 2 mV of noise, 1 s.
"""

import numpy as np
import pytest

from bms_estimator.core.ecm import EcmParams, simulate_ecm, soc_from_current
from bms_estimator.core.hysteresis import hysteresis_trajectory
from bms_estimator.core.ocv import OcvCurve
from bms_estimator.core.soc import SocConfig, SocEstimator
from tests.conftest import pulse_current

Q_AH = 2.5
HALF_GAP_V = 0.015
KNOTS = np.array([
    (0.00, 2.80), (0.02, 3.00), (0.05, 3.12), (0.10, 3.19), (0.15, 3.215), (0.20, 3.230),
    (0.30, 3.250), (0.40, 3.265), (0.50, 3.275), (0.60, 3.285), (0.65, 3.300), (0.70, 3.315),
    (0.80, 3.325), (0.90, 3.335), (0.95, 3.345), (0.98, 3.380), (1.00, 3.500)])
TRUE = OcvCurve(KNOTS[:, 0], KNOTS[:, 1], np.full(len(KNOTS), HALF_GAP_V), capacity_discharge_ah=Q_AH)
PARAMS = EcmParams.from_rc(0.018, [0.010, 0.015], [12.0, 250.0])

C20_TABLE_NOISE = ("known limitation: `bms-estimator ocv` (OcvCurve.from_c20) reads each knot off one sample, so "
                   "on a flat OCV a logger's 2 mV of noise becomes the table's slope (67 of 201 knots flat-repaired, "
                   "the slope's mean square 3.6 x the OCV's) and the SOC filter on that table is over-confident; "
                   "fitting each knot over its grid step fixes both, but moves the measured SOC matrix (the "
                   "Panasonic 25 degC hwfet_a correct start flips between 1.2-1.5 and 2.9 % on knot changes of 0.1 "
                   "mV), so it waits for the matrix to be re-measured")


def _cell(i_true: np.ndarray, soc0: float, h0: float, seed: int):
    """Measured (current, voltage) and the true SOC (hysteresis rate 25 per unit SOC; the estimator assumes 30)."""
    soc = soc_from_current(i_true, 1.0, Q_AH, soc0)
    h, _ = hysteresis_trajectory(i_true, 1.0, Q_AH, 25.0, h0=h0)
    v = simulate_ecm(i_true, 1.0, PARAMS, soc=soc, output="mean").voltage_v + TRUE.ocv(soc) + h * HALF_GAP_V
    rng = np.random.default_rng(seed)
    return i_true + 0.02 * rng.standard_normal(i_true.size), v + 2e-3 * rng.standard_normal(i_true.size), soc


def _drive(legs, soc0: float, h0: float, seed: int):
    """Pulses (levels held 5-120 s, up to 2C) whose means move the SOC by each leg's dz, then 20 min of rest."""
    parts = []
    for k, (n, dz) in enumerate(legs):
        i = pulse_current(n, seed + k, amp_a=2 * Q_AH)
        parts.append(i - (i.mean() - dz * Q_AH * 3600 / n))
    return _cell(np.concatenate(parts + [np.zeros(1200)]), soc0, h0, seed)


def _run(table: OcvCurve, cur: np.ndarray, vol: np.ndarray, start_soc: float):
    est = SocEstimator(1, table, Q_AH, 1.0, initial_soc=start_soc, config=SocConfig())
    soc, sigma, cap = (np.empty(cur.size) for _ in range(3))
    for k in range(cur.size):
        est.update(cur[k:k + 1], vol[k:k + 1])
        soc[k], sigma[k], cap[k] = est.soc[0], est.soc_sigma[0], est.capacity_ah[0]
    return soc, sigma, cap


@pytest.fixture(scope="module")
def c20_table() -> OcvCurve:
    """The table `bms-estimator ocv` makes of the cell's C/20 test logged at 1 s."""
    n = 20 * 3600
    i = np.concatenate([np.zeros(3600), -Q_AH / 20 * np.ones(n), np.zeros(3600), Q_AH / 20 * np.ones(n)])
    cur, vol, _ = _cell(i, 1.0, 1.0, 1)
    return OcvCurve.from_c20(np.arange(i.size, dtype=float), cur, vol)


@pytest.fixture(scope="module")
def plateau_drive():
    """3 h from 85 % (off a charge) down to 30 %, up to 88 %, down to 50 %: never off the plateau."""
    return _drive([(3600, -0.55), (3600, 0.50), (2400, -0.30)], 0.85, 1.0, 201)


def _within_2_sigma(soc, sigma, soc_true, after_s: int = 1800) -> float:
    return float(np.mean(np.abs(soc[after_s:] - soc_true[after_s:]) <= 2 * sigma[after_s:]))


def test_on_the_plateau_the_soc_sigma_says_how_little_the_voltage_tells(plateau_drive):
    """From 20 % low with the cell's own table: the SOC stays in [0, 1] and the error within 2 sigma from
    30 min on (measured 100 %, its median sigma 3.1 %, the error -3.6 % at the end with sigma 2.6 %), and
    the capacity, which the plateau cannot tell, holds at the table's."""
    cur, vol, soc_true = plateau_drive
    soc, sigma, cap = _run(TRUE, cur, vol, 0.65)
    assert np.all(np.isfinite(soc)) and np.all((soc >= 0) & (soc <= 1)) and np.all(np.isfinite(sigma))
    assert _within_2_sigma(soc, sigma, soc_true) > 0.95
    assert np.all(np.abs(cap / Q_AH - 1) < 0.01)


def test_a_start_20pct_low_is_corrected_where_the_ocv_turns_steep():
    """From 70 % down to 3 % and back to 30 %, started at 50 %: corrected at the steep low end (measured:
    at most 0.3 % over the last 20 min) and never claimed surer than it was (within 2 sigma from 30 min on:
    100 %); the capacity 2.499-2.514 Ah."""
    cur, vol, soc_true = _drive([(5400, -0.67), (2700, 0.27)], 0.70, -1.0, 301)
    soc, sigma, cap = _run(TRUE, cur, vol, 0.50)
    assert np.all((soc >= 0) & (soc <= 1))
    assert np.max(np.abs(soc[-1200:] - soc_true[-1200:])) < 0.01
    assert _within_2_sigma(soc, sigma, soc_true) > 0.95
    assert np.all(np.abs(cap / Q_AH - 1) < 0.02)


@pytest.mark.xfail(strict=True, reason=C20_TABLE_NOISE)
def test_a_c20_table_of_a_flat_ocv_keeps_its_slope(c20_table):
    """On the plateau the table's slope is the OCV's, not 2 mV of noise over 0.5 % SOC (now: 67 of 201
    knots flat-repaired, the slope's mean square 3.6 times the OCV's; knots fitted over their grid step:
    none, 1.07)."""
    z = np.linspace(0.2, 0.9, 1401)
    ratio = np.mean(c20_table.docv_dsoc(z) ** 2 / TRUE.docv_dsoc(z) ** 2)
    assert 0.7 < ratio < 1.3, ratio
    assert np.count_nonzero(np.diff(c20_table.ocv_v) < 2e-6) == 0  # no knot needed the monotone repair


@pytest.mark.xfail(strict=True, reason=C20_TABLE_NOISE)
def test_on_the_plateau_the_soc_sigma_covers_the_error_on_the_c20_table(c20_table, plateau_drive):
    """As the test on the cell's own table, on the table its C/20 test gives (now: outside 2 sigma for the
    whole drive, -7 % at its end with sigma 1.9 %; knots fitted over their grid step: within 2 sigma)."""
    cur, vol, soc_true = plateau_drive
    soc, sigma, _ = _run(c20_table, cur, vol, 0.65)
    assert np.all((soc >= 0) & (soc <= 1))
    assert _within_2_sigma(soc, sigma, soc_true) > 0.95
