"""The service's data path without the daemon: frames -> Pipeline -> Snapshot (its state, valid mask and
status counters), on the project DBC and the 6-cell pack of test_daemon."""

from __future__ import annotations

import numpy as np
import pytest
from structlog.testing import capture_logs

from bms_estimator.can.decoder import FrameDecoder
from bms_estimator.can.sampler import SampleAssembler, first_current, sample_current
from bms_estimator.core.soc import SocEstimator
from bms_estimator.core.sox import SoxEstimator
from bms_estimator.service.pipeline import Pipeline, Snapshot
from bms_estimator.service.schema import EstimatorState

from test_daemon import CAPACITY_AH, DB, N, current_frame, ocv, restamp, voltage_frame


def _pipeline(sox: bool = False) -> tuple[Pipeline, list[Snapshot]]:
    snaps: list[Snapshot] = []
    pipe = Pipeline(FrameDecoder(DB, "default", N), SampleAssembler(N, 1.0, 2.5),
                    SocEstimator(N, ocv(), CAPACITY_AH, 1.0), on_snapshot=snaps.append,
                    sox=SoxEstimator(N, 1.0) if sox else None, clock=lambda: 0.0, wall_clock=lambda: 0.0)
    return pipe, snaps


def _seconds(t0: float, n: int, volts, current_a: float = -1.0) -> list:
    """``n`` seconds of bus traffic from ``t0``: the current and every cell group each 0.1 s."""
    out = []
    for k in range(10 * n):
        t = t0 + 0.1 * k
        out.append(current_frame(t, current_a))
        for base in range(0, N, 3):
            out.append(voltage_frame(t + 0.002, base, volts[base:base + 3]))
    return out


def _feed(pipe: Pipeline, frames) -> None:
    for f in restamp(frames):
        pipe.process_frame(f)


def test_a_cell_that_never_sent_a_usable_voltage_degrades_the_pack_not_back_to_init():
    """Cell 5 reads 6 V (above valid_max 5.5 V, dropped) from the start: it has no SOC and is stale.
    The pack is DEGRADED, not INIT (INIT is "no SOC yet": no cell has one); one stale cell is counted,
    the other five are valid and have their SOC, and cell 5 publishes no voltage."""
    pipe, snaps = _pipeline()
    volts = [3.6] * (N - 1) + [6.0]
    _feed(pipe, _seconds(100.0, 4, volts) + [current_frame(104.0, -1.0)])
    assert [s.t_s for s in snaps] == [101.0, 102.0, 103.0, 104.0]
    last = snaps[-1]
    assert last.state == EstimatorState.DEGRADED and last.counters.estimator_state == int(EstimatorState.DEGRADED)
    assert last.valid.tolist() == [True] * (N - 1) + [False]
    assert last.counters.stale_cells == 1 and last.cells_valid == N - 1
    assert np.isfinite(last.cells["soc"][:-1]).all() and np.isnan(last.cells["soc"][-1])
    assert np.isnan(last.cells["voltage_v"][-1]) and last.soc.n == N - 1
    # the status frame's DecodeErrors: every dropped value, here cell 5's 6 V in 4 s of frames every 0.1 s
    assert last.counters.decode_errors == pipe.decoder.counters.out_of_range == 40


def test_status_counters_count_rewinds_as_time_jumps():
    """The status frame's TimeJumps is the sampler's time jumps plus its rewinds: a log that restarts
    200 s back (a rewind) and then a 50 s silence (a time jump) count 2."""
    pipe, snaps = _pipeline()
    volts = [3.6] * N
    _feed(pipe, _seconds(1000.0, 3, volts) + _seconds(800.0, 3, volts) + _seconds(853.0, 3, volts)
          + [current_frame(856.0, -1.0)])
    sc = pipe.sampler.counters
    assert (sc.rewinds, sc.time_jumps) == (1, 1)
    assert snaps[-1].counters.time_jumps == 2
    assert snaps[-1].state == EstimatorState.RUNNING


def test_a_second_without_a_valid_current_is_published_as_such():
    """The second [102, 103) carries only flagged-invalid current frames (CurrentInvalid = 1): its snapshot
    says ``current_valid`` False, no cell is valid (every one is counted stale) and the pack is DEGRADED;
    the seconds around it are RUNNING with a valid current."""
    pipe, snaps = _pipeline()
    volts = [3.6] * N
    frames = _seconds(100.0, 4, volts) + [current_frame(104.0, -1.0)]
    frames = [current_frame(f.timestamp, -1.0, invalid=True)
              if 102.0 <= f.timestamp < 103.0 and f.arbitration_id == frames[0].arbitration_id else f for f in frames]
    _feed(pipe, frames)
    by_t = {s.t_s: s for s in snaps}
    assert sorted(by_t) == [101.0, 102.0, 103.0, 104.0]
    lost = by_t[103.0]
    assert not lost.current_valid and not lost.valid.any()
    assert lost.state == EstimatorState.DEGRADED and lost.counters.stale_cells == N
    for t in (102.0, 104.0):
        assert by_t[t].current_valid and by_t[t].valid.all() and by_t[t].state == EstimatorState.RUNNING
    assert pipe.counters.samples_current_invalid == 1


def test_a_stale_cells_kept_voltage_counts_no_energy():
    """The SOX part gets the sample's valid mask: cell 5's voltage is NotAvailable after the first
    second, so it is stale from the end 104 s on (its last 3.6 V at 100.902 s, staleness 2.5 s) and its
    kept voltage counts no energy. At -1 A and 3.6 V every valid second discharges 3.6 / 3600 Wh: six
    for cells 0-4, three for cell 5."""
    pipe, snaps = _pipeline(sox=True)
    frames = []
    for k in range(60):
        t = 100.0 + 0.1 * k
        frames.append(current_frame(t, -1.0))
        frames.append(voltage_frame(t + 0.002, 0, [3.6] * 3))
        frames.append(voltage_frame(t + 0.002, 3, [36000, 36000, 36000 if t < 101.0 else 0xFFFF], raw=True))
    _feed(pipe, frames + [current_frame(106.0, -1.0)])
    assert [s.t_s for s in snaps] == [101.0, 102.0, 103.0, 104.0, 105.0, 106.0]
    assert [bool(s.valid[-1]) for s in snaps] == [True] * 3 + [False] * 3
    e = pipe.sox.energy_discharged_wh
    assert e[:-1] == pytest.approx(np.full(N - 1, 6 * 3.6 / 3600))
    assert e[-1] == pytest.approx(3 * 3.6 / 3600)


def test_a_wall_clock_step_whose_gap_never_came_does_not_hide_a_later_silence():
    """A step the daemon reported but the sampler bridged (1 s, within its 5 s ``max_gap_s``: no gap
    appears) is forgotten two periods later, so a real 100 s silence after it is rested over."""
    pipe, snaps = _pipeline()
    volts = [3.6] * N
    _feed(pipe, _seconds(100.0, 3, volts))
    pipe.clock_stepped(102.95, 1.0)
    _feed(pipe, _seconds(103.0, 5, volts) + _seconds(208.0, 3, volts) + [current_frame(211.0, -1.0)])
    assert pipe.counters.clock_steps == 1
    assert pipe.counters.rests == 1 and pipe.counters.rest_s == pytest.approx(100.0)


def test_the_estimator_is_fed_from_the_first_valid_current_on():
    """Before the first sample with a valid current there is nothing to count: those samples are not
    fed (the state stays as it started), so the estimator ends bit for bit where one fed the samples
    from the first valid current on ends (``first_current``, the fleet's rule), its identifier included.
    The first 3 s carry only flagged-invalid current frames."""
    pipe, snaps = _pipeline()
    frames = _seconds(100.0, 8, [3.6 + 0.01 * c for c in range(N)], current_a=-2.0)
    frames = [current_frame(f.timestamp, -2.0, invalid=True)
              if f.timestamp < 103.0 and f.arbitration_id == frames[0].arbitration_id else f for f in frames]
    _feed(pipe, frames + [current_frame(108.0, -2.0)])
    samples = [s.sample for s in snaps]
    k0 = first_current(np.array([s.current_a for s in samples]), np.array([s.current_valid for s in samples]))
    assert k0 == 3 and [s.state for s in snaps[:3]] == [EstimatorState.INIT] * 3
    ref = SocEstimator(N, ocv(), CAPACITY_AH, 1.0)
    for s in samples[k0:]:
        ref.update(sample_current(s.current_a, s.current_valid), s.cell_voltage_v, s.valid,
                   temperature_c=s.cell_temperature_c)
    got, want = pipe.estimator.state_dict(), ref.state_dict()
    assert got.keys() == want.keys()
    for key in want:
        np.testing.assert_array_equal(got[key], want[key], err_msg=key)


def test_a_lost_current_and_cells_gone_stale_are_said_once_each_way():
    """30 s of traffic: cells 3-5 send nothing in [105, 115), the pack current nothing in [120, 125).
    Both were only counted (``stale_cells``, ``samples_current_invalid``), nothing in the log said a
    cell had gone silent or that the SOC was being counted with a guessed current. Now one WARNING
    when it starts (naming the cells and the setting), one INFO when it ends, none in between."""
    pipe, snaps = _pipeline()
    volts = [3.6] * N
    frames = [f for f in _seconds(100.0, 30, volts) + [current_frame(130.0, -1.0)]
              if not (f.arbitration_id == voltage_frame(0, 0, volts[:3]).arbitration_id and f.data[0] == 3
                      and 105.0 <= f.timestamp < 115.0)
              and not (f.arbitration_id == current_frame(0, -1.0).arbitration_id and 120.0 <= f.timestamp < 125.0)]
    with capture_logs() as logs:
        _feed(pipe, frames)
    assert len(snaps) == 30
    said = [(e["log_level"], e["event"].split(":")[0], e.get("cells")) for e in logs
            if e["event"].startswith(("cells stale", "cells no longer stale", "pack current"))]
    assert said == [("warning", "cells stale", [3, 4, 5]), ("info", "cells no longer stale", [3, 4, 5]),
                    ("warning", "pack current lost", None), ("info", "pack current back", None)]
    stale = next(e for e in logs if e["event"].startswith("cells stale"))
    assert stale["config_key"] == "estimator.staleness_s" and stale["staleness_s"] == 2.5
    back = next(e for e in logs if e["event"].startswith("pack current back"))
    assert back["lost_samples"] == pipe.counters.samples_current_invalid > 0


def test_a_cell_flapping_at_its_staleness_edge_does_not_flood_the_log():
    """A cell refreshed just slower than ``staleness_s`` is stale every other sample: the first 20 changes
    are said, then one in 1000, with the count."""
    from bms_estimator.can.sampler import Sample

    pipe, _ = _pipeline()
    with capture_logs() as logs:
        for k in range(200):
            valid = np.ones(N, dtype=bool)
            valid[5] = k % 2 == 0
            pipe.tick(Sample(101.0 + k, -1.0, np.full(N, 3.6), np.full(N, 25.0), valid, 3.6 * N))
    said = [e for e in logs if e["event"].startswith(("cells stale", "cells no longer stale"))]
    assert len(said) == 20 and pipe.counters.stale_changes == 199
    assert said[-1]["stale_changes"] == 20


def test_the_per_cell_metrics_are_as_many_series_as_the_configuration_says():
    """``health.cell_metrics`` adds a fixed number of series per cell (what a fleet sizes Prometheus by: a
    192-cell pack times it, per pack). Its description said 3 (SOC, R0, capacity); the 10 s power limits,
    per direction, made it 5: 960 series for 192 cells, not 576."""
    import re
    from types import SimpleNamespace

    from bms_estimator.service.config import HealthConfig
    from bms_estimator.service.metrics import _ServiceCollector

    pipe, snaps = _pipeline(sox=True)
    _feed(pipe, _seconds(100.0, 4, [3.7] * N) + [current_frame(104.0, -1.0)])
    assert snaps and "p_discharge_max_10s_w" in snaps[-1].cells
    svc = SimpleNamespace(pipeline=pipe)
    per_cell = sum(1 for fam in _ServiceCollector(svc, True)._battery(svc) for s in fam.samples if "cell" in s.labels)
    assert sum(1 for fam in _ServiceCollector(svc, False)._battery(svc) for s in fam.samples if "cell" in s.labels) == 0
    said = re.search(r"(\d+) series per cell", HealthConfig.model_fields["cell_metrics"].description)
    assert said is not None and per_cell == int(said[1]) * N
