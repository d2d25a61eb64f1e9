"""diagnose names the hidden cause on synthetic cells driven by the measured current profiles.

Every cause is hidden at sizes of 3 mV RMS and more (what the effect adds to the
2-RC baseline's residual, see bms_estimator/diagnose/generator.py) on different
shipped profiles, with different seeds (base parameters, effect shape, noise);
clean cells must give ``none``; two effects at once must give the larger.  The
LIF warm start is skipped here for speed (a grid start is always tried); the CLI
and real-data tests run it.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from bms_estimator.diagnose import CAUSES, DiagnoseConfig, Series, diagnose, generate, load_profile
from bms_estimator.diagnose.decide import fold_blocks, noise_level, tau_int

PAN1 = "panasonic-18650pf/25degC/cycle_1"
PAN2 = "panasonic-18650pf/25degC/cycle_2"
LG = "lg-hg2/25degC/la92"
FAST = DiagnoseConfig(lif=False)

_PROFILES: dict = {}


def profile(name):
    if name not in _PROFILES:
        _PROFILES[name] = load_profile(name)
    return _PROFILES[name]


def cell(name, cause, size, seed, **kw):
    i, _, _, ocv = profile(name)
    return generate(i, 1.0, cause, size, seed=seed, ocv=ocv, **kw)


# (cause, profile, size in mV, seed): two profiles and sizes per cause, the 3 mV floor included
CASES = [
    ("hysteresis", PAN2, 3.0, 4), ("hysteresis", LG, 6.0, 5),
    ("temperature", PAN1, 3.0, 5), ("temperature", LG, 5.0, 4),
    ("soc_dependence", LG, 3.0, 4), ("soc_dependence", PAN2, 8.0, 5),
    ("current_nonlinearity", PAN1, 3.0, 4), ("current_nonlinearity", LG, 10.0, 6),
    ("direction_asymmetry", LG, 3.0, 5), ("direction_asymmetry", PAN1, 4.0, 4),
    ("slow_diffusion", PAN2, 3.0, 5), ("slow_diffusion", LG, 6.0, 4),
    ("current_offset", LG, 3.0, 4), ("current_offset", PAN2, 5.0, 4),
    ("capacity_error", PAN1, 3.0, 5), ("capacity_error", LG, 8.0, 5),
]


def test_every_cause_has_cases():
    assert {c for c, *_ in CASES} == set(CAUSES)


@pytest.mark.parametrize("cause,prof,size,seed", CASES, ids=[f"{c}-{p.split('/')[-1]}-{s:g}mV" for c, p, s, _ in CASES])
def test_hidden_cause_is_named(cause, prof, size, seed):
    g = cell(prof, cause, size, seed)
    assert g.truth["effects"][cause]["residual_rms_mv"] == pytest.approx(size, rel=0.02)
    d = diagnose(g.series(), config=FAST)
    assert d.cause == cause, [(c.cause, round(c.gain_pct, 1), c.significant) for c in d.ranking()]
    assert d.extended_rmse_mv < d.baseline_rmse_mv
    # the extension explains the effect down to about the noise (1 mV) out of sample
    assert d.extended_rmse_mv < 1.0 + 0.5 * size


@pytest.mark.parametrize("prof,seed", [(PAN1, 7), (LG, 8)])
def test_clean_cell_gives_none(prof, seed):
    d = diagnose(cell(prof, "none", 0.0, seed).series(), config=FAST)
    assert d.cause == "none", [(c.cause, round(c.explained_mv, 2), c.significant) for c in d.ranking()]
    assert d.baseline_rmse_mv == pytest.approx(1.0, abs=0.1)  # the noise: the baseline is the truth


@pytest.mark.parametrize("causes,prof,seed", [
    ({"current_offset": 5.0, "soc_dependence": 3.0}, PAN1, 54),
    ({"slow_diffusion": 5.0, "current_nonlinearity": 3.0}, PAN2, 48),
    ({"temperature": 5.0, "hysteresis": 3.0}, LG, 9),
], ids=["offset>soc", "slow>nonlinearity", "temperature>hysteresis"])
def test_two_effects_name_the_larger(causes, prof, seed):
    i, _, _, ocv = profile(prof)
    g = generate(i, 1.0, causes, seed=seed, ocv=ocv)
    d = diagnose(g.series(), config=FAST)
    big, small = sorted(causes, key=lambda c: -causes[c])
    assert d.cause == big
    assert d.secondary == small
    comps = d.joint["components_mv"]
    assert comps[big] == pytest.approx(causes[big], rel=0.2)
    assert comps[small] == pytest.approx(causes[small], rel=0.2)


def test_json_has_the_issue_fields_and_is_serialisable():
    d = diagnose(cell(LG, "hysteresis", 4.0, 3).series(), config=FAST.with_(pairs=False))
    out = json.loads(json.dumps(d.to_json()))
    for key in ("cause", "baseline_rmse_mv", "extended_rmse_mv", "gain_pct", "candidates"):
        assert key in out
    assert {c["cause"] for c in out["candidates"]} == set(CAUSES)
    for c in out["candidates"]:
        assert {"cause", "rmse_mv", "gain_pct", "params"} <= set(c)
    hy = next(c for c in out["candidates"] if c["cause"] == "hysteresis")
    assert hy["params"]["m_v"] > 0 and hy["params"]["gamma"] > 0


def test_the_soc_window_is_said_within_0_and_1():
    """--soc-min 0.1 alone (the findings table's window) read 'SOC window 0.1..2': the open end is SOC 1."""
    d = diagnose(cell(LG, "none", 0.0, 2).series(), config=FAST.with_(pairs=False, soc_window=(0.1, 2.0)))
    assert d.scoring.endswith(", SOC window 0.1..1"), d.scoring


def test_validate_file_scores_on_the_other_file():
    # same hidden cell (seed) on two profiles of the same cell type: fit on one, score on the other
    i1, _, _, ocv = profile(PAN1)
    i2, _, _, _ = profile(PAN2)
    g1 = generate(i1, 1.0, "direction_asymmetry", 4.0, seed=21, ocv=ocv, capacity_ah=2.9)
    g2 = generate(i2, 1.0, "direction_asymmetry", 4.0, seed=21, ocv=ocv, capacity_ah=2.9)
    d = diagnose(g1.series(), validate=g2.series(), config=FAST.with_(pairs=False))
    assert d.scoring == "validation file"
    assert d.cause == "direction_asymmetry"


def test_temperature_is_skipped_without_a_temperature_column():
    g = cell(LG, "none", 0.0, 2)
    s = g.series()
    s2 = Series(s.current_a, s.voltage_v, s.ocv, s.capacity_ah, s.soc0, s.dt_s, None)
    d = diagnose(s2, config=FAST.with_(pairs=False))
    t = d.candidate("temperature")
    assert not t.significant and "temperature" in t.note


def test_statistics_helpers():
    rng = np.random.default_rng(0)
    white = rng.standard_normal(20000)
    assert tau_int(white) == pytest.approx(1.0, abs=0.2)
    ar = np.zeros(20000)
    for k in range(1, ar.size):
        ar[k] = 0.9 * ar[k - 1] + white[k]
    assert tau_int(ar) == pytest.approx(19.0, rel=0.25)  # (1 + 0.9) / (1 - 0.9)
    assert noise_level(white + np.linspace(0, 50, white.size)) == pytest.approx(1.0, rel=0.05)
    blocks, folds = fold_blocks(10000, 1.0, FAST)
    assert folds[0] == -1 and set(folds[blocks > 0]) == {0, 1, 2, 3}
    assert np.all(np.diff(blocks) >= 0)


def test_a_window_the_file_passes_only_at_its_start_is_refused_before_any_fit(monkeypatch):
    """The Panasonic cycle_1 sample (Kollmeyer, CC BY 4.0) is above 0.95 SOC only in its first block, which
    cross-validation trains on and never scores: 'Mean of empty slice' warnings, then a ZeroDivisionError
    in the score (n_eff 0)."""
    import warnings

    from bms_estimator.data import load_recording
    from bms_estimator.ocv_table import read_ocv_table
    from bms_estimator.samples import drive_cycle, ocv_table

    rec = load_recording(drive_cycle("panasonic-18650pf", "cycle_1"))
    s = Series.from_recording(rec, read_ocv_table(ocv_table("panasonic-18650pf")), 2.9, 1.0)
    cfg = FAST.with_(soc_window=(0.95, 0.99))
    said = r"only 0 samples with the counted SOC at least 0.95 and at most 0.99 after the first \d+ s"
    def fit(*args, **kwargs):
        raise AssertionError("a model was fitted before the window was refused")

    monkeypatch.setattr("bms_estimator.diagnose.decide.fit_model", fit)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no RuntimeWarning on the way
        with pytest.raises(ValueError, match=said):
            diagnose(s, config=cfg)
    monkeypatch.undo()
    from bms_estimator.diagnose.decide import scored_folds

    blocks, fold_of = scored_folds(s, cfg.with_(soc_window=(0.2, 0.9)), validation=False)
    assert np.all(fold_of[blocks == 0] == -1) and np.count_nonzero(fold_of >= 0) > 1000
