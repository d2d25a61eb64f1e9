"""Tests of bms_estimator.core.ocv.OcvCurve: interpolation, inverse, C/20, HPPC, CSV."""

from __future__ import annotations

import gzip
import re
import warnings
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bms_estimator.core.ocv import MIN_SLOPE_V, OcvCurve
from bms_estimator.data import load_recording
from bms_estimator.ocv_table import read_ocv_table, read_ocv_tables, write_ocv_table
from tests.conftest import shared_file


def true_ocv(soc):
    """A smooth, strictly increasing test OCV [V] (slope >= 0.4 V per unit SOC)."""
    s = np.asarray(soc, dtype=float)
    return 3.2 + 0.9 * s + 0.08 * np.sin(2 * np.pi * s) - 0.3 * np.exp(-15 * s)


def true_hyst(soc):
    return 0.015 + 0.01 * np.asarray(soc, dtype=float)


def knot_curve(n: int = 21, hysteresis: bool = True) -> OcvCurve:
    s = np.linspace(0, 1, n)
    return OcvCurve(s, true_ocv(s), true_hyst(s) if hysteresis else None)


# --------------------------------------------------------------------------- construction


@pytest.mark.parametrize(
    "soc, ocv, hyst, pattern",
    [
        ([0, 0.5, 0.5, 1], [3, 3.5, 3.6, 4], None, "soc must be strictly increasing"),
        ([0, 0.5, 1], [3, 3.6, 3.5], None, "ocv_v must be strictly increasing"),
        ([0, 0.5, 1], [3, np.nan, 4], None, "finite"),
        ([0, 50, 100], [3, 3.5, 4], None, r"soc must lie in \[0, 1\]"),
        ([0, 0.5, 1], [3, 3.5, 4], [0.01, -0.01, 0.01], "hysteresis_v must be >= 0"),
        ([0, 0.5, 1], [3, 3.5], None, "equal length"),
        ([0.5], [3.5], None, "at least 2 points"),
    ],
)
def test_constructor_rejects_bad_tables(soc, ocv, hyst, pattern) -> None:
    with pytest.raises(ValueError, match=pattern):
        OcvCurve(soc, ocv, hyst)


def test_knots_are_reproduced_and_curve_is_close_to_truth() -> None:
    c = knot_curve(41)
    np.testing.assert_allclose(c.ocv(c.soc), c.ocv_v, atol=1e-12)
    s = np.linspace(0.05, 0.95, 500)
    np.testing.assert_allclose(c.ocv(s), true_ocv(s), atol=2e-3)


def test_scalar_in_float_out_and_shapes_kept() -> None:
    c = knot_curve()
    assert isinstance(c.ocv(0.5), float)
    assert isinstance(c.soc_from_ocv(3.7), float)
    assert isinstance(c.docv_dsoc(0.5), float)
    assert isinstance(c.hysteresis(0.5), float)
    x = np.random.default_rng(0).uniform(0, 1, (7, 3))
    for f in (c.ocv, c.docv_dsoc, c.hysteresis):
        out = f(x)
        assert out.shape == (7, 3)
        np.testing.assert_allclose(out.ravel(), [f(float(v)) for v in x.ravel()], atol=1e-12)
    np.testing.assert_allclose(c.soc_from_ocv(c.ocv(x)), x, atol=1e-12)


def test_extrapolation_is_linear_with_end_slopes_and_finite() -> None:
    c = knot_curve(21)
    lo = (c.ocv_v[1] - c.ocv_v[0]) / (c.soc[1] - c.soc[0])
    hi = (c.ocv_v[-1] - c.ocv_v[-2]) / (c.soc[-1] - c.soc[-2])
    assert c.ocv(-0.2) == pytest.approx(c.ocv_v[0] - 0.2 * lo, abs=1e-12)
    assert c.ocv(1.3) == pytest.approx(c.ocv_v[-1] + 0.3 * hi, abs=1e-12)
    assert c.docv_dsoc(-0.2) == pytest.approx(lo)
    assert c.docv_dsoc(1.3) == pytest.approx(hi)
    far = np.array([-1e3, -5.0, 5.0, 1e3])
    assert np.all(np.isfinite(c.ocv(far)))
    assert np.all(np.isfinite(c.soc_from_ocv(np.array([-10.0, 0.0, 10.0, 100.0]))))
    assert c.soc_from_ocv(0.0) < 0.0 and c.soc_from_ocv(10.0) > 1.0
    # hysteresis is held constant beyond the ends
    assert c.hysteresis(-0.5) == pytest.approx(c.hysteresis_v[0])
    assert c.hysteresis(1.5) == pytest.approx(c.hysteresis_v[-1])


def test_slope_matches_finite_difference_and_is_floored() -> None:
    c = knot_curve(41)
    s = np.linspace(0.05, 0.95, 91)
    fd = (c.ocv(s + 1e-4) - c.ocv(s - 1e-4)) / 2e-4
    np.testing.assert_allclose(c.docv_dsoc(s), fd, rtol=2e-2, atol=2e-3)
    # a nearly flat table: slope is floored, still strictly positive
    flat = OcvCurve([0, 0.5, 1], [3.7, 3.7 + 1e-7, 3.7 + 2e-7])
    assert np.all(flat.docv_dsoc(np.linspace(-1, 2, 31)) >= MIN_SLOPE_V)


def test_hysteresis_zero_without_table() -> None:
    c = knot_curve(hysteresis=False)
    assert not c.has_hysteresis
    np.testing.assert_array_equal(c.hysteresis(np.linspace(0, 1, 5)), 0.0)
    h = knot_curve()
    np.testing.assert_allclose(h.hysteresis(np.linspace(0, 1, 11)), true_hyst(np.linspace(0, 1, 11)), atol=1e-6)


@st.composite
def increasing_tables(draw):
    n = draw(st.integers(min_value=2, max_value=25))
    ds = np.array(draw(st.lists(st.floats(1e-3, 1.0), min_size=n - 1, max_size=n - 1)))
    dv = np.array(draw(st.lists(st.floats(1e-5, 1.0), min_size=n - 1, max_size=n - 1)))
    soc = np.r_[0.0, np.cumsum(ds)]
    soc /= soc[-1]
    ocv = 2.5 + np.r_[0.0, np.cumsum(dv)]
    return soc, ocv


@settings(max_examples=60, deadline=None)
@given(increasing_tables(), st.floats(-0.5, 1.5))
def test_monotone_and_inverse_consistent(table, s_probe) -> None:
    soc, ocv = table
    c = OcvCurve(soc, ocv)
    s = np.linspace(-0.3, 1.3, 4001)
    v = c.ocv(s)
    assert np.all(np.isfinite(v))
    assert np.all(np.diff(v) > 0)  # strictly increasing
    assert np.all(c.docv_dsoc(s) > 0)
    # non-decreasing even at rounding resolution around an arbitrary probe
    near = np.sort(np.r_[s_probe, np.nextafter(s_probe, 2.0), s_probe + 1e-12, s_probe - 1e-12])
    assert np.all(np.diff(c.ocv(near)) >= 0)
    np.testing.assert_allclose(c.soc_from_ocv(v), s, atol=1e-9)
    assert c.soc_from_ocv(c.ocv(s_probe)) == pytest.approx(s_probe, abs=1e-9)
    vv = np.linspace(ocv[0] - 0.5, ocv[-1] + 0.5, 2001)
    assert np.all(np.diff(c.soc_from_ocv(vv)) > 0)


def test_nan_propagates_without_runtime_warnings() -> None:
    c = knot_curve()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert np.isnan(c.ocv(np.nan))
        assert np.isnan(c.soc_from_ocv(np.nan))
        out = c.ocv(np.array([np.nan, 0.5]))
        assert np.isnan(out[0]) and np.isfinite(out[1])
        out = c.soc_from_ocv(np.array([np.nan, 3.7]))
        assert np.isnan(out[0]) and np.isfinite(out[1])


# --------------------------------------------------------------------------- C/20


def make_c20(cap_d=3.0, cap_c=2.7, i_a=0.15, r_ohm=0.05, dt=60.0):
    """Synthetic C/20 test: rest, discharge 1 -> 0 over cap_d, rest, charge 0 -> 1 over cap_c, rest.

    Records follow the logger model: a step's first record one interval after its start.
    """
    t, i, v = [], [], []
    now = 0.0

    def rest(n, soc):
        nonlocal now
        for _ in range(n):
            now += dt
            t.append(now), i.append(0.0), v.append(float(true_ocv(soc)))

    rest(5, 1.0)
    n_d = int(round(cap_d * 3600 / (i_a * dt)))
    for k in range(1, n_d + 1):
        soc = 1.0 - k * i_a * dt / 3600 / cap_d
        now += dt
        t.append(now), i.append(-i_a), v.append(float(true_ocv(soc) - i_a * r_ohm - true_hyst(soc)))
    rest(60, 0.0)
    n_c = int(round(cap_c * 3600 / (i_a * dt)))
    for k in range(1, n_c + 1):
        soc = k * i_a * dt / 3600 / cap_c
        now += dt
        t.append(now), i.append(i_a), v.append(float(true_ocv(soc) + i_a * r_ohm + true_hyst(soc)))
    rest(60, 1.0)
    return np.array(t), np.array(i), np.array(v)


def test_from_c20_recovers_ocv_hysteresis_and_branch_capacities() -> None:
    t, i, v = make_c20()
    c = OcvCurve.from_c20(t, i, v)
    assert c.capacity_discharge_ah == pytest.approx(3.0, abs=1e-9)
    assert c.capacity_charge_ah == pytest.approx(2.7, abs=1e-9)
    assert c.soc[0] == 0.0 and c.soc[-1] == 1.0 and c.soc.size == 201
    s = np.linspace(0.02, 0.98, 97)
    np.testing.assert_allclose(c.ocv(s), true_ocv(s), atol=3e-3)
    # half gap = hysteresis + |I| R
    np.testing.assert_allclose(c.hysteresis(s), true_hyst(s) + 0.15 * 0.05, atol=2e-3)
    assert np.all(np.diff(c.ocv_v) > 0)


def test_from_c20_and_from_hppc_take_the_tests_median_temperature() -> None:
    t, i, v = make_c20()
    temp = np.full(t.size, 24.0)
    temp[: t.size // 3] = 30.0  # a warm start does not move the median
    temp[5] = np.nan  # a logging gap is ignored
    assert OcvCurve.from_c20(t, i, v, temperature_c=temp).temperature_c == pytest.approx(24.0)
    assert OcvCurve.from_c20(t, i, v, temperature_c=-10).temperature_c == -10.0
    assert OcvCurve.from_c20(t, i, v).temperature_c is None  # unknown stays unknown
    h, s, _ = make_hppc()
    assert OcvCurve.from_hppc(h, s, temperature_c=np.array([0.5, 1.0, 1.5])).temperature_c == 1.0
    with pytest.raises(ValueError, match="temperature_c must be a finite"):
        OcvCurve([0, 1], [3, 4], temperature_c=float("inf"))


def test_from_c20_with_noise_is_still_monotone() -> None:
    t, i, v = make_c20()
    v = v + np.random.default_rng(3).normal(0, 2e-3, v.size)
    c = OcvCurve.from_c20(t, i, v)
    assert np.all(np.diff(c.ocv_v) > 0)
    s = np.linspace(0.05, 0.95, 19)
    np.testing.assert_allclose(c.ocv(s), true_ocv(s), atol=6e-3)


def test_from_c20_with_capacity_uses_common_ah_scale() -> None:
    t, i, v = make_c20(cap_d=3.0, cap_c=3.0)
    c = OcvCurve.from_c20(t, i, v, capacity_ah=3.0)
    s = np.linspace(0.05, 0.95, 19)
    np.testing.assert_allclose(c.ocv(s), true_ocv(s), atol=3e-3)
    with pytest.raises(ValueError, match="overlap"):
        OcvCurve.from_c20(t, i, v, capacity_ah=9.0)


def test_from_c20_needs_both_branches() -> None:
    t, i, v = make_c20()
    n_dis = np.flatnonzero(i < 0)[-1] + 1
    with pytest.raises(ValueError, match="no charge segment"):
        OcvCurve.from_c20(t[:n_dis + 5], i[:n_dis + 5], v[:n_dis + 5])
    with pytest.raises(ValueError, match="no discharge segment"):
        OcvCurve.from_c20(t, np.abs(i), v)


def test_from_c20_of_a_test_that_starts_empty_and_charges_first() -> None:
    """A C/20 test that starts at the cut-off charges first, rests, then discharges: it was refused ('no
    charge segment after the discharge', with a hint at HPPC) though it holds both branches. The same
    branches give the same table, with a common Ah scale too."""
    t, i, v = make_c20(cap_d=3.0, cap_c=3.0)
    k_c = np.flatnonzero(i > 0)[0] - 30  # from the rest after the discharge on: rest, charge, rest
    t2 = np.r_[t[k_c:] - t[k_c], t[k_c:][-1] - t[k_c] + t[:k_c] - t[0] + 60.0]
    i2, v2 = np.r_[i[k_c:], i[:k_c]], np.r_[v[k_c:], v[:k_c]]
    assert np.all(np.diff(t2) > 0)
    for cap in (None, 3.0):
        a = OcvCurve.from_c20(t, i, v, capacity_ah=cap)
        b = OcvCurve.from_c20(t2, i2, v2, capacity_ah=cap)
        np.testing.assert_allclose(b.soc, a.soc)
        np.testing.assert_allclose(b.ocv_v, a.ocv_v, atol=1e-9)
        np.testing.assert_allclose(b.hysteresis_v, a.hysteresis_v, atol=1e-9)
        assert (b.capacity_discharge_ah, b.capacity_charge_ah) == pytest.approx((3.0, 3.0))


@pytest.mark.parametrize("at", [0.4, 0.7])
def test_from_c20_of_a_branch_with_a_pause_is_the_whole_branch(at) -> None:
    """A C/20 discharge paused for 10 min (a rest inside it, the same current on either side): its longest run
    alone was the branch, stretched over SOC 0..1 (the LG 25 degC test paused 40 % in: 105 mV RMS off, its
    capacity 1.67 Ah, exit 0). The paused test gives the unpaused one's table; a pause in the charge too."""
    t, i, v = make_c20(cap_d=3.0, cap_c=2.7)
    base = OcvCurve.from_c20(t, i, v)
    for sign in (-1, 1):
        k = np.flatnonzero(sign * i > 0)
        k = int(k[int(at * k.size)])
        pause = np.arange(1, 11) * 60.0
        t2 = np.r_[t[:k + 1], t[k] + pause, t[k + 1:] + 600.0]
        i2 = np.r_[i[:k + 1], np.zeros(10), i[k + 1:]]
        v2 = np.r_[v[:k + 1], v[k] - sign * 0.01 * np.ones(10), v[k + 1:]]  # relaxing towards the OCV
        c = OcvCurve.from_c20(t2, i2, v2)
        assert (c.capacity_discharge_ah, c.capacity_charge_ah) == pytest.approx((3.0, 2.7), abs=1e-9)
        np.testing.assert_allclose(c.ocv_v, base.ocv_v, atol=1e-9)
        np.testing.assert_allclose(c.hysteresis_v, base.hysteresis_v, atol=1e-9)
    # a run at another current after the pause is not joined (a drive's, an HPPC test's): the longest run is the
    # branch, as before
    k = int(np.flatnonzero(i < 0)[int(0.6 * np.count_nonzero(i < 0))])
    i3 = i.copy()
    i3[k:k + 10] = 0.0
    i3[k + 10:][i3[k + 10:] < 0] *= 2.0
    assert OcvCurve.from_c20(t, i3, v).capacity_discharge_ah == pytest.approx(2 * 0.4 * 3.0 - 0.05, abs=0.02)


# --------------------------------------------------------------------------- HPPC


def make_hppc(cap=3.0, r_ohm=0.05, n_sets=10, tail_test=True):
    """Synthetic HPPC in the Panasonic two-file layout (see OcvCurve.from_hppc).

    Pulse sets at soc 1.0, 0.9, ... logged densely in ``hppc``; the slow discharge
    between sets (to the next 10 % SOC) and the final discharge to empty logged
    sparsely in ``steps`` on its own time axis, followed by an unrelated test.
    Returns (hppc, steps, true soc of the sets).
    """
    hppc, steps = ([], [], []), ([], [], [])
    state = {"t": 0.0, "soc": 1.0}

    def step(duration, current, log, delta):
        t0, s0 = state["t"], state["soc"]
        times = list(np.arange(t0 + delta, t0 + duration - 1e-9, delta)) + [t0 + duration]
        for tt in times:
            soc = s0 + current * (tt - t0) / 3600 / cap
            log[0].append(tt), log[1].append(current), log[2].append(float(true_ocv(soc) + r_ohm * current))
        state["t"] = t0 + duration
        state["soc"] = s0 + current * duration / 3600 / cap

    set_socs = []
    for k in range(n_sets):
        target = 1.0 - 0.1 * k
        assert abs(state["soc"] - target) < 1e-12
        set_socs.append(state["soc"])
        step(10.0, 0.0, hppc, 0.1)  # end of the long rest, logged densely
        for pulse in (-1.5, -3.0, -6.0):
            step(10.0, pulse, hppc, 0.1)
            step(100.0, 0.0, hppc, 1.0)
        step(60.0, 0.0, hppc, 1.0)
        next_soc = max(target - 0.1, 0.0) if k < n_sets - 1 else 0.0
        duration = (state["soc"] - next_soc) * cap * 3600 / 0.9
        step(duration, -0.9, steps, 60.0)
        if k < n_sets - 1:
            step(1500.0, 0.0, steps, 300.0)
    if tail_test:  # an unrelated later test in the steps file
        state["t"] += 20000.0
        state["soc"] = 1.0
        for _ in range(3):
            step(700.0, -0.9, steps, 60.0)
            step(1500.0, 0.0, steps, 300.0)
    h = tuple(np.array(x) for x in hppc)
    s0 = steps[0][0]
    s = (np.array(steps[0]) - s0, np.array(steps[1]), np.array(steps[2]))
    return h, s, np.array(set_socs)


def test_from_hppc_recovers_soc_and_ocv_of_each_rest() -> None:
    h, s, socs = make_hppc()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        c = OcvCurve.from_hppc(h, s)
    assert c.hysteresis_v is None
    assert c.capacity_discharge_ah == pytest.approx(3.0, abs=1e-9)
    np.testing.assert_allclose(c.soc, np.sort(socs), atol=1e-9)
    np.testing.assert_allclose(c.ocv_v, true_ocv(np.sort(socs)), atol=1e-6)


def test_from_hppc_capacity_argument_rescales_soc() -> None:
    h, s, socs = make_hppc()
    c = OcvCurve.from_hppc(h, s, capacity_ah=3.3)
    np.testing.assert_allclose(c.soc, np.sort(1 - (1 - socs) * 3.0 / 3.3), atol=1e-9)


def test_from_hppc_without_steps_warns_about_gaps() -> None:
    h, _, _ = make_hppc()
    with pytest.warns(UserWarning, match="no steps were given"):
        c = OcvCurve.from_hppc(h, None)
    assert c.soc.size == 10


def test_from_hppc_refuses_a_test_without_rest_points() -> None:
    """A drive cycle given as the HPPC file (under load from its first sample, no logging gaps) has no rest
    point: an IndexError from the de-duplication of no points at all; now the ValueError that names it."""
    h, s, _ = make_hppc()
    t = np.arange(0.0, 3000.0, 0.1)
    drive = (t, -1.0 - 0.5 * np.sin(t / 30.0), 3.9 - 1e-5 * t)
    with pytest.raises(ValueError, match=r"only 0 usable rest point\(s\) .* not an HPPC test"):
        OcvCurve.from_hppc(drive, s)


def test_from_hppc_refuses_steps_that_leave_most_gaps_empty() -> None:
    """Another test's steps (here only the first discharge step of this one) line up with one gap of nine:
    that wrote a table whose SOC axis missed eight steps' charge, with a warning only. One gap without its
    step still warns and builds the table."""
    h, s, _ = make_hppc()
    first = s[0] <= s[0][np.flatnonzero(s[1] == 0)[0]]  # up to the first rest record after the first step
    with pytest.raises(ValueError, match="8 of the 9 hppc logging gaps hold no discharge step"):
        OcvCurve.from_hppc(h, tuple(x[first] for x in s))
    t_gap2 = s[0][np.flatnonzero(np.diff(s[1]) < 0)[1] + 1]  # the second discharge step's first record
    second = (s[0] >= t_gap2 - 1) & (s[0] < t_gap2 + 2000)
    with pytest.warns(UserWarning, match="1 of 9 hppc gaps have no discharge step"):
        OcvCurve.from_hppc(h, tuple(x[~second] for x in s))


def test_from_hppc_naive_integration_would_be_wrong() -> None:
    """The sparse steps file cannot be integrated naively (the reason for the alignment)."""
    _, s, _ = make_hppc()
    naive_ah = -np.sum(s[1][:-1] * np.diff(s[0])) / 3600
    assert naive_ah > 2 * 3.0


# --------------------------------------------------------------------------- CSV


def test_csv_round_trip(tmp_path: Path) -> None:
    for hyst in (True, False):
        c = knot_curve(31, hysteresis=hyst)
        path = write_ocv_table(c, tmp_path / f"ocv_{hyst}.csv")
        header = path.read_text().splitlines()[0]
        assert header == ("soc,ocv_v,hysteresis_v" if hyst else "soc,ocv_v")
        back = read_ocv_table(path)
        np.testing.assert_allclose(back.soc, c.soc, atol=1e-8)
        np.testing.assert_allclose(back.ocv_v, c.ocv_v, atol=1e-8)
        s = np.linspace(-0.1, 1.1, 121)
        np.testing.assert_allclose(back.ocv(s), c.ocv(s), atol=1e-6)
        assert (back.hysteresis_v is not None) == hyst


def test_csv_round_trip_of_temperature_and_capacity(tmp_path: Path) -> None:
    c = knot_curve(31, hysteresis=True)
    warm = OcvCurve(c.soc, c.ocv_v, c.hysteresis_v, capacity_discharge_ah=2.778764189, temperature_c=-0.526)
    path = write_ocv_table(warm, tmp_path / "ocv.csv")
    lines = path.read_text().splitlines()
    assert lines[0] == "soc,ocv_v,hysteresis_v,temperature_c,capacity_ah"
    assert all(ln.endswith(",-0.526,2.778764189") for ln in lines[1:])
    back = read_ocv_table(path)
    assert back.temperature_c == -0.526 and back.capacity_discharge_ah == 2.778764189
    np.testing.assert_allclose(back.hysteresis_v, c.hysteresis_v, atol=1e-8)
    only_t = write_ocv_table(OcvCurve(c.soc, c.ocv_v, temperature_c=10.0), tmp_path / "t.csv")
    assert only_t.read_text().splitlines()[0] == "soc,ocv_v,temperature_c"
    assert read_ocv_table(only_t).capacity_discharge_ah is None
    assert read_ocv_table(write_ocv_table(c, tmp_path / "old.csv")).temperature_c is None  # old tables still read


def test_csv_extra_columns_ignored(tmp_path: Path) -> None:
    p = tmp_path / "x.csv"
    p.write_text("note,soc,ocv_v\na,0,3.0\nb,0.5,3.6\nc,1,4.2\n")
    c = read_ocv_table(p)
    assert c.ocv(0.5) == pytest.approx(3.6)


@pytest.mark.parametrize(
    "text, pattern",
    [
        ("soc,voltage\n0,3\n1,4\n", r"missing column\(s\) ocv_v"),
        ("soc,ocv_v\n0,3\n0.6,3.5\n0.5,3.6\n1,4\n", r"soc is not strictly increasing at line 4 \(0.6 -> 0.5\)$"),
        ("soc,ocv_v\n0,3\n0.5,3.5\n0.5,3.6\n1,4\n", r"soc is not strictly increasing at line 4 \(0.5 -> 0.5\)$"),
        ("soc,ocv_v\n0,3000\n0.5,3600\n1,4100\n", r"line 2: ocv_v 3000.0 is not a cell's open-circuit voltage .*in mV\?"),
        ("soc,ocv_v,hysteresis_v\n0,3,0.01\n1,4,-0.01\n", r"line 3: hysteresis_v -0.01 is negative$"),
        ("soc,ocv_v\n0,3\n0.5,nan\n1,4\n", r"line 3: value 'nan' in column 'ocv_v' is not finite"),
        ("soc,ocv_v\n0,3\n0.5,x\n1,4\n", r"line 3: non-numeric value 'x'"),
        ("soc,ocv_v\n0,3\n50,3.5\n100,4\n", r"percent\?"),
        ("soc,ocv_v\n0,3\n0.5,3.8\n0.6,3.7\n1,4\n", r"ocv_v decreases by 100.0 mV"),
        ("soc,ocv_v\n0,3\n", r"at least 2 data rows"),
        ("", r"empty file"),
        ("soc,ocv_v,temperature_c\n0,3,25\n1,4,0\n", r"column 'temperature_c' must hold one value .* line 3 has 0$"),
        ("soc,ocv_v,capacity_ah\n0,3,0\n1,4,0\n", r"capacity_ah must be positive"),
        ("soc,ocv_v,temperature_c\n0,3,25\n1,4,\n", r"line 3: non-numeric value '' in column 'temperature_c'"),
        # a table in kelvin was filed at 298 degC (held there: every recording read on it as at its end table)
        ("soc,ocv_v,temperature_c\n0,3,298.15\n1,4,298.15\n",
         r"temperature_c 298.15 is not a cell temperature \(expected -60..150 degC; is the column in kelvin\?\)$"),
    ],
)
def test_csv_errors_name_file_and_problem(tmp_path: Path, text: str, pattern: str) -> None:
    p = tmp_path / "bad.csv"
    p.write_text(text)
    with pytest.raises(ValueError, match=pattern) as exc:
        read_ocv_table(p)
    assert str(p) in str(exc.value)


def test_csv_that_is_not_text_names_the_file(tmp_path: Path) -> None:
    """A binary file given as the table read "OCV table: 'utf-8' codec can't decode byte 0xff ...", no file."""
    p = tmp_path / "binary.csv"
    p.write_bytes(b"\xff\xfe\x00garbage")
    with pytest.raises(ValueError, match=r"binary.csv: not UTF-8 text \(invalid start byte at byte 0\)$"):
        read_ocv_table(p)


def test_a_gzipped_table_reads_as_the_plain_one(tmp_path: Path) -> None:
    """Recordings are read as .csv.gz; an OCV table so compressed read "not UTF-8 text (invalid start byte at
    byte 1)" from every command's --ocv and the service's pack.ocv_csv."""
    c = knot_curve(31, hysteresis=True)
    plain = write_ocv_table(OcvCurve(c.soc, c.ocv_v, c.hysteresis_v, temperature_c=10.0), tmp_path / "ocv.csv")
    gz = tmp_path / "ocv.csv.gz"
    gz.write_bytes(gzip.compress(plain.read_bytes()))
    want, got = read_ocv_table(plain), read_ocv_table(gz)
    np.testing.assert_array_equal(got.soc, want.soc)
    np.testing.assert_array_equal(got.ocv_v, want.ocv_v)
    np.testing.assert_array_equal(got.hysteresis_v, want.hysteresis_v)
    assert got.temperature_c == 10.0
    assert list(read_ocv_tables([gz]).temperatures_c) == [10.0]
    # a .gz name on a file that is not gzip data, or a truncated one, is named, not a traceback
    fake = tmp_path / "fake.csv.gz"
    fake.write_bytes(plain.read_bytes())
    with pytest.raises(ValueError, match=r"fake.csv.gz: not a gzip file, or a truncated one"):
        read_ocv_table(fake)
    cut = tmp_path / "cut.csv.gz"
    cut.write_bytes(gz.read_bytes()[:-20])
    with pytest.raises(ValueError, match=r"cut.csv.gz: not a gzip file, or a truncated one"):
        read_ocv_table(cut)


def test_csv_small_dip_is_repaired_with_warning(tmp_path: Path) -> None:
    p = tmp_path / "dip.csv"
    p.write_text("soc,ocv_v\n0,3.0\n0.4,3.6\n0.5,3.599\n0.6,3.6\n1,4.2\n")
    with pytest.warns(UserWarning, match="not strictly increasing"):
        c = read_ocv_table(p)
    assert np.all(np.diff(c.ocv_v) > 0)
    assert c.ocv_v[2] == pytest.approx(3.6, abs=1e-5)


@pytest.mark.parametrize("rows, covered", [
    ("0.45,3.60\n0.50,3.65\n0.55,3.70\n", "0.45..0.55"),  # a file cut short
    ("0.30,3.50\n0.60,3.70\n1.00,4.20\n", "0.3..1"),
    ("0.00,3.00\n0.50,3.65\n0.80,3.95\n", "0..0.8"),
])
def test_csv_that_does_not_span_the_soc_range_is_read_with_a_warning(tmp_path: Path, rows: str, covered: str) -> None:
    """Beyond its knots a table is extrapolated along its end segments: a table cut to 0.45..0.55 read
    the LG la92 sample to 5.1 % SOC RMSE (46 % for one cut to 0..0.005) without a word."""
    p = tmp_path / "short.csv"
    p.write_text("soc,ocv_v\n" + rows)
    with pytest.warns(UserWarning, match=rf"short.csv: the table covers soc {re.escape(covered)} only; outside it"):
        c = read_ocv_table(p)
    knots = np.array([[float(x) for x in r.split(",")] for r in rows.split()])
    np.testing.assert_allclose(c.ocv(knots[:, 0]), knots[:, 1], atol=1e-6)  # read as before, through its knots


@pytest.mark.parametrize("rows", ["0.10,3.40\n0.50,3.65\n0.90,4.05\n", "0.015,3.10\n0.5,3.65\n1.0,4.20\n"])
def test_csv_that_spans_the_soc_range_reads_without_a_warning(tmp_path: Path, rows: str) -> None:
    """0.1..0.9 is enough (the Panasonic HPPC tables start at 1.5-2.2 % SOC)."""
    p = tmp_path / "ok.csv"
    p.write_text("soc,ocv_v\n" + rows)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        read_ocv_table(p)


# --------------------------------------------------------------------------- real data




def _c20(rel: str) -> OcvCurve:
    rec = load_recording(shared_file(rel), resample_s=None)
    return OcvCurve.from_c20(rec.time_s, rec.current_a, rec.voltage_v, temperature_c=rec.temperature_c)


@pytest.mark.shared_data
@pytest.mark.parametrize(
    "rel, cap_d, cap_c, gap50_mv",
    [
        ("panasonic-18650pf/25degC/c20_ocv.csv.gz", 3.00, 2.62, 40.0),
        ("lg-hg2/25degC/c20_ocv.csv.gz", 2.78, 2.97, 38.0),
        ("lg-hg2/0degC/c20_ocv.csv.gz", 2.60, 2.69, 60.0),
    ],
)
def test_real_c20_capacities_and_gap(rel: str, cap_d: float, cap_c: float, gap50_mv: float) -> None:
    c = _c20(rel)
    assert c.capacity_discharge_ah == pytest.approx(cap_d, abs=0.02)
    assert c.capacity_charge_ah == pytest.approx(cap_c, abs=0.02)
    assert 2e3 * c.hysteresis(0.5) == pytest.approx(gap50_mv, abs=3.0)
    assert np.all(np.diff(c.ocv_v) > 0)
    assert 3.5 < c.ocv(0.5) < 3.85
    assert 4.1 < c.ocv(1.0) < 4.25
    ambient = float(rel.split("/")[1].replace("degC", "").replace("n", "-"))
    assert c.temperature_c == pytest.approx(ambient, abs=1.5)  # the cell's median, near the chamber's


@pytest.mark.shared_data
def test_real_hppc_agrees_with_c20_at_25degC() -> None:
    c20 = _c20("panasonic-18650pf/25degC/c20_ocv.csv.gz")
    h = load_recording(shared_file("panasonic-18650pf/25degC/hppc.csv.gz"), resample_s=None)
    s = load_recording(shared_file("panasonic-18650pf/25degC/hppc_steps.csv.gz"), resample_s=None)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # every gap gets its step
        hc = OcvCurve.from_hppc(h, s)
    assert hc.soc.size == 14
    assert hc.soc[0] < 0.05 and hc.soc[-1] == 1.0
    # total charge to cut-off: below the C/20 capacity, nowhere near the naive 8.8 Ah
    assert 2.7 < hc.capacity_discharge_ah < 2.95
    grid = np.linspace(0.1, 0.9, 81)
    diff_mv = 1e3 * (hc.ocv(grid) - c20.ocv(grid))
    assert np.max(np.abs(diff_mv)) < 25.0, np.round(diff_mv, 1)


def test_tables_sharing_a_locator_answer_as_if_each_located_its_own_query() -> None:
    """The OCV, slope and hysteresis tables share one grid locator that keeps the last query's answer:
    equal queries, a query changed in place, NaN, other shapes and an inverse in between all give
    exactly what a fresh curve gives."""
    curve, fresh = knot_curve(), knot_curve
    rng = np.random.default_rng(5)
    x = rng.uniform(-0.05, 1.05, 96)
    x[3] = np.nan
    got = [curve.ocv(x), curve.hysteresis(x), curve.docv_dsoc(x)]
    want = [fresh().ocv(x), fresh().hysteresis(x), fresh().docv_dsoc(x)]
    for g, w in zip(got, want):
        assert np.array_equal(g, w, equal_nan=True)
    assert np.array_equal(curve.soc_from_ocv(curve.ocv(x)), fresh().soc_from_ocv(fresh().ocv(x)), equal_nan=True)
    x += 0.01  # in place: the same object, other values
    assert np.array_equal(curve.docv_dsoc(x), fresh().docv_dsoc(x), equal_nan=True)
    assert np.array_equal(curve.ocv(x[:10].reshape(2, 5)), fresh().ocv(x[:10].reshape(2, 5)), equal_nan=True)
    v = curve.ocv(x[:5])  # the inverse moves segment indices of its own: the kept answer stays intact
    curve.soc_from_ocv(v + 0.2)
    assert np.array_equal(curve.ocv(x[:5]), v, equal_nan=True)


@pytest.mark.parametrize("hysteresis", [True, False])
def test_ocv_slope_hysteresis_in_one_lookup_equals_the_three_methods(hysteresis: bool) -> None:
    """The estimator's one-lookup read gives the three methods' values bit for bit, inside the
    table, beyond both ends (the linear extrapolation, the end slopes) and at NaN."""
    curve = knot_curve(hysteresis=hysteresis)
    x = np.random.default_rng(7).uniform(-0.05, 1.05, 96)
    x[[3, 4, 5]] = [np.nan, 0.0, 1.0]
    v, d, h = curve.ocv_slope_hysteresis(x)
    assert np.array_equal(v, knot_curve(hysteresis=hysteresis).ocv(x), equal_nan=True)
    assert np.array_equal(d, knot_curve(hysteresis=hysteresis).docv_dsoc(x), equal_nan=True)
    if hysteresis:
        assert np.array_equal(h, knot_curve().hysteresis(x), equal_nan=True)
    else:
        assert h is None
    inside = np.linspace(0.01, 0.99, 96)  # no cell beyond the ends: the slope table's values as they are
    assert np.array_equal(curve.ocv_slope_hysteresis(inside)[1], knot_curve(hysteresis=hysteresis).docv_dsoc(inside))


def test_the_slope_is_floored_beyond_a_flat_end_for_a_float_as_for_an_array():
    """Below the knots the slope is the first secant floored at ``MIN_SLOPE_V``, a float in as an array in."""
    flat = OcvCurve([0.0, 0.5, 1.0], [3.0, 3.0 + 1e-4, 4.0])  # first secant 2e-4 V per unit SOC
    assert flat.docv_dsoc(-0.1) == MIN_SLOPE_V == flat.docv_dsoc(np.array([-0.1]))[0]


@pytest.mark.parametrize("k", [20.0, 0.3])
def test_from_hppc_rests_scale_with_the_cells_size(k) -> None:
    """The same HPPC test on a cell k times the size (current x k) with a current sensor whose zero offset
    scales with its range (2 mA at rest on the 3 Ah cell, 40 mA on 60 Ah): the same table, capacity x k.
    A fixed 0.01 A rest threshold read every rest of the 60 Ah cell as a current run."""
    h, s, socs = make_hppc()

    def sized(log, factor):
        t, i, v = log
        return t, factor * np.where(i == 0.0, 0.002, i), v

    one = OcvCurve.from_hppc(sized(h, 1.0), sized(s, 1.0))
    big = OcvCurve.from_hppc(sized(h, k), sized(s, k))
    np.testing.assert_allclose(one.soc, np.sort(socs), atol=2e-3)
    np.testing.assert_allclose(big.soc, one.soc, atol=1e-9)
    np.testing.assert_allclose(big.ocv_v, one.ocv_v, atol=1e-12)
    assert big.capacity_discharge_ah == pytest.approx(k * one.capacity_discharge_ah, rel=1e-9)
