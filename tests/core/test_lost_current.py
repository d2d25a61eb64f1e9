"""A lost current (``SocEstimator.update`` with a NaN current): counted with the current's running mean,
the SOC's uncertainty grown by what that guess may miss, and the voltage correcting it once the current
is back. On the shipped measured LG HG2 la92 recording (Kollmeyer et al., CC BY 4.0; see
``bms_estimator/samples/ATTRIBUTION.md``), scored against its independent reference."""

from __future__ import annotations

import numpy as np
import pytest

from bms_estimator.cli.common import load_ocv
from bms_estimator.core.soc import SocConfig, SocEstimator
from bms_estimator.data import load_recording
from bms_estimator.samples import drive_cycle, ocv_table
from bms_estimator.scoring import soc_reference

Q_STATED = 3.0
LOST_S = 300  # five minutes without the current frame
AFTER_S = 1800  # scored over the half hour after it


@pytest.fixture(scope="module")
def la92():
    rec = load_recording(drive_cycle("lg-hg2", "la92"), resample_s=1.0)
    ocv = load_ocv([ocv_table("lg-hg2")], rec, capacity_ah=Q_STATED)
    ref = soc_reference(rec.current_a, rec.voltage_v, rec.dt_s, ocv)
    return rec, ocv, ref.soc


def _run(rec, ocv, lost_at: int, mode: str, config: SocConfig = SocConfig()):
    """SOC error (%) and sigma (%) per sample; the current lost for LOST_S from ``lost_at``, handled as
    ``mode``: "nan" (what the service now passes), "skip" (no update at all: what it did before), or
    "none" (not lost)."""
    est = SocEstimator(1, ocv, Q_STATED, 1.0, initial_soc=np.array([1.0]), config=config)
    soc, sigma = np.full(len(rec), np.nan), np.full(len(rec), np.nan)
    for k in range(len(rec)):
        lost = mode != "none" and lost_at <= k < lost_at + LOST_S
        if not (lost and mode == "skip"):
            i = np.nan if lost else rec.current_a[k]
            est.update(np.array([i]), rec.voltage_v[k:k + 1], temperature_c=rec.temperature_c[k:k + 1])
        soc[k], sigma[k] = est.soc[0], est.soc_sigma[0]
    return est, 100 * soc, 100 * sigma


def _run_lost_nan(rec, ocv, places: tuple[int, ...]):
    """``_run(rec, ocv, place, "nan")`` for each place at once: the places as the cells of one estimator, each
    cell its own current (the estimator is vectorised over cells, a cell's results its solo run's)."""
    k = np.arange(len(rec))
    lost = np.array([(place <= k) & (k < place + LOST_S) for place in places])
    i = np.where(lost, np.nan, rec.current_a)
    est = SocEstimator(len(places), ocv, Q_STATED, 1.0, initial_soc=1.0)
    soc, sigma = np.full(i.shape, np.nan), np.full(i.shape, np.nan)
    for j in range(len(rec)):
        est.update(i[:, j], np.full(len(places), rec.voltage_v[j]), temperature_c=rec.temperature_c[j])
        soc[:, j], sigma[:, j] = est.soc, est.soc_sigma
    return 100 * soc, 100 * sigma


def test_a_lost_current_is_counted_with_its_mean_and_its_uncertainty_told(la92):
    """Five minutes without the current at four places of the drive. Measured on the two shipped LG
    recordings, losses every 20 min (17 places): held, the half hour after a loss was within 0.12-1.21 %
    RMSE, median 0.42 %; skipped (no update while lost, what the service did before), 0.30-3.85 %,
    median 1.02 %; held was worse at three of the 17 (by 0.10-0.27 %)."""
    rec, ocv, ref = la92
    ref = 100 * ref
    held, skipped = [], []
    places = (1200, 3000, 4800, 6600)
    socs, sigmas = _run_lost_nan(rec, ocv, places)
    for lost_at, soc, sigma in zip(places, socs, sigmas):
        end = lost_at + LOST_S
        after = slice(end, end + AFTER_S)
        _, soc_skip, _ = _run(rec, ocv, lost_at, "skip")
        held.append(float(np.sqrt(np.mean((soc[after] - ref[after]) ** 2))))
        skipped.append(float(np.sqrt(np.mean((soc_skip[after] - ref[after]) ** 2))))
        # the uncertainty grew over the loss and says how far off the count is at its end
        assert sigma[end - 1] - sigma[lost_at - 1] > 1.0, (lost_at, sigma[lost_at - 1], sigma[end - 1])
        assert abs(soc[end - 1] - ref[end - 1]) < 1.5 * sigma[end - 1], lost_at
        assert np.isfinite(soc).all() and ((soc >= 0) & (soc <= 100)).all()
    assert max(held) < 1.5, held
    assert np.mean(held) < 0.7 * np.mean(skipped), (held, skipped)


def test_the_lost_periods_count_the_running_mean(la92):
    """During the loss the SOC moves by the running mean's charge, not by nothing."""
    rec, ocv, _ = la92
    lost_at = 2400
    est, soc, _ = _run(rec, ocv, lost_at, "none")
    # the running mean at the loss (time constant current_hold_s = 60 s), from the data itself
    a = 1.0 / SocConfig().current_hold_s
    mean = 0.0
    for i in rec.current_a[:lost_at]:
        mean += a * (i - mean)
    est_lost, soc_lost, _ = _run(rec, ocv, lost_at, "nan", SocConfig(soc_method="c0"))
    moved = soc_lost[lost_at + LOST_S - 1] - soc_lost[lost_at]
    q = est_lost.counting_capacity_ah[0]
    expect = 100 * mean * (LOST_S - 1) / 3600.0 / q
    assert mean < -0.5  # la92 here: discharging on average
    assert moved == pytest.approx(expect, rel=0.02), (moved, expect)


def test_a_state_saved_during_a_loss_resumes_it_exactly(la92):
    rec, ocv, _ = la92
    lost = np.zeros(len(rec), dtype=bool)
    lost[1000:1300] = True
    i = np.where(lost, np.nan, rec.current_a)

    def make():
        return SocEstimator(1, ocv, Q_STATED, 1.0, initial_soc=np.array([1.0]))

    a = make()
    for k in range(1400):
        if k == 1150:
            b = make()
            b.load_state_dict(a.state_dict())
        a.update(i[k:k + 1], rec.voltage_v[k:k + 1], temperature_c=rec.temperature_c[k:k + 1])
        if k >= 1150:
            b.update(i[k:k + 1], rec.voltage_v[k:k + 1], temperature_c=rec.temperature_c[k:k + 1])
    assert a.soc[0] == b.soc[0] and a.soc_sigma[0] == b.soc_sigma[0]

    # a state saved before the running mean existed still loads (held from its last current)
    old = {k: v for k, v in a.state_dict().items() if k != "i_hold"}
    c = make()
    c.load_state_dict(old)
    c.update(np.array([np.nan]), rec.voltage_v[1400:1401])
    assert np.isfinite(c.soc).all()
