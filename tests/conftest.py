"""Shared fixtures: synthetic cells and access to the measured data."""

from __future__ import annotations

import numpy as np
import pytest

from bms_estimator.core.ecm import EcmParams, simulate_ecm
from bms_estimator.core.ocv import OcvCurve
from bms_estimator.data import shared_data_dir

SHARED = shared_data_dir()
needs_shared = pytest.mark.skipif(
    SHARED is None, reason="../shared/data (the full measured data set) is absent; CI has it"
)

# The synthetic cell: R0 20 mOhm; R1 10 mOhm, tau1 10 s; R2 15 mOhm, tau2 200 s; c0 5 mV
TRUE = dict(r0_ohm=0.020, r1_ohm=0.010, tau1_s=10.0, r2_ohm=0.015, tau2_s=200.0, c0_v=0.005)


def pulse_current(n: int, seed: int = 0, amp_a: float = 6.0) -> np.ndarray:
    """Random pulses: levels held 5..120 s, 20 % rests, both directions."""
    rng = np.random.default_rng(seed)
    i = np.zeros(n)
    k = 0
    while k < n:
        d = int(rng.integers(5, 120))
        i[k : k + d] = rng.choice([-1.0, 1.0]) * rng.uniform(0.2, amp_a) * (rng.random() < 0.8)
        k += d
    return i


def synthetic_overpotential(n: int = 7200, seed: int = 0, noise_v: float = 0.0, noise_a: float = 0.0):
    """(current, v_o) of the issue's 2-RC cell, 1 s samples averaged over each step."""
    i = pulse_current(n, seed)
    p = EcmParams.from_rc(TRUE["r0_ohm"], [TRUE["r1_ohm"], TRUE["r2_ohm"]], [TRUE["tau1_s"], TRUE["tau2_s"]], TRUE["c0_v"])
    v = simulate_ecm(i, 1.0, p, output="mean").voltage_v
    rng = np.random.default_rng(seed + 1000)
    return i + noise_a * rng.standard_normal(n), v + noise_v * rng.standard_normal(n)


@pytest.fixture
def nmc_like_ocv() -> OcvCurve:
    soc = np.linspace(0.0, 1.0, 201)
    ocv = 3.0 + 0.75 * soc + 0.45 * soc**2 - 0.25 * np.exp(-25 * soc) + 0.05 * np.sin(4 * soc)
    return OcvCurve(soc, ocv)
