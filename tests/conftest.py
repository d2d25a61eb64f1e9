"""Shared fixtures: synthetic cells and access to the measured data."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from bms_estimator.core.ecm import EcmParams, simulate_ecm
from bms_estimator.core.ocv import OcvCurve
from bms_estimator.data import shared_data_dir

SHARED = shared_data_dir()
needs_shared = pytest.mark.skipif(
    SHARED is None, reason="../shared/data (the full measured data set) is absent; CI has it"
)


def foxbms_dbc_path() -> Path | None:
    """foxBMS' DBC (``$BMS_FOXBMS_DBC``, else ``../shared/dbc/foxbms/foxbms.dbc``), None where absent."""
    env = os.environ.get("BMS_FOXBMS_DBC")
    candidates = [Path(env)] if env else []
    candidates += [Path(__file__).resolve().parents[2] / "shared" / "dbc" / "foxbms" / "foxbms.dbc",
                   Path("/work/shared/dbc/foxbms/foxbms.dbc")]
    return next((p for p in candidates if p.is_file()), None)


def shared_file(rel: str) -> Path:
    """A file of the measured data set by its path inside it; the test skips, saying why, when the set
    or the file is absent."""
    if SHARED is None:
        pytest.skip("shared data set not available (set BMS_SHARED_DATA or provide ../shared/data)")
    path = SHARED / rel
    if not path.exists():
        pytest.skip(f"{rel} not in the shared data set")
    return path

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


def median_identification(method: str, overpotential, n: int = 6000, seeds=range(30, 34), noise_v: float = 0.005,
                          noise_a: float = 0.02, capacity_ah: float = 3.0) -> dict[str, np.ndarray]:
    """Each seed's pulse current (up to 2 C of 3 Ah) as one cell, its ``overpotential(current)``, 5 mV / 20 mA
    noise (rng 7), identified online by ``method``: every parameter's median over the second half, per cell."""
    from bms_estimator.core.identifier import IdentifierConfig
    from bms_estimator.core.identifier_methods import make_identifier

    cur = np.stack([pulse_current(n, s) for s in seeds], axis=1)
    v = np.stack([overpotential(cur[:, j]) for j in range(cur.shape[1])], axis=1)
    rng = np.random.default_rng(7)
    v = v + noise_v * rng.standard_normal(v.shape)
    meas = cur + noise_a * rng.standard_normal(cur.shape)
    est = make_identifier(cur.shape[1], 1.0, capacity_ah, IdentifierConfig(method=method))
    seen = []
    for k in range(n):
        est.update(meas[k], v[k])
        if k >= n // 2:
            seen.append(est.param_dict())
    return {key: np.median(np.array([s[key] for s in seen]), axis=0) for key in seen[0]}


def state_round_trip(make, current: np.ndarray, v_o: np.ndarray, split: int, cells: int = 2):
    """Two identifiers ``make()``: ``a`` runs the whole stream, ``b`` takes ``a``'s state at ``split`` and runs on
    (every cell the same sample); returns (a, b) for the caller to compare."""
    a, b = make(), make()
    for k in range(split):
        a.update(np.full(cells, current[k]), np.full(cells, v_o[k]))
    b.load_state_dict(a.state_dict())
    for k in range(split, len(current)):
        a.update(np.full(cells, current[k]), np.full(cells, v_o[k]))
        b.update(np.full(cells, current[k]), np.full(cells, v_o[k]))
    return a, b


def assert_physical_and_finite(est, cells: int) -> dict[str, np.ndarray]:
    """What an identifier gives out after a sample: every parameter finite, admissible, R0, R1, R2 > 0, the time
    constants inside the guard's bounds and ordered, a finite recursion and static prediction; returns param_dict."""
    p, cfg = est.params, est.config
    assert np.all(p.admissible)
    d = est.param_dict()
    for key, val in d.items():
        assert np.all(np.isfinite(val)), key
    assert np.all(np.stack([d["r0_ohm"], d["r1_ohm"], d["r2_ohm"]]) > 0)
    assert np.all((p.tau1_s >= cfg.tau_min_s) & (p.tau2_s <= cfg.tau_max_s) & (p.tau1_s < p.tau2_s))
    assert np.all(np.isfinite(est.rls.theta)) and np.all(np.isfinite(est.rls.P))
    assert np.all(np.isfinite(est.predict_static(np.full(cells, 10.0))))
    return d


@pytest.fixture
def nmc_like_ocv() -> OcvCurve:
    soc = np.linspace(0.0, 1.0, 201)
    ocv = 3.0 + 0.75 * soc + 0.45 * soc**2 - 0.25 * np.exp(-25 * soc) + 0.05 * np.sin(4 * soc)
    return OcvCurve(soc, ocv)


def hostile_strategies() -> dict:
    """Hypothesis strategies for :func:`hostile_stream`'s seed, amp, noise_v, noise_a and dropout."""
    from hypothesis import strategies as st

    return dict(seed=st.integers(0, 2**31 - 1), amp=st.floats(0.0, 30.0), noise_v=st.floats(0.0, 0.05),
                noise_a=st.floats(0.0, 0.5), dropout=st.floats(0.0, 0.5))


def hostile_stream(seed: int, amp: float, noise_v: float, noise_a: float, dropout: float, step_v: float = 0.0,
                   bend_ohm_per_a: float = 0.0, n: int = 600, cells: int = 3):
    """(current, v_o, valid) per sample for the identifiers' no-NaN properties: random levels of up to
    +-amp A held 10 s, a 1-RC cell with R0 20 mOhm (plus ``bend_ohm_per_a * i |i|``), voltage and
    current noise, a v_o step of step_v half-way, NaN voltages, NaN currents and invalid cells."""
    rng = np.random.default_rng(seed)
    current = np.repeat(rng.uniform(-amp, amp, n // 10 + 1), 10)[:n]
    state = np.zeros(cells)
    for k in range(n):
        state = 0.99 * state + 0.0005 * current[k]
        v = (0.02 * current[k] + bend_ohm_per_a * current[k] * abs(current[k]) + state
             + noise_v * rng.standard_normal(cells) + (step_v if k > n // 2 else 0.0))
        v = np.where(rng.random(cells) < dropout / 4, np.nan, v)
        i = current[k] + noise_a * rng.standard_normal() if rng.random() > dropout / 10 else np.nan
        yield i, v, rng.random(cells) >= dropout


def pytest_terminal_summary(terminalreporter) -> None:
    """Figures a test reports for CI's log (``record_property("summary_line", text)``), printed in the
    run's summary.  Not printed from the test itself: with pytest-xdist (``scripts/test`` runs the
    suite on every core) a test runs in a worker whose output is captured; its properties reach the
    controller with its report."""
    for report in terminalreporter.getreports("passed"):
        for name, value in report.user_properties:
            if name == "summary_line":
                terminalreporter.write_line(str(value))
