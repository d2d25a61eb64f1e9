"""State of energy and state of health: known answers and the SOX tracker on a simulated cell."""

import numpy as np
import pytest

from bms_estimator.core.ecm import EcmParams, simulate_ecm
from bms_estimator.core.soc import SocEstimator
from bms_estimator.core.soe import SoeConfig, energy_left_wh, time_to_empty_s, time_to_full_s
from bms_estimator.core.soh import ResistanceSoh, SohConfig, capacity_soh, r0_at_reference
from bms_estimator.core.sop import SopConfig
from bms_estimator.core.sox import SoxConfig, SoxEstimator


def _linear_ocv(s):
    return 3.0 + 1.2 * np.asarray(s)


def test_energy_left_is_the_integral_of_the_loaded_voltage_down_to_the_cut_off():
    # OCV = 3 + 1.2 z, R_ss = 0.05 ohm, Q = 3 Ah, rate 1C -> v(z) = 2.85 + 1.2 z; v_min = 3.0 -> z_cut = 0.125
    s = np.array([0.9, 0.5, 0.1])
    e, z_cut = energy_left_wh(s, 3.0, 0.05, _linear_ocv, v_min=3.0, config=SoeConfig(rate_c=1.0, n_points=21))
    exact = 3.0 * np.array([(2.85 * z + 0.6 * z**2) for z in s]) - 3.0 * (2.85 * 0.125 + 0.6 * 0.125**2)
    np.testing.assert_allclose(e[:2], exact[:2], rtol=1e-9)
    np.testing.assert_allclose(z_cut[:2], 0.125, atol=1e-12)
    assert e[2] == 0.0  # below the cut-off already
    # the OCV energy (rate 0) of a full cell: Q * integral_0^1 OCV = 3 * 3.6 Wh
    e0, _ = energy_left_wh(np.array([1.0]), 3.0, 0.05, _linear_ocv, v_min=2.0, config=SoeConfig(rate_c=0.0))
    np.testing.assert_allclose(e0, 10.8, rtol=1e-12)
    bad, _ = energy_left_wh(np.array([np.nan]), 3.0, 0.05, _linear_ocv, v_min=3.0)
    assert np.isnan(bad[0])


def test_time_to_empty_and_full():
    q = np.array([3.0, 3.0, 3.0])
    tte = time_to_empty_s(np.array([0.5, 0.5, 0.5]), np.array([0.1, 0.1, 0.1]), q, np.array([-3.0, 0.0, 1.5]))
    np.testing.assert_allclose(tte[0], 0.4 * 3600)  # 1.2 Ah at 3 A
    assert np.isinf(tte[1]) and np.isinf(tte[2])
    ttf = time_to_full_s(np.array([0.5, 0.5]), q[:2], np.array([1.5, -1.0]))
    np.testing.assert_allclose(ttf[0], 3600.0)
    assert np.isinf(ttf[1])


def test_capacity_soh_only_once_justified():
    soh, sig = capacity_soh(np.array([2.6, 2.6]), 2.9, np.array([0.05, 0.05]), np.array([True, False]))
    np.testing.assert_allclose(soh[0], 2.6 / 2.9)
    np.testing.assert_allclose(sig[0], 0.05 / 2.9)
    assert np.isnan(soh[1]) and np.isnan(sig[1])


def test_resistance_soh_separates_temperature_from_ageing():
    cfg = SohConfig(r0_activation_k=3000.0, commissioning_samples=10, smoothing_s=5.0)
    r_ref = 0.02

    def r0_at(t_c, ageing=1.0):  # the Arrhenius law the reference is taken with
        return ageing * r_ref * np.exp(3000.0 * (1 / (t_c + 273.15) - 1 / 298.15))

    np.testing.assert_allclose(r0_at_reference(r0_at(np.array([-10.0, 0.0, 40.0])), [-10.0, 0.0, 40.0], cfg), r_ref)
    soh = ResistanceSoh(2, 1.0, cfg)
    for _ in range(20):  # commissioning at 25 degC
        soh.update(np.array([r_ref, r_ref]), 25.0, np.array([0.5, 0.5]), np.array([True, True]))
    np.testing.assert_allclose(soh.r0_commissioning_ohm, r_ref)
    for _ in range(100):  # cell 0 cold but new, cell 1 warm and aged 30 %
        soh.update(np.array([r0_at(-5.0), r0_at(25.0, 1.3)]), np.array([-5.0, 25.0]), np.array([0.5, 0.5]),
                   np.array([True, True]))
    np.testing.assert_allclose(soh.ratio, [1.0, 1.3], rtol=1e-3)
    # outside the SOC band nothing is taken
    before = soh.r0_ref_ohm.copy()
    soh.update(np.array([1.0, 1.0]), 25.0, np.array([0.05, 0.95]), np.array([True, True]))
    np.testing.assert_array_equal(soh.r0_ref_ohm, before)
    # the commissioning value survives a state round trip, a wrong shape is refused
    other = ResistanceSoh(2, 1.0, cfg)
    other.load_state_dict(soh.state_dict())
    np.testing.assert_array_equal(other.r0_commissioning_ohm, soh.r0_commissioning_ohm)
    with pytest.raises(ValueError, match="r0_ref_ohm"):
        ResistanceSoh(3, 1.0, cfg).load_state_dict(soh.state_dict())


def test_sox_tracker_on_a_simulated_discharge(nmc_like_ocv):
    """A known ECM discharged at 1C: the energy counters add up v*i, the RC voltages follow the
    simulation once identified, and every output is finite where it should be."""
    n_s = 1800
    p = EcmParams.from_rc(0.03, [0.01, 0.02], [8.0, 150.0])
    i = np.full(n_s, -3.0)
    i[::120] = 0.0  # some variation for the identifier
    sim = simulate_ecm(i, 1.0, p, nmc_like_ocv.ocv, soc0=0.95, capacity_ah=3.0)
    est = SocEstimator(1, nmc_like_ocv, 3.0, 1.0, initial_soc=0.95)
    sox = SoxEstimator(1, 1.0)
    for k in range(n_s):
        est.update(i[k], sim.voltage_v[k:k + 1])
        sox.update(est, i[k], sim.voltage_v[k:k + 1])
    out = sox.outputs
    np.testing.assert_allclose(out["energy_discharged_wh"][0], -np.sum(i * sim.voltage_v) / 3600.0, rtol=1e-12)
    np.testing.assert_allclose(out["energy_delivered_wh"][0], out["energy_discharged_wh"][0], rtol=1e-12)
    for key in ("i_discharge_max_10s_a", "p_discharge_max_10s_w", "energy_left_wh", "time_to_empty_s"):
        assert np.isfinite(out[key][0]) and out[key][0] > 0, key
    assert np.isinf(out["time_to_full_s"][0])
    # energy left at 0.5C against the exact ECM discharged from here to v_min
    soc_now = float(est.soc[0])
    assert abs(soc_now - sim.soc[-1]) < 0.02
    pack = sox.pack_outputs()
    assert pack["i_discharge_max_10s_a"] == out["i_discharge_max_10s_a"][0]
    st = sox.state_dict()
    again = SoxEstimator(1, 1.0)
    again.load_state_dict(st)
    np.testing.assert_array_equal(again.energy_discharged_wh, sox.energy_discharged_wh)


def test_energy_left_matches_a_simulated_discharge_to_v_min(nmc_like_ocv):
    r0, r = 0.03, [0.01, 0.02]
    q, rate = 3.0, 0.5
    soc0 = 0.8
    i = -rate * q
    n = 3600 * 3
    sim = simulate_ecm(np.full(n, i), 1.0, EcmParams.from_rc(r0, r, [8.0, 150.0]), nmc_like_ocv.ocv, soc0=soc0,
                       capacity_ah=q)
    stop = int(np.argmax(sim.voltage_v < 3.2)) if np.any(sim.voltage_v < 3.2) else n
    e_true = -np.sum(i * sim.voltage_v[:stop]) / 3600.0
    e, _ = energy_left_wh(np.array([soc0]), q, r0 + sum(r), nmc_like_ocv.ocv, v_min=3.2,
                          config=SoeConfig(rate_c=rate))
    # the steady-state resistance overstates the drop while the slow pair charges up: within 1 %
    assert abs(e[0] - e_true) / e_true < 0.01


def test_energy_left_refuses_a_non_positive_capacity():
    """A capacity of 0 or below is no cell's: NaN, not an energy of 0 or below."""
    e, z_cut = energy_left_wh(np.array([0.5, 0.5, 0.5]), np.array([3.0, 0.0, -3.0]), 0.05, _linear_ocv, v_min=3.0)
    assert np.isfinite(e[0]) and np.isnan(e[1:]).all() and np.isnan(z_cut[1:]).all()


def test_times_idle_below_a_c_rate_and_never_negative():
    """The idle threshold is ``idle_current_c * Q`` (a C-rate: 1 A on a 100 Ah cell at 0.01 C);
    a SOC already past the end gives 0 s, not a negative time."""
    q = np.array([100.0, 100.0])
    tte = time_to_empty_s(np.array([0.5, 0.5]), np.array([0.1, 0.1]), q, np.array([-0.5, -2.0]))
    assert np.isinf(tte[0])  # 0.5 A < 1 A: idle
    np.testing.assert_allclose(tte[1], 3600.0 * 100.0 * 0.4 / 2.0)
    ttf = time_to_full_s(np.array([0.5, 0.5]), q, np.array([0.5, 2.0]))
    assert np.isinf(ttf[0])
    np.testing.assert_allclose(ttf[1], 3600.0 * 100.0 * 0.5 / 2.0)
    assert time_to_empty_s(0.05, 0.1, 3.0, -3.0) == 0.0  # below the cut-off already
    assert time_to_full_s(1.0, 3.0, 3.0, soc_max=0.95) == 0.0


def test_resistance_soh_commissioning_count_smoothing_and_band_edges():
    """R0_c is the mean of exactly the first ``commissioning_samples`` counted samples (each reading
    weighted by the samples it stands for); R0_ref starts at the first reading and then follows
    R0_ref += (1 - exp(-dt/tau)) (R0 - R0_ref); the band ends count, R0 <= 0 and a temperature no cell
    has do not; a state saved mid-commissioning continues it."""
    cfg = SohConfig(commissioning_samples=4, smoothing_s=10.0, soc_lo=0.3, soc_hi=0.8)
    a = 1.0 - np.exp(-1.0 / 10.0)
    soh = ResistanceSoh(2, 1.0, cfg)
    on = np.array([True, True])
    for k, r in enumerate([1.0, 2.0, 3.0]):  # at 25 degC (the reference): R0_ref = R0
        soh.update(np.array([r, r]), 25.0, np.array([0.3, 0.8]), on)  # both band ends count
        if k == 0:
            np.testing.assert_array_equal(soh.r0_ref_ohm, [1.0, 1.0])
    np.testing.assert_allclose(soh.r0_ref_ohm, (1.0 + a * 1.0) + a * (3.0 - (1.0 + a * 1.0)), rtol=1e-12)
    soh.update(np.array([-1.0, 0.0]), 25.0, np.array([0.5, 0.5]), on)  # R0 <= 0: not taken
    assert np.isnan(soh.r0_commissioning_ohm).all()
    resumed = ResistanceSoh(2, 1.0, cfg)
    resumed.load_state_dict(soh.state_dict())
    for s in (soh, resumed):
        s.update(np.array([4.0, 4.0]), 25.0, np.array([0.5, 0.5]), on)
        s.update(np.array([100.0, 100.0]), 25.0, np.array([0.5, 0.5]), on)  # after commissioning: held
        np.testing.assert_allclose(s.r0_commissioning_ohm, 2.5, rtol=1e-12)  # (1 + 2 + 3 + 4) / 4
    two = ResistanceSoh(1, 2.0, cfg)  # readings every 2nd sample: each counts twice
    for r in (1.0, 3.0, 50.0):
        two.update(np.array([r]), 25.0, np.array([0.5]), np.array([True]), samples=2)
    np.testing.assert_allclose(two.r0_commissioning_ohm, 2.0, rtol=1e-12)
    assert np.isnan(r0_at_reference(0.02, 500.0, cfg))  # no cell's temperature (a sensor fault)


def test_sox_counts_discharge_and_charge_apart_and_anchors_the_sop_a_period_on(nmc_like_ocv):
    """E_dis sums -v i Ts / 3600 over discharge samples only, E_chg v i Ts / 3600 over charge samples only;
    the SOP's SOC anchor is the SOC at the next period's start, s + i Ts / (3600 Q)."""
    p = EcmParams.from_rc(0.03, [0.01, 0.02], [8.0, 150.0])
    i = np.concatenate([np.full(300, 3.0), np.full(300, -3.0)])
    sim = simulate_ecm(i, 1.0, p, nmc_like_ocv.ocv, soc0=0.5, capacity_ah=3.0)
    est = SocEstimator(1, nmc_like_ocv, 3.0, 1.0, initial_soc=0.5)
    sox = SoxEstimator(1, 1.0)
    for k in range(i.size):
        est.update(i[k], sim.voltage_v[k:k + 1])
        sox.update(est, i[k], sim.voltage_v[k:k + 1])
        if k in (10, 400):
            step = sox.soc_anchor[0] - est.soc[0]
            np.testing.assert_allclose(step, i[k] / (3600.0 * est.capacity_ah[0]), rtol=1e-9)
    e = i * sim.voltage_v / 3600.0
    np.testing.assert_allclose(sox.energy_discharged_wh[0], -e[i < 0].sum(), rtol=1e-12)
    np.testing.assert_allclose(sox.energy_charged_wh[0], e[i > 0].sum(), rtol=1e-12)


def test_sox_pack_figures_take_the_weakest_cell_and_the_slowest_to_fill(nmc_like_ocv):
    """A series string ends its discharge with its weakest cell: the pack's energy left is that cell's
    times the cells (times n_parallel), not the cells' sum; it is full when its slowest cell is."""
    est = SocEstimator(2, nmc_like_ocv, 3.0, 1.0, initial_soc=np.array([0.3, 0.6]))
    sox = SoxEstimator(2, 1.0)
    v = nmc_like_ocv.ocv(np.array([0.3, 0.6]))
    for _ in range(30):
        est.update(1.5, v)
        sox.update(est, 1.5, v)
    out, pack = sox.outputs, sox.pack_outputs()
    assert out["energy_left_wh"][0] < out["energy_left_wh"][1]
    assert pack["energy_left_wh"] == pytest.approx(2 * out["energy_left_wh"][0], rel=1e-12)
    assert out["time_to_full_s"][0] > out["time_to_full_s"][1]
    assert pack["time_to_full_s"] == out["time_to_full_s"][0]
    out["soh_resistance"] = np.array([1.1, 1.3])  # (two cells' ageing, as the slow outputs hold it)
    assert sox.pack_outputs()["soh_resistance_max"] == 1.3  # the most aged cell
    again = SoxEstimator(2, 1.0)
    again.load_state_dict(sox.state_dict())  # the energy charged is kept across a restart
    np.testing.assert_array_equal(again.energy_charged_wh, sox.energy_charged_wh)
    assert np.all(sox.energy_charged_wh > 0)
    two = SoxEstimator(2, 1.0, SoxConfig(sop=SopConfig(n_parallel=2)))
    assert two.pack_energy_wh([1.0, 2.0]) == 6.0  # every cell stands for its n_parallel equal cells


def test_the_net_energy_delivered_restarts_at_full_soc_itself(nmc_like_ocv):
    """``energy_delivered_wh`` restarts while the cell is at or above ``full_soc`` (a charge to full ends a
    trip's count) and counts below it: at exactly ``full_soc`` it is 0, a hair below it is the period's energy."""
    est = SocEstimator(1, nmc_like_ocv, 3.0, 1.0, initial_soc=0.995)
    i, v = -1.5, np.array([float(nmc_like_ocv.ocv(0.995)) - 0.05])
    est.update(i, v)
    soc = float(est.soc[0])
    at = SoxEstimator(1, 1.0, SoxConfig(full_soc=soc))
    at.update(est, i, v)
    below = SoxEstimator(1, 1.0, SoxConfig(full_soc=float(np.nextafter(soc, 2.0))))
    below.update(est, i, v)
    assert at.outputs["energy_delivered_wh"][0] == 0.0
    np.testing.assert_allclose(below.outputs["energy_delivered_wh"][0], -i * v[0] / 3600.0, rtol=1e-12)
