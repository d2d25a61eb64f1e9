"""The per-sample SOP fast path against a straightforward reference, and the SOX cadence.

Reference: every cell, horizon and direction on its own, the root of
``v(D, I) = bound`` found by bracketing (scipy's brentq to 1e-12 A) on
:func:`predict_voltage`, then the SOC room and the derated design limit.  The fast
path (one stacked Newton step and the overshoot step-back) must never be above that
root (the predicted voltage at the limit never passes the bound) and must be within
``TOL_REL`` (0.1 %) below it; the power is the limit current times the predicted voltage there.
"""

import numpy as np
import pytest
from scipy.optimize import brentq

from bms_estimator.core.ocv import OcvCurve
from bms_estimator.core.ocv_surface import OcvAtTemperatures, OcvSurface
from bms_estimator.core.sop import SopConfig, derate, pack_limits, predict_voltage, sop_and_pack_limits, sop_limits

TOL_REL = 1e-3  # the fast path's limit within 0.1 % below the exact root (1 Newton step; 0.03 % seen)


def _surface() -> OcvSurface:
    soc = np.linspace(0, 1, 101)
    curves = [OcvCurve(soc, 3.0 + 1.2 * soc - 0.15 * np.sin(3 * soc) + 0.03 * k - 0.2 * np.exp(-20 * soc))
              for k in range(3)]
    return OcvSurface(curves, [-10.0, 0.0, 25.0])


def _pack(n: int, seed: int):
    rng = np.random.default_rng(seed)
    t = rng.uniform(-15.0, 40.0, n)
    soc = rng.uniform(0.03, 0.97, n)
    q = rng.uniform(2.5, 3.1, n)
    r0 = rng.uniform(0.01, 0.08, n)
    r_rc = rng.uniform(0.0, 0.04, (n, 2))
    tau = np.column_stack([rng.uniform(2, 20, n), rng.uniform(50, 400, n)])
    x = rng.uniform(-0.05, 0.03, (n, 2))
    i_now = rng.uniform(-10, 4, n)
    f = OcvAtTemperatures(_surface(), t)
    v = f.ocv(soc) + r0 * i_now + x.sum(axis=1) + rng.normal(0, 0.01, n)  # + what the model does not explain
    margin = rng.uniform(0.0, 0.05, (3, n))
    return dict(voltage_v=v, current_now_a=i_now, soc=soc, capacity_ah=q, temperature_c=t, r0_ohm=r0, r_ohm=r_rc,
                tau_s=tau, x_v=x), f, margin


def _reference(kw, f, margin, cfg: SopConfig):
    """(discharge, charge) limits (H, N) and their powers, each cell and horizon solved on its own."""
    n = len(kw["soc"])
    out = np.zeros((4, len(cfg.horizons_s), n))
    d_dis = cfg.i_discharge_max_a * derate(kw["temperature_c"], cfg.derate_temperatures_c, cfg.discharge_derate)
    d_chg = cfg.i_charge_max_a * derate(kw["temperature_c"], cfg.derate_temperatures_c, cfg.charge_derate)
    for c in range(n):
        one = {k: np.atleast_1d(np.asarray(a)[c]) for k, a in kw.items() if k != "temperature_c"}
        one["r_ohm"], one["tau_s"], one["x_v"] = (np.asarray(kw[k])[c:c + 1] for k in ("r_ohm", "tau_s", "x_v"))
        f1 = OcvAtTemperatures(_surface(), np.array([kw["temperature_c"][c]]))
        for h, d in enumerate(cfg.horizons_s):
            def v_of(i):
                return float(predict_voltage(np.array([i]), d, ocv=f1.ocv, **one)[0])
            per_a = d / (3600.0 * kw["capacity_ah"][c])
            for row, (sign, bound, cap) in enumerate(((-1, cfg.v_min + margin[h, c], d_dis[c]),
                                                      (1, cfg.v_max - margin[h, c], d_chg[c]))):
                room = (kw["soc"][c] - cfg.soc_min if sign < 0 else cfg.soc_max - kw["soc"][c]) / per_a
                cap = min(cap, max(room, 0.0))
                g = lambda i: sign * (v_of(sign * i) - bound)  # noqa: E731  increasing in i
                if g(0.0) >= 0.0:
                    lim = 0.0
                elif g(cap) <= 0.0:
                    lim = cap
                else:
                    lim = brentq(g, 0.0, cap, xtol=1e-12)
                out[row, h, c] = lim
                out[2 + row, h, c] = lim * v_of(sign * lim) if lim > 0 else 0.0
    return out


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_fast_path_gives_the_reference_limits(seed):
    cfg = SopConfig()
    kw, f, margin = _pack(60, seed)
    ref = _reference(kw, f, margin, cfg)
    res = sop_limits(ocv=f.ocv, docv_dsoc=f.slope, ocv_slope=f.ocv_slope, config=cfg, v_margin=margin, **kw)
    for fast, exact in ((res.discharge_a, ref[0]), (res.charge_a, ref[1])):
        assert np.all(fast <= exact + 1e-9)  # never past the bound
        assert np.all(fast >= exact * (1.0 - TOL_REL) - 1e-9), np.max((exact - fast) / np.maximum(exact, 1e-9))
    # the power: the limit current times the predicted voltage there (the bound, to the Newton residual)
    np.testing.assert_allclose(res.discharge_w, ref[2], rtol=1e-3, atol=1e-2)
    np.testing.assert_allclose(res.charge_w, ref[3], rtol=1e-3, atol=1e-2)
    # some limits are the root, some the caps: both paths are exercised
    at_root = (ref[0] > 0) & (ref[0] < 20.0 * derate(kw["temperature_c"], cfg.derate_temperatures_c,
                                                       cfg.discharge_derate) - 1e-6)
    assert 0 < np.count_nonzero(at_root) < at_root.size


def test_fused_pack_pass_equals_the_two_calls():
    cfg = SopConfig()
    kw, f, margin = _pack(40, 5)
    kw["voltage_v"][3] = np.nan  # a cell without a reading: left out of the pack
    valid = np.isfinite(kw["voltage_v"])
    res, pack = sop_and_pack_limits(ocv=f.ocv, docv_dsoc=f.slope, ocv_slope=f.ocv_slope, config=cfg,
                                    v_margin=margin, n_parallel=2, valid=valid, **kw)
    res2 = sop_limits(ocv=f.ocv, docv_dsoc=f.slope, config=cfg, v_margin=margin, **kw)
    for a in ("discharge_a", "charge_a", "discharge_w", "charge_w"):
        np.testing.assert_array_equal(getattr(res, a), getattr(res2, a))
    model = {k: v for k, v in kw.items() if k != "temperature_c"}
    pack2 = pack_limits(res2, ocv=f.ocv, n_parallel=2, valid=valid, **model)
    for a in pack2:
        np.testing.assert_allclose(pack[a], pack2[a], rtol=1e-12)
    assert pack["discharge_a"][0] == 2 * np.min(res.discharge_a[0, valid]) > 0


def test_ocv_at_temperatures_is_the_surface_itself():
    s = _surface()
    rng = np.random.default_rng(3)
    t = rng.uniform(-20.0, 45.0, 50)
    t[4] = np.nan  # reads the default temperature
    f = OcvAtTemperatures(s, t)
    z = rng.uniform(-0.1, 1.1, (7, 50))  # inside and beyond the tables
    z[2, 7] = np.nan
    v, d = f.ocv_slope(z)
    tt = np.broadcast_to(t, z.shape)
    np.testing.assert_array_equal(v, s.ocv(z, tt))
    np.testing.assert_array_equal(d, s.docv_dsoc(z, tt))
    np.testing.assert_array_equal(f.ocv(z), v)
    assert np.isnan(v[2, 7]) and np.isnan(d[2, 7])
    one = OcvAtTemperatures(s.curves[0], t)  # one table: the temperature is ignored
    np.testing.assert_array_equal(one.ocv(z[:, :3]), s.curves[0].ocv(z[:, :3]))


def test_energy_left_and_capacity_soh_refresh_every_slow_period_the_sop_every_sample(nmc_like_ocv):
    from bms_estimator.core.ecm import EcmParams, simulate_ecm
    from bms_estimator.core.soc import SocEstimator
    from bms_estimator.core.soe import energy_left_wh
    from bms_estimator.core.sox import SoxConfig, SoxEstimator

    i = np.full(400, -3.0)
    i[::50] = 0.0
    sim = simulate_ecm(i, 1.0, EcmParams.from_rc(0.03, [0.01, 0.02], [8.0, 150.0]), nmc_like_ocv.ocv, soc0=0.9,
                       capacity_ah=3.0)
    est = SocEstimator(1, nmc_like_ocv, 3.0, 1.0, initial_soc=0.9)
    sox = SoxEstimator(1, 1.0, SoxConfig(slow_period_s=10.0))
    e_left, i_lim, fresh = [], [], []
    for k in range(len(i)):
        est.update(i[k], sim.voltage_v[k:k + 1])
        sox.update(est, i[k], sim.voltage_v[k:k + 1])
        e_left.append(sox.outputs["energy_left_wh"][0])
        i_lim.append(sox.outputs["p_discharge_max_10s_w"][0])
        if k % 10 == 0:  # a refresh: the energy left of the state now
            kw = sox.model(est)
            cfg = sox.config
            fresh.append(energy_left_wh(kw["soc"], kw["capacity_ah"], kw["r0_ohm"] + kw["r_ohm"].sum(axis=1),
                                        SoxEstimator.ocv_at(est).ocv, v_min=cfg.sop.v_min, config=cfg.soe)[0][0])
    e_left = np.asarray(e_left)
    np.testing.assert_allclose(e_left[::10], fresh, rtol=1e-12)
    held = e_left.reshape(-1, 10)
    assert np.all(held == held[:, :1])  # held for the 9 samples in between
    assert np.all(np.diff(e_left[::10][5:]) < 0)  # and falling as the cell discharges
    assert np.count_nonzero(np.diff(i_lim)) > 300  # the SOP (here the 20 A-capped power) moves every sample


def test_per_sample_update_equals_track_then_compute():
    """SoxEstimator.update (the estimator read once, the OCV at the SOC now and at the next
    period's start in one lookup, masked updates skipped while every cell is valid) gives
    exactly what track() then compute() give, each reading the estimator on its own: over a
    discharge with per-cell temperatures across the OCV tables and cells losing their reading."""
    from bms_estimator.core.soc import SocEstimator
    from bms_estimator.core.sox import SoxEstimator

    n, steps = 12, 160
    rng = np.random.default_rng(7)
    temps = np.linspace(-15.0, 40.0, n)
    est = SocEstimator(n, _surface(), 3.0, 1.0, initial_soc=0.9)
    fast, plain = SoxEstimator(n, 1.0), SoxEstimator(n, 1.0)
    compared = 0
    for k in range(steps):
        i = -3.0 if (k // 20) % 2 else 0.5
        v = 3.6 + 0.02 * i + 0.002 * rng.standard_normal(n)
        if k % 17 == 5:
            v[rng.integers(0, n, 2)] = np.nan  # no reading from two cells this sample
        t = temps + 2.0 * np.sin(k / 15.0)
        est.update(i, v, temperature_c=t)
        fast.update(est, i, v)
        plain.track(est, i, v)
        plain.compute(est)
        assert fast.outputs.keys() == plain.outputs.keys()
        for key in fast.outputs:
            np.testing.assert_array_equal(fast.outputs[key], plain.outputs[key], err_msg=f"{key} at sample {k}")
        pf, pp = fast.pack_outputs(), plain.pack_outputs()
        assert pf.keys() == pp.keys()
        np.testing.assert_array_equal(list(pf.values()), list(pp.values()))  # NaN (no SOH yet) equals NaN
        compared += 1
    assert compared == steps
    assert np.any(fast.outputs["i_discharge_max_10s_a"] > 0)  # limits that were actually computed
