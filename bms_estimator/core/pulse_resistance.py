"""Pulse resistance: the voltage response to current pulses from rest, as a resistance at fixed times.

For every pulse that starts from rest (a run of same-sign current records
``|I| >= threshold_a`` preceded by at least ``rest_s`` of ``|I| < threshold_a``)::

    R(t) = (v(t0 + t) - v_rest) / I_pulse

``v_rest`` the last rest record before the pulse, ``I_pulse`` the mean current
of the pulse's records, ``t0`` the pulse start: one logging interval (the
median spacing of the pulse's records) before its first record, the logger
model of :meth:`bms_estimator.core.ocv.OcvCurve.from_hppc`. ``v(t0 + t)`` is
interpolated between the pulse's records; a time outside the pulse is NaN.

For a linear 2-RC cell ``R(t) = R0 + sum_j R_j (1 - exp(-t / tau_j))``
whatever the current: R(t) that changes with ``|I_pulse|`` at equal t (and SOC)
is a current-dependent resistance, and the time at which it appears tells the
branch (R(0.1 s) ~ the ohmic R0, R(10 s) - R(0.1 s) the fast polarisation).
A Butler-Volmer charge-transfer overpotential ``eta = K i0 asinh(i/i0)`` gives a
chord resistance ``K asinh(i/i0) / (i/i0)`` that falls with ``|i|``.

Arrays in, arrays out; no I/O.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["Pulses", "pulse_resistance"]


@dataclass(frozen=True)
class Pulses:
    """One row per pulse from rest."""

    start_s: np.ndarray  # pulse start t0
    current_a: np.ndarray  # mean pulse current (signed, positive = charge)
    rest_voltage_v: np.ndarray  # last rest record before the pulse
    duration_s: np.ndarray  # t0 to the pulse's last record
    at_s: np.ndarray  # the times of the columns of resistance_ohm
    resistance_ohm: np.ndarray  # (pulses, len(at_s)); NaN where at_s exceeds the pulse


def pulse_resistance(
    time_s: np.ndarray, current_a: np.ndarray, voltage_v: np.ndarray, *, threshold_a: float,
    rest_s: float = 60.0, at_s: tuple[float, ...] = (0.1, 1.0, 10.0), min_records: int = 3,
) -> Pulses:
    """Every pulse from rest and its resistance at the times ``at_s`` (module docstring)."""
    t, i, v = (np.asarray(x, dtype=float) for x in (time_s, current_a, voltage_v))
    if not (t.ndim == 1 and t.shape == i.shape == v.shape):
        raise ValueError(f"time, current and voltage must be 1-D of one length, got {t.shape}, {i.shape}, {v.shape}")
    if not threshold_a > 0:
        raise ValueError(f"threshold_a must be positive, got {threshold_a}")
    if np.any(np.diff(t) <= 0):
        raise ValueError("time must increase strictly")
    at = np.asarray(at_s, dtype=float)
    on = np.abs(i) >= threshold_a
    sign = np.sign(i) * on
    # runs of same-sign current records
    change = np.flatnonzero(np.diff(sign) != 0) + 1
    bounds = np.r_[0, change, len(i)]
    rows = []
    for a, b in zip(bounds[:-1], bounds[1:]):
        if not on[a] or a == 0 or b - a < min_records:
            continue
        # the rest before: records a-1, a-2, ... with |I| < threshold covering rest_s
        r = a - 1
        while r > 0 and not on[r - 1]:
            r -= 1
        if on[a - 1] or t[a - 1] - t[r] < rest_s:
            continue
        dt = float(np.median(np.diff(t[a:b])))
        t0 = t[a] - min(dt, t[a] - t[a - 1])
        v_rest = v[a - 1]
        cur = float(np.mean(i[a:b]))
        elapsed = t[a:b] - t0
        with np.errstate(invalid="ignore"):
            dv = np.interp(at, elapsed, v[a:b] - v_rest, left=np.nan, right=np.nan)
        dv = np.where((at >= elapsed[0]) & (at <= elapsed[-1]), dv, np.nan)
        rows.append((t0, cur, v_rest, elapsed[-1], dv / cur))
    if not rows:
        empty = np.zeros(0)
        return Pulses(empty, empty, empty, empty, at, np.zeros((0, len(at))))
    cols = list(zip(*rows))
    return Pulses(np.array(cols[0]), np.array(cols[1]), np.array(cols[2]), np.array(cols[3]), at,
                  np.array(cols[4]))
