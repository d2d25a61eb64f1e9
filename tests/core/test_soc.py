"""SOC: c0 compensation from a wrong start and capacity estimation, on a synthetic cell."""

import numpy as np
import pytest

from bms_estimator.analysis import reference_soc, run_soc, soc_errors
from bms_estimator.core.ecm import EcmParams, simulate_ecm
from bms_estimator.core.ocv import OcvCurve
from bms_estimator.core.soc import VOLTAGE_LINE_RATIO_MAX, SocConfig, SocEstimator
from tests.conftest import pulse_current


def _drive_cycle(n: int, seed: int) -> np.ndarray:
    """Discharge-heavy pulses with regen, about 0.9 of a 3 Ah cell in n seconds."""
    i = pulse_current(n, seed, amp_a=4.0)
    return i - (i.mean() + 0.9 * 3.0 * 3600 / n)


def _cell(n, seed, nmc_like_ocv, q_true=3.0):
    i = _drive_cycle(n, seed)
    p = EcmParams.from_rc(0.02, [0.01, 0.015], [10.0, 200.0])
    sim = simulate_ecm(i, 1.0, p, nmc_like_ocv.ocv, soc0=1.0, capacity_ah=q_true, output="mean")
    rng = np.random.default_rng(seed)
    return i, sim.voltage_v + 5e-4 * rng.standard_normal(n)


def test_compensation_removes_a_20pct_initial_error(nmc_like_ocv):
    n = 3 * 3600
    i, v = _cell(n, 1, nmc_like_ocv)
    run = run_soc(i, v, nmc_like_ocv, 3.0, initial_soc=0.8, config=SocConfig(soc_method="c0", estimate_capacity=False))
    ref = reference_soc(i, 1.0, 3.0, 1.0)
    err = soc_errors(run.soc, ref, np.arange(n))
    assert run.corrections >= 1
    assert err["soc_rmse_pct_after_3600s"] < 1.5, err
    # without compensation the 20 % error would simply stay
    assert err["soc_rmse_pct"] < 10



def test_compensation_removes_a_20pct_initial_error_from_above(nmc_like_ocv):
    """Step 5 compares ``|c0_avg|``: a start too high (c0 < 0, the voltage below what the SOC implies) is
    corrected as a start too low is: a 3 h drive from a true 70 % read from 90 %."""
    n = 3 * 3600
    i = 0.5 * _drive_cycle(n, 1)  # 45 % of 3 Ah in 3 h: 70 % -> 25 %
    p = EcmParams.from_rc(0.02, [0.01, 0.015], [10.0, 200.0])
    v = simulate_ecm(i, 1.0, p, nmc_like_ocv.ocv, soc0=0.7, capacity_ah=3.0, output="mean").voltage_v
    v = v + 5e-4 * np.random.default_rng(1).standard_normal(n)
    run = run_soc(i, v, nmc_like_ocv, 3.0, initial_soc=0.9, config=SocConfig(soc_method="c0", estimate_capacity=False))
    ref = reference_soc(i, 1.0, 3.0, 0.7)
    err = soc_errors(run.soc, ref, np.arange(n))
    assert run.corrections >= 1
    assert err["soc_rmse_pct_after_3600s"] < 1.5, err

CAPACITY_SEEDS = (2, 3, 4, 5, 6, 7)  # six drive cycles, not one that happens to work


def _capacity_runs(updates: tuple[str, ...]) -> dict[str, dict]:
    """A 2.7 Ah cell stated as 3.0 Ah, discharged to empty, per ``capacity_soc_update`` mode:
    {mode: {seed: (estimated capacity, last-hour SOC RMSE, the same trusting 3.0 Ah)}}.
    The six drive cycles run as six cells of one estimator (each cell its own current: the estimator is
    vectorised over cells and a cell's results are its solo run's, tests/fleet/test_fleet_stack.py), one
    run per setting instead of one per setting and seed; the trusting run does not depend on the mode."""
    ocv = _nmc_like_ocv()  # the conftest fixture's curve (that one is function-scoped)
    n = 3 * 3600
    cells = [_cell(n, seed, ocv, q_true=2.7) for seed in CAPACITY_SEEDS]
    i, v = (np.array(x) for x in zip(*cells))  # (seeds, samples)
    ref = np.array([reference_soc(c, 1.0, 2.7, 1.0) for c in i])

    def run(config):
        est = SocEstimator(len(CAPACITY_SEEDS), ocv, 3.0, 1.0, initial_soc=1.0, config=config)
        soc = np.empty_like(v)
        for k in range(n):
            est.update(i[:, k], v[:, k])
            soc[:, k] = est.soc
        last_hour = 100.0 * (soc[:, n - 3600:] - ref[:, n - 3600:])
        return est.capacity_ah.copy(), np.sqrt(np.mean(last_hour**2, axis=1))

    _, trusting = run(SocConfig(soc_method="c0", estimate_capacity=False))
    out: dict[str, dict] = {}
    for mode in updates:
        q, err = run(SocConfig(soc_method="c0", capacity_soc_update=mode))
        out[mode] = {seed: (q[j], err[j], trusting[j]) for j, seed in enumerate(CAPACITY_SEEDS)}
    return out


@pytest.fixture(scope="module")
def capacity_modes():
    return _capacity_runs((SocConfig(soc_method="c0").capacity_soc_update, "line"))


@pytest.fixture(scope="module")
def capacity_runs(capacity_modes):
    return capacity_modes[SocConfig(soc_method="c0").capacity_soc_update]


def _nmc_like_ocv():
    soc = np.linspace(0.0, 1.0, 201)
    return OcvCurve(soc, 3.0 + 0.75 * soc + 0.45 * soc**2 - 0.25 * np.exp(-25 * soc) + 0.05 * np.sin(4 * soc))


def test_capacity_estimate_moves_towards_the_cells_and_helps_the_soc(capacity_runs):
    """The stated 3.0 Ah is not trusted: on every drive cycle the estimate goes at least half-way
    to 2.7 Ah, typically to within 0.1 Ah, and the last hour's SOC is typically better for it."""
    q, err, err_trusting = (np.array(x) for x in zip(*capacity_runs.values()))
    assert np.all(q < 2.85), q
    assert np.median(np.abs(q - 2.7)) < 0.1, q
    assert np.sum(err < err_trusting + 0.1) >= len(q) - 1, (err, err_trusting)
    assert np.median(err) < 0.85 * np.median(err_trusting), (err, err_trusting)


def test_capacity_line_option_moves_the_soc_to_the_anchor_line(capacity_modes):
    """capacity_soc_update="line": on a 10 % capacity error the SOC gains most (the line also
    carries each anchor's OCV-model error, which is why it is not the default on measured cells)."""
    q, err, err_trusting = (np.array(x) for x in zip(*capacity_modes["line"].values()))
    assert np.all(q < 2.96), q
    assert np.all(err < err_trusting + 0.1), (err, err_trusting)
    assert np.median(err) < 2.0 and np.median(err) < 0.6 * np.median(err_trusting), (err, err_trusting)


@pytest.mark.xfail(strict=True, reason=(
    "known limitation: a capacity error makes the OCV error an integral of the current, which the "
    "slow RC branch partly absorbs (it is an integrator for t << tau2, and R2 grows towards the "
    "tau bound), so c0 shows only part of the SOC error and the compensation fires late"))
def test_soc_within_2pct_in_the_last_hour_despite_a_10pct_capacity_error(capacity_runs):
    for seed, (_, err, _) in capacity_runs.items():
        assert err < 2.0, (seed, err)


def test_recount_option_counts_again_from_the_last_correction_with_the_new_capacity(nmc_like_ocv):
    i, v = _cell(3 * 3600, 5, nmc_like_ocv, q_true=2.7)
    est = SocEstimator(1, nmc_like_ocv, 3.0, initial_soc=1.0, config=SocConfig(soc_method="c0", capacity_soc_update="recount"))
    moved = 0
    for k in range(len(i)):
        q_before = est.capacity_ah.copy()
        est.update(i[k], v[k : k + 1])
        if est.capacity_ah[0] != q_before[0] and est.corrections[0] >= 1:
            expect = np.clip(est._soc_fix + (est.charge_ah - est._q_fix) / est.capacity_ah, 0, 1)
            if abs(expect[0] - est.soc[0]) < 1e-12:
                moved += 1
            else:  # not moved: the recount was within reanchor_min_soc of the count
                assert abs(expect[0] - est.soc[0]) <= est.config.reanchor_min_soc
    assert est.capacity_estimated[0] and moved >= 1


def test_a_state_saved_without_hysteresis_loads_with_every_other_field_kept(nmc_like_ocv):
    curve = OcvCurve(nmc_like_ocv.soc, nmc_like_ocv.ocv_v, np.full(len(nmc_like_ocv.soc), 0.02))
    i, v = _cell(1500, 3, nmc_like_ocv)
    old = SocEstimator(1, curve, 3.0, initial_soc=0.9, config=SocConfig(soc_method="c0", hysteresis=False))
    for k in range(1500):
        old.update(i[k], v[k : k + 1])
    state = old.state_dict()
    assert not any(k.startswith("hyst.") for k in state)
    new = SocEstimator(1, curve, 3.0)
    assert new._hyst is not None  # the default tracks the branch of a table with hysteresis_v
    new.load_state_dict(state)
    np.testing.assert_array_equal(new.soc, old.soc)
    np.testing.assert_array_equal(new.charge_ah, old.charge_ah)
    # the branch is guessed from the restored SOC, as at a start: mid-range it is unknown (the mean curve)
    assert 0.02 < new.soc[0] < 0.98 and new.hysteresis_state[0] == 0.0
    new.update(-1.0, v[-1:])  # and it runs on
    assert np.isfinite(new.soc[0])


def test_hysteresis_without_a_hysteresis_column_is_the_mean_curve_exactly(nmc_like_ocv):
    i, v = _cell(1800, 4, nmc_like_ocv)
    a = run_soc(i, v, nmc_like_ocv, 3.0, initial_soc=0.8, config=SocConfig(soc_method="c0", hysteresis=True))
    b = run_soc(i, v, nmc_like_ocv, 3.0, initial_soc=0.8, config=SocConfig(soc_method="c0", hysteresis=False))
    np.testing.assert_array_equal(a.soc, b.soc)


def test_state_round_trip_and_shape_errors_are_named(nmc_like_ocv):
    import pytest

    i, v = _cell(2000, 3, nmc_like_ocv)
    a = SocEstimator(1, nmc_like_ocv, 3.0, initial_soc=0.9)
    for k in range(1000):
        a.update(i[k], v[k : k + 1])
    b = SocEstimator(1, nmc_like_ocv, 3.0)
    b.load_state_dict(a.state_dict())
    for k in range(1000, 2000):
        a.update(i[k], v[k : k + 1])
        b.update(i[k], v[k : k + 1])
    np.testing.assert_array_equal(a.soc, b.soc)
    with pytest.raises(ValueError, match="soc"):
        SocEstimator(2, nmc_like_ocv, 3.0).load_state_dict(a.state_dict())


def test_initial_soc_from_ocv_when_not_given(nmc_like_ocv):
    est = SocEstimator(2, nmc_like_ocv, 3.0)
    est.update(0.0, nmc_like_ocv.ocv(np.array([0.3, 0.7])))
    np.testing.assert_allclose(est.soc, [0.3, 0.7], atol=1e-3)


def test_running_c0_statistics_equal_the_window_at_every_sample(nmc_like_ocv):
    """The c0 average the compensation uses is the mean of the window, at every sample, through corrections."""
    n = 3600
    i, v = _cell(n, 4, nmc_like_ocv)
    est = SocEstimator(2, nmc_like_ocv, 3.0, initial_soc=np.array([0.8, 1.0]),
                       config=SocConfig(soc_method="c0", c0_window_s=50))
    for k in range(n):
        est.update(i[k], np.full(2, v[k]))
        np.testing.assert_allclose(est._c0_sum, est._c0_buf.sum(axis=1), atol=1e-12)
        np.testing.assert_allclose(est._c0_sq, (est._c0_buf**2).sum(axis=1), atol=1e-12)
    assert est.corrections[0] >= 1  # the window went through at least one compensation


def test_hysteresis_option_tracks_the_branch_and_survives_a_restart(nmc_like_ocv):
    """The state follows Plett's one-state model (throughput-driven), the OCV the estimator
    reads carries H(soc) times the state, and a restored estimator continues identically."""
    from bms_estimator.core.ocv import OcvCurve

    curve = OcvCurve(nmc_like_ocv.soc, nmc_like_ocv.ocv_v, np.full(len(nmc_like_ocv.soc), 0.03))
    est = SocEstimator(1, curve, 3.0, initial_soc=0.5, config=SocConfig(soc_method="c0", hysteresis=True))
    assert est.hysteresis_state[0] == 0.0  # started mid-range: the branch is unknown, the mean curve
    assert SocEstimator(1, curve, 3.0, initial_soc=1.0).hysteresis_state[0] == 1.0  # full: came off a charge
    assert SocEstimator(1, curve, 3.0, initial_soc=0.0).hysteresis_state[0] == -1.0  # empty: off a discharge
    for _ in range(600):  # 0.5 Ah of charge = 17 % SOC = 5/rate: h = 1 - 2 exp(-5), the charge branch
        est.update(3.0, curve.ocv(est.soc) + 0.03)
    assert est.hysteresis_state[0] > 0.9
    np.testing.assert_allclose(est._ocv(est.soc), curve.ocv(est.soc) + 0.03 * est.hysteresis_state, atol=1e-12)
    est.update(0.0, curve.ocv(est.soc) + 0.03)  # the state at a sample's start: the last charge lands here
    h_charged = est.hysteresis_state[0]
    for _ in range(60):  # a rest does not move it: the state is driven by throughput, not time
        est.update(0.0, curve.ocv(est.soc) + 0.03)
    assert est.hysteresis_state[0] == h_charged
    twin = SocEstimator(1, curve, 3.0, config=SocConfig(soc_method="c0", hysteresis=True))
    twin.load_state_dict(est.state_dict())
    for _ in range(400):  # 11 % SOC discharged = 3.3/rate
        for e in (est, twin):
            e.update(-3.0, curve.ocv(e.soc) - 0.03)
    np.testing.assert_array_equal(twin.hysteresis_state, est.hysteresis_state)
    assert est.hysteresis_state[0] < -0.8  # back on the discharge branch


def test_the_start_branch_is_known_only_at_the_ends(nmc_like_ocv):
    """Class docstring, "Starting hysteresis": a cell started full (SOC >= 0.98) came off a charge (h = +1), one
    started empty (<= 0.02) off a discharge (h = -1); anywhere else, 0.95 and 0.05 included, the mean curve (h = 0)."""
    curve = OcvCurve(nmc_like_ocv.soc, nmc_like_ocv.ocv_v, np.full(len(nmc_like_ocv.soc), 0.03))
    start = np.array([1.0, 0.98, 0.95, 0.5, 0.05, 0.02, 0.0])
    est = SocEstimator(len(start), curve, 3.0, initial_soc=start)
    np.testing.assert_array_equal(est.hysteresis_state, [1, 1, 0, 0, 0, -1, -1])


def test_the_overpotential_is_read_at_the_periods_middle_soc(nmc_like_ocv):
    """Step 2: the voltage is a period mean, so ``v_o = v - OCV(soc + i Ts / 2 / (3600 Q))``: at 1C over a 10 s
    period the middle is 0.14 % SOC past the count (2 mV on this curve)."""
    est = SocEstimator(1, nmc_like_ocv, 3.0, 10.0, initial_soc=0.5, config=SocConfig(soc_method="c0"))
    est.update(3.0, np.array([3.8]))
    mid = 0.5 + 3.0 * 5.0 / (3600.0 * 3.0)
    assert est.v_o[0] == pytest.approx(3.8 - nmc_like_ocv.ocv(mid), abs=1e-9)


@pytest.mark.parametrize("stated_ah, flag", [(1.0, 1), (1.45, 1), (1.55, 0), (6.2, -1), (5.8, 0)])
def test_the_voltage_line_flags_a_stated_capacity_off_by_more_than_its_ratio_either_way(stated_ah, flag, nmc_like_ocv):
    """The c0 method's voltage line (module docstring, "At a bound") of a 3 Ah cell flags a stated capacity more
    than VOLTAGE_LINE_RATIO_MAX (2) times it as at the low bound (-1) and one under 1/2 of it as at the high
    bound (+1); within the ratio, no flag. A state carries the line: its sums of points on s = 0.9 + q / 3 Ah."""
    assert VOLTAGE_LINE_RATIO_MAX == 2.0
    q = np.linspace(-2.4, 0.0, 50)
    s = 0.9 + q / 3.0
    cfg = SocConfig(soc_method="c0")
    state = SocEstimator(1, nmc_like_ocv, stated_ah, 1.0, initial_soc=0.9, config=cfg).state_dict()
    state["vline"] = np.array([[q.size, q.sum(), s.sum(), (q * q).sum(), (q * s).sum(), (s * s).sum()]])
    state["vline_q_range"] = np.array([[q.min(), q.max()]])
    est = SocEstimator(1, nmc_like_ocv, stated_ah, 1.0, config=cfg)
    est.load_state_dict(state)
    assert est.capacity_voltage_ah[0] == pytest.approx(3.0, rel=1e-9)
    assert est.capacity_at_bound[0] == flag
