"""The half-gap cap keeps each measured branch where its leg of the C/20 test ran longest."""

import numpy as np
import pytest

from bms_estimator.core.ocv import OcvCurve
from bms_estimator.core.ocv_surface import OcvSurface

CAP = 0.05


def _table(temperature_c: float = 25.0, scale: float = 1.0) -> OcvCurve:
    """A C/20-like table: gap 240 mV wide at empty (the charge leg's start), 130 mV at full."""
    s = np.linspace(0.0, 1.0, 51)
    mean = 3.2 + 0.8 * s + 0.2 * s**2 - 0.3 * np.exp(-10 * s)
    half = scale * (0.015 + 0.105 * np.exp(-15 * s) + 0.05 * np.exp(-15 * (1 - s)))
    return OcvCurve(s, mean, half, capacity_discharge_ah=2.9, temperature_c=temperature_c)


def test_the_discharge_branch_is_kept_near_empty_and_the_charge_branch_near_full():
    t = _table()
    c = t.with_half_gap_cap(CAP)
    low = np.linspace(0.0, 0.4, 81)
    high = np.linspace(0.6, 1.0, 81)
    # the measured branch, unchanged (between the knots to the splines' interpolation, < 1 mV here)
    np.testing.assert_allclose(c.ocv(low) - c.hysteresis(low), t.ocv(low) - t.hysteresis(low), atol=1e-3)
    np.testing.assert_allclose(c.ocv(high) + c.hysteresis(high), t.ocv(high) + t.hysteresis(high), atol=1e-3)
    # exactly at the knots
    k = t.soc <= 0.4
    np.testing.assert_allclose((c.ocv_v - c.hysteresis_v)[k], (t.ocv_v - t.hysteresis_v)[k], atol=1e-12)
    # the other branch comes within 2 cap; the mean moved by the excess, where there is one
    s = np.linspace(0.0, 1.0, 401)
    assert np.all(c.hysteresis(s) <= CAP + 1e-9)
    assert np.max(t.ocv(low) - c.ocv(low)) > 0.05  # 240 mV gap at empty: the mean fell ~70 mV
    mid = np.linspace(0.3, 0.7, 41)
    wide = t.hysteresis(mid) > CAP + 1e-3
    np.testing.assert_allclose(c.ocv(mid)[~wide], t.ocv(mid)[~wide], atol=1e-3)
    # still a table: strictly increasing, exact inverse, the rest carried over
    assert np.all(np.diff(c.ocv(s)) > 0)
    np.testing.assert_allclose(c.soc_from_ocv(c.ocv(s)), s, atol=1e-9)
    assert (c.capacity_discharge_ah, c.temperature_c) == (t.capacity_discharge_ah, t.temperature_c)


def test_a_table_within_the_cap_or_without_hysteresis_is_returned_as_it_is():
    narrow = _table(scale=0.2)  # at most 34 mV
    assert narrow.with_half_gap_cap(CAP) is narrow
    none = OcvCurve(narrow.soc, narrow.ocv_v)
    assert none.with_half_gap_cap(CAP) is none
    with pytest.raises(ValueError, match="half-gap cap"):
        narrow.with_half_gap_cap(float("nan"))
    with pytest.raises(ValueError, match="half-gap cap"):
        narrow.with_half_gap_cap(-0.01)


def test_a_surface_caps_every_table_and_keeps_its_temperatures():
    cold, warm = _table(0.0, 1.3), _table(25.0)
    surf = OcvSurface([warm, cold], default_temperature_c=20.0)
    capped = surf.with_half_gap_cap(CAP)
    assert capped.default_temperature_c == 20.0
    assert list(capped.temperatures_c) == [0.0, 25.0]
    s = np.linspace(0.0, 0.4, 41)
    for t, table in ((0.0, cold), (25.0, warm)):
        np.testing.assert_allclose(capped.ocv(s, t) - capped.hysteresis(s, t), table.ocv(s) - table.hysteresis(s),
                                   atol=1e-3)
    one = OcvSurface([warm])
    assert one.with_half_gap_cap(1.0) is one
