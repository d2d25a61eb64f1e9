"""SOC on the measured drive cycles, from four starts, against the independent reference.

The reference (:mod:`bms_estimator.scoring`) is coulomb counting from the full start
with the capacity read from the relaxed end rest on the same ambient's C/20 discharge
branch: nothing the estimator does enters it.  Scored where it is defined: LG HG2 at
25 and 0 degC, Panasonic 18650PF at 25 degC (the LG -10 degC rests are not relaxed;
Panasonic has no C/20 test at its other ambients).  The figures asserted here are the
README's (``python scripts/soc_matrix.py --readme``), with a margin.
"""

import re

import numpy as np
import pytest

from bms_estimator.core.soc import SocConfig
from bms_estimator.soc_matrix import STARTS, check_start, run_cell, start_point
from tests.conftest import SHARED, needs_shared

DEFAULT = SocConfig().soc_method


LATE = ("at50+20", "at50-20", "at50+5", "at50-5", "at75+20", "at75-20", "at75+5", "at75-5")
LOADED = ("at10ocv", "at25ocv", "at50ocv", "at75ocv")
FIRST_SAMPLE = ("ocv",)


@pytest.fixture(scope="module")
def every_start() -> list[dict]:
    """The scored files from the README's four starts and every other start the tests below score, in one run
    per cell: each (file, start) is a cell of one estimator, and a cell's figures are its run alone's (the
    README's four rows measured equal in every field), at a quarter of the time of a run per set of starts."""
    out = []
    for cell, pattern in (("lg-hg2", "lg-hg2/[02]*degC/*"), ("panasonic-18650pf", "panasonic-18650pf/25degC/*")):
        out += run_cell(SHARED, cell, [DEFAULT], pattern, leave_out=False,
                        start_names=tuple(STARTS) + LATE + LOADED + FIRST_SAMPLE)
    return out


def _starting(rows: list[dict], names: tuple[str, ...]) -> list[dict]:
    return [r for r in rows if r["start"] in names]


@pytest.fixture(scope="module")
def rows(every_start) -> list[dict]:
    return [r for r in _starting(every_start, tuple(STARTS)) if r.get("reference_relaxed")]


@needs_shared
def test_every_scored_file_and_start_is_run(rows):
    files = {(r["cell"], r["ambient"], r["file"]) for r in rows}
    assert len(files) == 4 + 7 + 7, sorted(files)  # LG 0 degC, LG 25 degC, Panasonic 25 degC
    assert len(rows) == 4 * len(files)


@needs_shared
def test_a_correct_start_beats_counting_wherever_the_stated_capacity_is_off(rows):
    """Started right, after 1 h the estimator beats counting with the stated capacity on every file where that
    capacity is measurably off (counting's own error above 1 %: every LG file).  Where the stated capacity
    happens to be the reference's (Panasonic: 2.9 Ah stated, 2.89-2.92 Ah measured, counting within
    0.0-0.4 %), the estimator is not better, and the README says so with its figures."""
    full = [r for r in rows if r["start"] == "full" and np.isfinite(r["rmse_1h_pct"])]
    off = [r for r in full if r["counting_rmse_1h_pct"] > 1.0]
    assert len(off) >= 10, len(off)
    worse = {f"{r['cell']}/{r['ambient']}/{r['file']}": (round(r["rmse_1h_pct"], 2), round(r["counting_rmse_1h_pct"], 2))
             for r in off if not r["rmse_1h_pct"] < r["counting_rmse_1h_pct"]}
    assert not worse, worse
    # and where counting is right, a correct start stays close: measured 0.28-1.92 % (median 0.88 %) on the
    # seven Panasonic files, where the count starts from the table's 3.00 Ah against a reference of 2.89-2.92
    right = np.array([r["rmse_1h_pct"] for r in full if r["counting_rmse_1h_pct"] <= 1.0])
    assert right.size == 7 and np.median(right) <= 1.2 and right.max() <= 2.5, right


@needs_shared
def test_the_capacity_learns_toward_the_reference_where_the_tables_is_off(rows):
    """Panasonic's table counts 3.00 Ah against these files' 2.88-2.92 Ah (its reference): the filter learns
    the capacity once the SOC is sure apart from the capacity's own share (core.soc_ekf).  Measured over
    its 28 runs: median |Q - Q_ref| 1.19 % (1.89 % while the gate was on the SOC's whole sigma, which the
    capacity's own share kept above 2 % on hwfet_a, cycle_1 and cycle_3); over all 72 runs mean 1.44 %."""
    err = {r["cell"]: [] for r in rows}
    for r in rows:
        err[r["cell"]].append(100 * abs(r["capacity_ah_estimated"] / r["capacity_ah_reference"] - 1))
    pan = np.array(err["panasonic-18650pf"])
    assert pan.size == 28 and np.median(pan) <= 1.5, np.sort(pan)
    assert np.mean(np.concatenate(list(err.values()))) <= 1.6, {k: np.mean(v) for k, v in err.items()}


@needs_shared
def test_soc_from_any_start_at_25_degc(rows):
    e30 = np.array([r["rmse_30min_pct"] for r in rows if r["ambient"] == "25degC"])
    assert e30.size == 4 * 14
    assert np.median(e30) <= 2.0, np.median(e30)
    assert np.mean(e30 <= 2.0) >= 0.95, np.sort(e30)  # measured 56 of 56 (53 before the diffusion prior)
    assert e30.max() <= 2.5, e30.max()  # measured 1.96 % (1.93 % before the slow-branch floor, 2.85 % before the diffusion prior)


@needs_shared
def test_soc_from_any_start_at_0_degc(rows):
    """The cold ambient: the identifier starts on a prior whose resistance is 1.5-2x low; the filter must not
    read that as SOC (before the load-scaled voltage noise: median 5.1 %, worst 10.5 %)."""
    e30 = np.array([r["rmse_30min_pct"] for r in rows if r["ambient"] == "0degC"])
    assert e30.size == 4 * 4
    assert np.median(e30) <= 2.0, np.median(e30)  # measured 1.22 % (1.23 % before the capacity's gate, 1.06 % before the slow-branch floor, 1.3 % before the prior at the start temperature, 1.7 % before the diffusion prior)
    assert np.mean(e30 <= 2.0) >= 0.9, np.sort(e30)  # measured 16 of 16 (14 before the slow-branch floor, 10 before the diffusion prior)
    assert e30.max() <= 2.5, e30.max()  # measured 1.91 % (2.54 % before the slow-branch floor, 2.74 % before the prior at the start temperature, 4.47 % before the diffusion prior)


def test_start_names_place_the_start_and_an_unknown_one_is_named():
    ref = np.linspace(1.0, 0.0, 1001)
    assert start_point("full", ref) == (0, 1.0)
    assert start_point("full-20", ref) == (0, 0.8)
    k, soc = start_point("mid-10", ref)
    assert k == 250 and soc == pytest.approx(ref[250] - 0.1)
    k, soc = start_point("at75-5", ref)
    assert k == 750 and soc == pytest.approx(ref[750] - 0.05)
    assert start_point("at10+20", ref) == (100, 1.0)  # clipped to full
    k, soc = start_point(check_start("ocv"), ref)  # read from the first sample's voltage by the estimator
    assert k == 0 and np.isnan(soc)
    k, soc = start_point(check_start("at50ocv"), ref)  # read from the voltage halfway through
    assert k == 500 and np.isnan(soc)
    for bad in ("late", "at100+5", "at50", "at50*5", "at100ocv", "atocv"):
        with pytest.raises(ValueError, match=re.escape(repr(bad))):
            check_start(bad)


@needs_shared
def test_starts_later_in_a_drive(every_start):
    """Halfway and three quarters into each scored file, 20 % and 5 % off either way: starts the README
    matrix does not use (its mid-file starts are at a quarter).  Measured 108 of 124 scored runs within 2 %
    (median 0.95 %; 61 of 68 halfway, 47 of 56 at three quarters, where the end of discharge weighs most),
    and better than counting with the stated capacity from the same start on 122 of 124 (before the OCV
    branch fix 59 of 124, before the diffusion prior 93, before the identifier's prior at the start
    temperature 102; 105 while a later start took the priors at the recording's first sample; 104 before
    the slow-branch floor)."""
    rows = _starting(every_start, LATE)
    scored = [r for r in rows if r.get("reference_relaxed") and np.isfinite(r["rmse_30min_pct"])]
    assert len(scored) >= 120, len(scored)
    e30 = np.array([r["rmse_30min_pct"] for r in scored])
    cnt = np.array([r["counting_rmse_30min_pct"] for r in scored])
    assert np.mean(e30 <= 2.0) >= 0.75, np.sort(e30)
    assert np.median(e30) <= 1.4, np.median(e30)
    assert np.mean(e30 < cnt) >= 0.95, np.mean(e30 < cnt)


@needs_shared
def test_starts_read_from_a_loaded_voltage_mid_drive(every_start):
    """A gateway started mid-drive without a state (``soc --start-s T --start-soc ocv``): 10, 25, 50 and 75 %
    into each scored file the SOC is read from the voltage under load.  Measured 57 of 67 within 2 % from
    30 min (median 0.91 %, worst 4.55 %; 55 of 67 before the slow-branch floor), better than counting with
    the stated capacity from the same start on 63; 33 of 67 (median 2.10 %, worst 11.93 %) while the whole overpotential was read as OCV and
    trusted to 3 %."""
    rows = _starting(every_start, LOADED)
    scored = [r for r in rows if r.get("reference_relaxed") and np.isfinite(r["rmse_30min_pct"])]
    assert len(scored) >= 60, len(scored)
    e30 = np.array([r["rmse_30min_pct"] for r in scored])
    cnt = np.array([r["counting_rmse_30min_pct"] for r in scored])
    assert np.mean(e30 <= 2.0) >= 0.7, np.sort(e30)
    assert np.median(e30) <= 1.6 and e30.max() <= 6.0, (np.median(e30), e30.max())
    assert np.mean(e30 < cnt) >= 0.85, np.mean(e30 < cnt)


def test_sigma_coverage_counts_the_samples_within_one_and_two_sigma():
    from bms_estimator.soc_matrix import _sigma_coverage

    ref = np.full(10, 0.5)
    soc = ref + np.array([0.0, 0.0, 0.005, -0.005, 0.015, -0.015, 0.03, -0.03, np.nan, 0.0])
    sigma = np.full(10, 0.01)
    sigma[9] = np.nan  # no sigma: not counted
    # from sample 2 on, 6 counted: |err| 0.005 twice within 1 sigma; 0.015 twice within 2; 0.03 beyond
    one, two = _sigma_coverage(soc, sigma, ref, 2)
    assert one == pytest.approx(100 * 2 / 6) and two == pytest.approx(100 * 4 / 6)
    assert np.isnan(_sigma_coverage(soc, np.full(10, np.nan), ref, 0)[0])


@needs_shared
def test_a_start_read_from_the_ocv_at_the_first_sample(every_start):
    """What the service does after a rest (and ``soc --start-soc ocv``): the SOC read from the first
    sample's voltage, every scored file starting after a charge (three Panasonic files under a 1.6-2.7 A
    load: the prior's ohmic drop taken out).  Measured 17 of 18 within 2 % from 30 min (median 0.60 %;
    0.56 % before the loaded reads, which read 0.92-0.96 then); the miss is Panasonic hwfet_a, 2.55 %
    (1.50 % when told it is full: from 35 min the identifier's slow branch and its c0 drift together, README)."""
    rows = _starting(every_start, FIRST_SAMPLE)
    scored = [r for r in rows if r.get("reference_relaxed")]
    assert len(scored) == 18, len(scored)
    starts = np.array([r["start_soc"] for r in scored])
    assert np.all((starts > 0.85) & (starts <= 1.0)), starts  # read near full: measured 0.97-1.00
    e30 = np.array([r["rmse_30min_pct"] for r in scored])
    assert np.sum(e30 <= 2.0) >= 16, np.sort(e30)
    assert np.median(e30) <= 1.0, np.median(e30)
    assert e30.max() <= 3.5, e30.max()


@needs_shared
@pytest.mark.parametrize("gain", [0.97, 1.03])
def test_a_cell_three_percent_off_its_tables_capacity(rows, gain):
    """How the figures carry to a cell that is not the one its OCV tables were measured on: every file's
    current times ``gain`` (``scripts/soc_matrix.py --current-gain``), so the reference's Q_ref moves with
    it and the tables' C/20 capacities do not.  Measured (README): 61 of 72 at 0.97 and 67 of 72 at 1.03
    within 2 % from 30 min (72 at 1.0), median 1.18 / 0.78 %, worst 2.78 / 2.57 %; the capacity learns
    little where the SOC filter's sigma stays above its 2 % gate (us06, LG mixed4)."""
    out = []
    for cell, pattern in (("lg-hg2", "lg-hg2/[02]*degC/*"), ("panasonic-18650pf", "panasonic-18650pf/25degC/*")):
        out += run_cell(SHARED, cell, [DEFAULT], pattern, leave_out=False, current_gain=gain)
    scored = [r for r in out if r.get("reference_relaxed")]
    assert len(scored) == len(rows) == 72
    base = {(r["cell"], r["file"], r["ambient"], r["start"]): r for r in rows}
    for r in scored:  # the reference counts the same scaled current
        b = base[(r["cell"], r["file"], r["ambient"], r["start"])]
        assert r["capacity_ah_reference"] == pytest.approx(gain * b["capacity_ah_reference"], rel=1e-9)
    e30 = np.array([r["rmse_30min_pct"] for r in scored])
    assert np.sum(e30 <= 2.0) >= 59, np.sort(e30)
    assert np.median(e30) <= 1.3, np.median(e30)
    assert e30.max() <= 3.5, e30.max()


@needs_shared
def test_a_current_sensor_offset_moves_counting_and_the_estimator_not_the_reference(rows):
    """A current sensor's zero offset (``scripts/soc_matrix.py --current-offset-a``): the estimator and plain
    counting read the current plus 50 mA, the reference stays the true charge.  Measured on LG 25 degC
    (README): 26 of 28 within 2 % from 30 min, worst 2.51 %, while counting from a correct start drifts to
    6.8-8.7 % after 1 h (3.9-5.2 % with an exact sensor)."""
    out = [r for r in run_cell(SHARED, "lg-hg2", [DEFAULT], "lg-hg2/25degC/*", leave_out=False,
                               current_offset_a=0.05) if r.get("reference_relaxed")]
    base = {(r["file"], r["start"]): r for r in rows if r["cell"] == "lg-hg2" and r["ambient"] == "25degC"}
    assert len(out) == len(base) == 28
    for r in out:
        b = base[(r["file"], r["start"])]
        assert r["capacity_ah_reference"] == b["capacity_ah_reference"]  # the reference reads the true current
        if r["start"] == "full":  # counting reads the offset: +50 mA is +1.7 % of 3 Ah an hour
            assert r["counting_rmse_1h_pct"] > b["counting_rmse_1h_pct"] + 1.0, (r["file"], r, b)
    e30 = np.array([r["rmse_30min_pct"] for r in out])
    assert np.sum(e30 <= 2.0) >= 25 and e30.max() <= 3.0, np.sort(e30)


def test_a_current_offset_that_is_not_finite_is_refused():
    with pytest.raises(ValueError, match="current_offset_a"):
        run_cell(SHARED, "lg-hg2", [DEFAULT], "nothing/matches/*", current_offset_a=float("nan"))


def test_a_jittered_table_moves_each_knot_by_its_sigma_and_stays_a_table():
    """``scripts/soc_matrix.py --ocv-jitter-mv``: every knot moved by an independent normal error, the
    same draw for the same seed and table, another for another seed; the curve still strictly increasing,
    its hysteresis and capacities as they were."""
    from bms_estimator.core.ocv import OcvCurve
    from bms_estimator.soc_matrix import Table, jittered

    soc = np.linspace(0.0, 1.0, 2001)
    curve = OcvCurve(soc, 3.0 + 1.2 * soc + 0.002 * soc**2, np.full(soc.size, 0.015), capacity_discharge_ah=2.9)
    table = Table("25degC", "c20", curve, 25.0)
    a, b, c = (jittered(table, 1e-4, s).curve for s in (1, 1, 2))
    np.testing.assert_array_equal(a.ocv_v, b.ocv_v)
    assert not np.array_equal(a.ocv_v, c.ocv_v)
    d = a.ocv_v - curve.ocv_v
    assert 0.8e-4 < np.std(d) < 1.2e-4 and abs(np.mean(d)) < 2e-5, (np.std(d), np.mean(d))
    assert np.all(np.diff(a.ocv_v) > 0)  # knots 0.6 mV apart, moved by 0.1 mV: still a table
    np.testing.assert_array_equal(a.hysteresis_v, curve.hysteresis_v)
    assert a.capacity_discharge_ah == curve.capacity_discharge_ah


def test_a_current_gain_that_is_not_positive_is_refused():
    with pytest.raises(ValueError, match="current_gain"):
        run_cell(SHARED, "lg-hg2", [DEFAULT], "nothing/matches/*", current_gain=0.0)
