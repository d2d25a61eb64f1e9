"""Drives stacked as the cells of one estimator give each drive its own results, bit for bit."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from bms_estimator.data import load_recording
from bms_estimator.fleet.batch import stack_groups
from bms_estimator.fleet.drive import _stack_factory, _stack_sox_factory, service_for, run_drive, run_drives
from bms_estimator.fleet.estimate import estimate_drive
from bms_estimator.fleet.samples import SampleArrays
from bms_estimator.fleet.stack import StackError, estimate_stacked
from bms_estimator.replay.encode_log import encode_log

N_CELLS = 3
SAMPLES = Path(__file__).parents[2] / "bms_estimator" / "samples"
SRC = SAMPLES / "lg-hg2_25degC_udds_1s.csv.gz"


@pytest.fixture(scope="module")
def svc(tmp_path_factory):
    d = tmp_path_factory.mktemp("stack")
    cfg = d / "config.toml"
    cfg.write_text(f'[pack]\nn_cells = {N_CELLS}\ncapacity_ah = 3.0\nocv_csv = "{SAMPLES / "lg-hg2_25degC_ocv.csv"}"\n'
                   '[can]\ninterface = "virtual"\n[mqtt]\nenabled = false\n')
    return service_for(str(cfg)), cfg


def _drive(base: SampleArrays, a: int, b: int, rng, stale: float = 0.0, bad_rows: int = 0,
           nan_frac: float = 0.0) -> SampleArrays:
    """Samples a..b of ``base`` with the anomalies the sampler produces: current-invalid rows, stale cells
    (runs of invalid samples), lost voltage and temperature readings."""
    k = b - a
    cur_ok = base.current_valid[a:b].copy()
    cur_ok[rng.integers(0, k, bad_rows)] = False
    valid = base.valid[a:b].copy()
    for _ in range(int(stale * k)):
        r, c, n = rng.integers(0, k), rng.integers(0, base.n_cells), rng.integers(1, 40)
        valid[r:r + n, c] = False
    volts = base.cell_voltage_v[a:b].copy()
    volts[rng.random(volts.shape) < nan_frac] = np.nan
    temps = base.cell_temperature_c[a:b].copy()
    temps[rng.random(temps.shape) < nan_frac] = np.nan
    return dataclasses.replace(base, t_s=base.t_s[a:b], current_a=base.current_a[a:b], current_valid=cur_ok,
                               current_coverage=base.current_coverage[a:b], cell_voltage_v=volts,
                               cell_temperature_c=temps, valid=valid & cur_ok[:, None] & np.isfinite(volts),
                               pack_voltage_v=base.pack_voltage_v[a:b])


def _pack(seconds: int) -> SampleArrays:
    """The shipped LG HG2 UDDS recording as a 3-cell pack (cells a few mV and 0.5 degC apart)."""
    one = SampleArrays.from_recording(load_recording(SRC, resample_s=1.0), 1.0)
    k = min(seconds, len(one))
    offset = np.array([0.0, 0.004, -0.003])
    volts = one.cell_voltage_v[:k] + offset
    temps = np.full((k, N_CELLS), 25.0) + np.array([0.0, 0.5, -0.5])
    return SampleArrays(t_s=one.t_s[:k], current_a=one.current_a[:k], current_valid=one.current_valid[:k],
                        current_coverage=one.current_coverage[:k], cell_voltage_v=volts, cell_temperature_c=temps,
                        valid=np.repeat(one.valid[:k], N_CELLS, axis=1), pack_voltage_v=volts.sum(axis=1), period_s=1.0)


def _mixed_drives(base: SampleArrays, rng, pulses: bool = False) -> list[SampleArrays]:
    """Five drives out of ``base``: the whole, two shorter ones with stale cells, lost readings and
    current-invalid samples, a one-sample drive and one without a valid current; with ``pulses``,
    steps out of rest (:func:`_pulses`) in the first three, at other times in each."""
    k = len(base)
    drives = [_drive(base, 0, k, rng),
              _drive(base, 300, k - 700, rng, stale=0.05, bad_rows=5, nan_frac=0.003),
              _drive(base, 900, 2600, rng, stale=0.15, bad_rows=20, nan_frac=0.01),
              _drive(base, 50, 51, rng),
              _drive(base, 10, 40, rng, bad_rows=200)]
    if pulses:
        starts = (range(400, k - 100, 170), (200, 500, 900), range(150, 1600, 230))
        drives[:3] = [_pulses(d, at) for d, at in zip(drives[:3], starts)]
    return drives


def _assert_same(a, b) -> None:
    assert a.cells.keys() == b.cells.keys()
    for key in a.cells:
        assert np.array_equal(a.cells[key], b.cells[key], equal_nan=True), key
    assert a.state.keys() == b.state.keys()
    for key in a.state:
        assert np.shape(a.state[key]) == np.shape(b.state[key]), key
        assert np.array_equal(a.state[key], b.state[key], equal_nan=True), key
    assert np.array_equal(a.t_s, b.t_s) and np.array_equal(a.valid, b.valid)


def test_stacked_drives_give_each_drive_its_solo_results(svc):
    """Different lengths and anomalies per drive (so at many steps one drive's cells learn and another's
    do not, which moved the shared RLS error-window head and trace limit before they were kept per drive),
    a one-sample drive and a drive without a single valid current: every output and the final state equal."""
    service, _ = svc
    base = _pack(4000)
    rng = np.random.default_rng(7)
    drives = _mixed_drives(base, rng)
    assert not (drives[4].current_valid.any())  # no update at all: the fresh estimator's values throughout
    solo = [estimate_drive(d, service._new_estimator()) for d in drives]
    stacked = estimate_stacked(drives, _stack_factory(service))
    assert len(stacked) == len(drives)
    for a, b in zip(solo, stacked):
        _assert_same(a, b)
    # the drives really ran as one estimator and differ from each other (not a trivial equality)
    assert not np.array_equal(solo[0].cells["soc"][-1], solo[1].cells["soc"][-1])
    assert np.isfinite(solo[2].cells["r0_ohm"][-1]).all()


def _pulses(d: SampleArrays, starts, rest_s: int = 65, pulse_s: int = 35, current_a: float = -1.2) -> SampleArrays:
    """``d`` with, from each of ``starts``, ``rest_s`` samples at rest then a ``current_a`` step held
    ``pulse_s`` samples (the voltage held, then falling 50 mOhm x I and 0.5 mV/s): the steps out of
    rest from which the SOX part learns its D-second resistance (core.sop_residual)."""
    cur, volts = d.current_a.copy(), d.cell_voltage_v.copy()
    for a in starts:
        v0 = volts[a - 1]
        cur[a:a + rest_s] = 0.0
        volts[a:a + rest_s] = v0
        b = a + rest_s
        cur[b:b + pulse_s] = current_a
        volts[b:b + pulse_s] = v0 + 0.05 * current_a - 0.0005 * np.arange(1, pulse_s + 1)[:, None]
    return dataclasses.replace(d, current_a=cur, cell_voltage_v=volts)


def _assert_same_sox(a, b) -> None:
    """Every output and the final state (:func:`_assert_same`), and the SOX part's pack figures and drive energy."""
    _assert_same(a, b)
    assert a.sox_keys and a.sox_keys == b.sox_keys
    assert a.pack.keys() == b.pack.keys() and len(a.pack) == 19
    for key in a.pack:
        assert np.array_equal(a.pack[key], b.pack[key], equal_nan=True), key
    assert a.energy_wh.keys() == b.energy_wh.keys()
    for key in a.energy_wh:
        assert np.array_equal(a.energy_wh[key], b.energy_wh[key]), key
    assert a.pack_energy_wh == b.pack_energy_wh


def test_stacked_sox_drives_give_each_drive_its_solo_results(svc):
    """With the SOP/SOE/SOH part (batch --sox): drives of different lengths with stale cells, lost readings,
    current-invalid samples, one that ends early and one without an update; steps out of rest in each at other
    times, so that one drive scores a learnt-resistance window while another's learnt dR ages or leaves its SOC
    band (which refreshed every drive's correction before it was kept per drive). Every per-cell SOX output, every
    pack figure, the drive energy and the final state (SOX part included) equal to the solo run, no tolerance."""
    service, _ = svc
    base = _pack(4000)
    rng = np.random.default_rng(11)
    drives = _mixed_drives(base, rng, pulses=True)
    solo = [estimate_drive(d, service._new_estimator(), sox=service._new_sox()) for d in drives]
    stacked = estimate_stacked(drives, _stack_factory(service), _stack_sox_factory(service))
    assert len(stacked) == len(drives)
    for a, b in zip(solo, stacked):
        _assert_same_sox(a, b)
    # not a trivial equality: windows were scored (dR learnt) in the pulsed drives, the limits differ between
    # drives, and a drive without an update has no figure at all
    for d in solo[:2]:
        assert np.isfinite(d.state["sox.residual.dr_ohm"]).any()
    assert solo[0].pack["p_discharge_max_10s_w"][-1] != solo[1].pack["p_discharge_max_10s_w"][-1]
    assert np.isnan(solo[4].pack["i_discharge_max_10s_a"]).all() and np.isnan(solo[4].cells["soh_resistance"]).all()


def test_a_drive_alone_with_sox_runs_as_its_solo_run(svc):
    """One drive with SOX (every batch of one log, and the last group of an uneven split) is a group of one:
    it asked the SOX part for the pack figures of groups it never set, failed, and fell back to running 'one by
    one' with a warning. Now its own pack figures, equal to the solo run, no tolerance; both packs, one and
    several cells."""
    service, _ = svc
    base = _pulses(_drive(_pack(1500), 0, 1500, np.random.default_rng(3)), range(200, 1400, 170))
    for d in (base, _first_cell(base)):
        n = d.n_cells
        solo = estimate_drive(d, _stack_factory(service)(n), sox=_stack_sox_factory(service)(n))
        (alone,) = estimate_stacked([d], _stack_factory(service), _stack_sox_factory(service))
        _assert_same_sox(solo, alone)
        assert np.isfinite(alone.pack["p_discharge_max_10s_w"][-1])


def test_a_stacked_drive_carries_on_like_a_solo_one(svc):
    """The state a stacked drive ends with resumes a next drive exactly as the solo state does (chaining)."""
    service, _ = svc
    base = _pack(3000)
    rng = np.random.default_rng(3)
    first, other = _drive(base, 0, 1200, rng, stale=0.05), _drive(base, 100, 2900, rng)
    nxt = _drive(base, 1200, 3000, rng)
    stacked = estimate_stacked([first, other], _stack_factory(service))[0]
    solo = estimate_drive(first, service._new_estimator())
    est_a, est_b = service._new_estimator(), service._new_estimator()
    est_a.load_state_dict(solo.state)
    est_b.load_state_dict(stacked.state)
    _assert_same(estimate_drive(nxt, est_a), estimate_drive(nxt, est_b))


def _first_cell(d: SampleArrays) -> SampleArrays:
    """``d`` as the drive of a one-cell pack (its first cell)."""
    return dataclasses.replace(d, cell_voltage_v=d.cell_voltage_v[:, :1], cell_temperature_c=d.cell_temperature_c[:, :1],
                               valid=d.valid[:, :1])


@pytest.mark.parametrize("sox", [False, True], ids=["plain", "sox"])
def test_stacked_one_cell_drives_give_each_drive_its_solo_results(svc, sox):
    """Drives of a one-cell pack (single-cell recordings) stacked as the cells of one estimator: the
    width-1 arithmetic a one-cell estimator gets alone (numpy's dot and sum kernels for one contiguous
    column, core/rls.py, core/soe.py) kept per cell. Different lengths, current-invalid samples, stale
    and lost readings, pulses out of rest (the SOX part's learnt resistance), a one-sample drive and one
    without an update: every output, pack figure, the drive energy and the final state equal, no tolerance."""
    service, _ = svc
    base = _pack(4000)
    rng = np.random.default_rng(5)
    drives = [_first_cell(d) for d in _mixed_drives(base, rng, pulses=sox)]
    one = service_for(str(svc[1]), n_cells=1)
    make_sox = _stack_sox_factory(one) if sox else None
    solo = [estimate_drive(d, one._new_estimator(), sox=one._new_sox() if sox else None) for d in drives]
    stacked = estimate_stacked(drives, _stack_factory(one), make_sox)
    assert len(stacked) == len(drives)
    for a, b in zip(solo, stacked):
        (_assert_same_sox if sox else _assert_same)(a, b)
    # not a trivial equality: the drives differ from each other, and the identifier ran
    assert not np.array_equal(solo[0].cells["soc"][-1], solo[1].cells["soc"][-1])
    assert np.isfinite(solo[2].cells["r0_ohm"][-1]).all() and solo[0].state["id.rls.initialised"].all()


def test_drives_of_other_packs_are_refused(svc):
    service, _ = svc
    base = _pack(100)
    with pytest.raises(StackError, match="same cells"):
        estimate_stacked([base, _first_cell(base)], _stack_factory(service))


@pytest.mark.parametrize("sox", [False, True], ids=["plain", "sox"])
def test_run_drives_writes_what_run_drive_writes(svc, tmp_path, sox):
    """The batch task: stacked logs (and a bad one among them) give the solo Parquet and summary; with SOX
    also the solo pack Parquet and pack summary."""
    import pyarrow.parquet as pq

    _, cfg = svc
    logs = []
    for i, dur in enumerate((300.0, 180.0, 240.0)):
        p = tmp_path / "logs" / f"car{i}" / "drive.log"
        p.parent.mkdir(parents=True)
        encode_log(SRC, p, N_CELLS, initial_soc=0.9 - 0.1 * i, duration_s=dur, reference_capacity_ah=3.0, seed=i)
        logs.append((str(p), f"car{i}"))
    bad = tmp_path / "logs" / "car9" / "empty.log"
    bad.parent.mkdir()
    bad.write_bytes(b"")
    logs.insert(1, (str(bad), "car9"))
    stacked = run_drives(logs, str(cfg), tmp_path / "stacked", sox=sox)
    assert [r.status for r in stacked] == ["ok", "skipped", "ok", "ok"]
    assert "empty log" in stacked[1].error
    assert all(r.counters["stacked_with"] == 3 for r in stacked if r.status == "ok")
    for (log, vehicle), got in zip(logs, stacked):
        want = run_drive(log, str(cfg), tmp_path / "solo", vehicle, sox=sox)[0]
        assert want.status == got.status
        assert want.cells.keys() == got.cells.keys() and want.samples == got.samples
        for key, values in want.cells.items():
            assert np.array_equal(values, got.cells[key], equal_nan=True), key
        assert want.pack.keys() == got.pack.keys() and bool(want.pack) == (sox and want.status == "ok")
        for key, value in want.pack.items():
            assert np.array_equal(value, got.pack[key], equal_nan=True), key
        if want.status == "ok":
            _assert_same_table(pq.read_table(want.parquet), pq.read_table(got.parquet))
            if sox:
                _assert_same_table(pq.read_table(want.pack_parquet), pq.read_table(got.pack_parquet))


def _assert_same_table(a, b) -> None:
    """Two Parquet tables equal column by column, NaN where NaN (pyarrow's ``equals`` takes NaN as unequal)."""
    assert a.schema == b.schema
    for name in a.column_names:
        x, y = a.column(name).to_numpy(), b.column(name).to_numpy()
        assert np.array_equal(x, y, equal_nan=x.dtype.kind == "f"), name


def test_stack_groups_keep_every_worker_busy():
    logs = [f"/fleet/car{i}/d.log" for i in range(10)]
    assert [len(g) for g in stack_groups(logs, 4, 1)] == [4, 4, 2]
    assert [len(g) for g in stack_groups(logs, 4, 4)] == [3, 3, 3, 1]
    assert [len(g) for g in stack_groups(logs, 1, 1)] == [1] * 10
    assert [log for g in stack_groups(logs, 4, 2) for log, _ in g] == logs
    assert stack_groups(logs, 4, 2)[0][0] == ("/fleet/car0/d.log", "car0")
    assert stack_groups([], 4, 2) == []
