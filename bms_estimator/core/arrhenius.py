"""Arrhenius temperature scaling of the equivalent circuit's resistances.

Ohmic conduction and charge transfer both slow down as the cell cools; over the
range of a drive cycle's self-heating one activation temperature ``B = E_a / R_gas``
describes both well enough::

    f(T; T_ref) = exp(B (1/T - 1/T_ref))            (T, T_ref in kelvin)
    R(T)        = f(T; T_ref) R(T_ref)

Applied to a 2-RC parameter set (:func:`resistances_at`) every resistance is scaled by
``f`` (R0, R1, R2 and a kinetic term's K1, K2) and the time constants are kept
(``C_j = tau_j / R_j`` takes ``1/f``): the RC branches respond as fast but with a
smaller (warmer) or larger (cooler) polarisation.  Where either temperature is not
finite, or outside ``CELL_TEMPERATURE_RANGE_C``, the factor is 1 (no correction).  Pure
numpy, no I/O.

Why a range.  No cell in a vehicle is below -60 degC or above 120 degC: such a reading is
a sensor fault (an open or shorted thermistor reads its converter's end), not a
temperature, and the line extrapolated there is absurd (x28 at -60 degC, 4e11 at
-200 degC, 1e43 at -250 degC).  The identifier's prior and the SOC filter's diffusion
resistance take the factor of the cell's first reading: one such reading at the start
left a cell warm ever after with R0 = 3.6e41 ohm (-250 degC), or its SOC read 37 % low
within 10 min of a pulsed drive (-100 degC).  It is treated as the missing reading it is.
"""

from __future__ import annotations

import numpy as np

__all__ = ["CELL_TEMPERATURE_RANGE_C", "cell_temperature_ok", "KELVIN", "R_GAS", "RESISTANCE_ACTIVATION_K", "arrhenius_factor", "resistances_at", "SCALED_RESISTANCES"]

KELVIN = 273.15
R_GAS = 8.314462618  # J / (mol K)

#: B = E_a / R_gas of the measured cells' resistances: their Arrhenius line of R0 across ambients
#: (README, diagnose findings: E_a = 19 kJ/mol Panasonic, 22 kJ/mol LG, i.e. 2300-2650 K), rounded
RESISTANCE_ACTIVATION_K = 2500.0

#: the temperatures [degC] a cell can have; a reading outside is a sensor fault (module docstring)
CELL_TEMPERATURE_RANGE_C = (-60.0, 120.0)

#: the parameter-dict keys that are resistances (scaled by f); capacitances take 1/f
SCALED_RESISTANCES = ("r0_ohm", "r1_ohm", "r2_ohm", "k1_ohm", "k2_ohm")
_CAPACITANCES = ("c1_f", "c2_f")


def cell_temperature_ok(temperature_c) -> np.ndarray:
    """True where ``temperature_c`` (degC) is one a cell can have: finite and inside
    ``CELL_TEMPERATURE_RANGE_C`` (module docstring)."""
    t = np.asarray(temperature_c, dtype=float)
    lo, hi = CELL_TEMPERATURE_RANGE_C
    with np.errstate(invalid="ignore"):
        return (t >= lo) & (t <= hi)  # (NaN: False)


def arrhenius_factor(temperature_c, reference_c, activation_k: float) -> np.ndarray:
    """``exp(B (1/T - 1/T_ref))`` with the temperatures in degC; 1 where either is not finite or outside
    ``CELL_TEMPERATURE_RANGE_C`` (module docstring).

    ``activation_k`` (B = E_a / R_gas, kelvin) must be finite and >= 0.
    """
    b = float(activation_k)
    if not (np.isfinite(b) and b >= 0.0):
        raise ValueError(f"activation temperature must be a finite number >= 0 K, got {activation_k}")
    t_c = np.asarray(temperature_c, dtype=float)
    ref_c = np.asarray(reference_c, dtype=float)
    ok = cell_temperature_ok(t_c) & cell_temperature_ok(ref_c)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):  # (where not ok: not used)
        f = np.exp(b * (1.0 / (t_c + KELVIN) - 1.0 / (ref_c + KELVIN)))
    return np.where(ok, f, 1.0)


def resistances_at(params: dict[str, np.ndarray], temperature_c, reference_c,
                   activation_k: float) -> dict[str, np.ndarray]:
    """A copy of ``params`` (identified at ``reference_c``) brought to ``temperature_c`` (module docstring)."""
    f = arrhenius_factor(temperature_c, reference_c, activation_k)
    out = dict(params)
    for key in SCALED_RESISTANCES:
        if key in out:
            out[key] = np.asarray(out[key], dtype=float) * f
    for key in _CAPACITANCES:
        if key in out:
            out[key] = np.asarray(out[key], dtype=float) / f
    return out
