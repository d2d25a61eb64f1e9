"""A capacity estimate at its bound, through the service's own pipeline (frames handed to it directly): one
warning naming the cells, the bound and the config key, once; the Prometheus gauge, the pack payload and the
/healthz and systemctl status texts count the cells.  A stated capacity far from the one the cell's OCV table
carries is refused at start, and the built-in sample curve's capacity is never counted with."""

from __future__ import annotations

import numpy as np
import pytest
from structlog.testing import capture_logs

from bms_estimator.service import schema
from bms_estimator.service.daemon import Service

from test_daemon import CAPACITY_AH, N, cached_rows, channel, make_cfg

SAMPLES = 120


def _run(tmp_path, capacity_ah: float, **over):
    svc = Service(make_cfg(tmp_path, channel(), pack={"capacity_ah": capacity_ah}, **over))
    svc.pipeline.hooks.clear()  # the daemon's outputs (MQTT, CAN, state saves) need its event loop
    gauge = []
    svc.pipeline.add_hook(lambda snap: gauge.append(svc.metrics.registry.get_sample_value("bms_cells_capacity_at_bound")))
    with capture_logs() as logs:
        for m in cached_rows(0, SAMPLES):
            svc.pipeline.process_frame(m)
    assert svc.pipeline.counters.tick_errors == 0
    return svc, logs, gauge


def _bound_warnings(logs):
    return [r for r in logs if r["log_level"] == "warning" and "capacity estimate at its" in r["event"]]


def test_a_capacity_at_its_bound_warns_once_and_the_gauge_counts_every_cell(tmp_path):
    """The plumbing, on a low bound above the table's 2.997 Ah (``capacity_bounds = [1.05, 1.4]`` x 2.9 Ah):
    the EKF's first step clips the count up to it, and it stays there, as a capacity learnt down to its bound
    over hours would."""
    svc, logs, gauge = _run(tmp_path, CAPACITY_AH, estimator={"core": {"capacity_bounds": [1.05, 1.4]}})
    warned = _bound_warnings(logs)
    assert len(warned) == 1, warned  # once per transition, not once per sample
    w = warned[0]
    assert w["cells"] == list(range(N)) and w["n_cells"] == N and w["bound"] == "low"
    assert w["config_key"] == "pack.capacity_ah" and "pack.capacity_ah" in w["event"]
    assert w["stated_ah"] == pytest.approx(CAPACITY_AH) and w["bound_ah"] == pytest.approx(1.05 * CAPACITY_AH)
    assert len(gauge) == SAMPLES and all(g == N for g in gauge)
    snap = svc.pipeline.last
    assert schema.pack_payload(snap)["cells_capacity_at_bound"] == N
    np.testing.assert_array_equal(snap.cells["capacity_at_bound"], -1.0)  # each cell's MQTT payload says which bound
    # /healthz's body and the systemctl status line say it too
    assert svc._health_status().endswith(f"; {N} cell(s) with the capacity at a bound: check pack.capacity_ah")
    assert svc._status_line().endswith(f", {N} cell(s) with the capacity at a bound: check pack.capacity_ah")
    np.testing.assert_allclose(svc.estimator.capacity_ah, 1.05 * CAPACITY_AH)


def test_a_stated_capacity_far_from_the_tables_counts_with_the_stated_one_and_says_so(tmp_path):
    """pack.capacity_ah 5x the C/20 capacity of the Panasonic table it names (2.997 Ah): not that table's cell
    (one cell of a parallel group, or a wrong setting). Before, the count started on the table's 2.997 Ah and
    the EKF's first step clipped it to 0.6 x 14.5 Ah, a capacity nobody stated; now it counts with the stated
    14.5 Ah and says so once at start, naming both capacities and the key."""
    with capture_logs() as logs:
        svc = Service(make_cfg(tmp_path, channel(), pack={"capacity_ah": 5 * CAPACITY_AH}))
    notes = [r for r in logs if r["log_level"] == "warning" and "times the C/20 capacity" in r["event"]]
    assert len(notes) == 1, logs
    assert "pack.capacity_ah 14.5 Ah is 4.84 times the C/20 capacity 2.997 Ah of pack.ocv_csv" in notes[0]["event"]
    np.testing.assert_array_equal(svc.estimator.capacity_ah, 5 * CAPACITY_AH)
    # within 2x the table's capacity is counted with, as before (the scale SOC is defined on)
    with capture_logs() as logs:
        svc = Service(make_cfg(tmp_path, channel(), pack={"capacity_ah": 1.5 * CAPACITY_AH}))
    assert not [r for r in logs if "times the C/20 capacity" in r["event"]]
    np.testing.assert_allclose(svc.estimator.capacity_ah, 2.997, atol=5e-4)


def test_the_built_in_curve_counts_with_the_stated_capacity(tmp_path):
    """Without pack.ocv_csv the built-in sample curve gives the OCV's shape only: a 50 Ah pack counts with
    50 Ah (it counted with the sample cell's 3.0 Ah clipped to 30 Ah before), and nothing is at a bound."""
    cfg = make_cfg(tmp_path, channel(), pack={"capacity_ah": 50.0})
    cfg.pack.ocv_csv = None
    svc = Service(cfg)
    np.testing.assert_array_equal(svc.estimator.capacity_ah, 50.0)
    assert not svc.estimator.capacity_at_bound.any()


def test_the_right_capacity_never_warns(tmp_path):
    svc, logs, gauge = _run(tmp_path, CAPACITY_AH)
    assert not _bound_warnings(logs)
    assert len(gauge) == SAMPLES and all(g == 0 for g in gauge)
    assert schema.pack_payload(svc.pipeline.last)["cells_capacity_at_bound"] == 0
    assert "capacity" not in svc._health_status() and "capacity" not in svc._status_line()


def test_the_c0_voltage_lines_capacity_is_named_in_the_warning(tmp_path):
    """On the c0 method the flag can come from its voltage line (core.soc, "At a bound": a stated capacity 5x the
    cell's with tables that carry none); the one warning then names the capacity that line reads."""
    svc, logs, _ = _run(tmp_path, CAPACITY_AH, estimator={"core": {"soc_method": "c0"}})
    assert not _bound_warnings(logs)
    est = svc.estimator
    est.capacity_voltage_ah = np.full(N, 0.58)  # as the line would read with 5x the cell's capacity stated
    est.capacity_at_bound = est._capacity_side_c0(*est._capacity_line()[1:])
    with capture_logs() as logs:
        svc.pipeline._log_capacity_bounds()
        svc.pipeline._log_capacity_bounds()  # nothing new: nothing said
    warned = _bound_warnings(logs)
    assert len(warned) == 1 and warned[0]["cells"] == list(range(N)) and warned[0]["bound"] == "low"
    assert warned[0]["voltage_line_ah"] == pytest.approx(0.58)


def test_sop_ratings_left_at_an_18650s_are_named_for_a_cell_of_another_size(tmp_path):
    """estimator.sop's current ratings default to an 18650's 20 A / 6 A: a 50 Ah cell's limits sat at 0.4 C /
    0.12 C with nothing to say so.  Now one warning at start names them in C; given ratings, or a cell near
    3 Ah (CAPACITY_AH 2.9), none."""
    def notes(**kw):
        with capture_logs() as logs:
            Service(make_cfg(tmp_path, channel(), **kw))
        return [r for r in logs if r["log_level"] == "warning" and "18650's ratings" in r["event"]]

    big = {"capacity_ah": 50.0, "ocv_csv": None}
    warned = notes(pack=big)
    assert len(warned) == 1 and warned[0]["config_key"] == "estimator.sop"
    assert ("estimator.sop.i_discharge_max_a and estimator.sop.i_charge_max_a not given: the defaults 20 A / 6 A "
            "are a 3 Ah 18650's ratings, 0.4 C / 0.12 C of pack.capacity_ah 50") in warned[0]["event"]
    estimator = {"sample_period_s": 1.0, "staleness_s": 2.5,
                 "sop": {"i_discharge_max_a": 150.0, "i_charge_max_a": 50.0}}
    assert notes(pack=big, estimator=estimator) == []
    assert notes() == []


def test_the_shipped_dbc_is_named_when_it_is_not_the_cells_size(tmp_path):
    """A 50 Ah cell on the project DBC (an 18650's ranges: its C1 of ~30,000 F went out as 13,106.8 F) is told to
    use can.dbc = "large-cell" at start; a 2.9 Ah cell on that variant (R0 ends at 16.38 mOhm) is told to leave it
    unset; the right DBC for the cell, or CAN output off, says nothing."""
    def notes(**kw):
        with capture_logs() as logs:
            Service(make_cfg(tmp_path, channel(), **kw))
        return [r for r in logs if r["log_level"] == "warning" and r.get("config_key") == "can.dbc"]

    big = {"capacity_ah": 50.0, "ocv_csv": None}
    warned = notes(pack=big)
    assert len(warned) == 1 and 'set can.dbc = "large-cell"' in warned[0]["event"]
    assert notes(pack=big, can={"dbc": "large-cell"}) == []
    small = notes(can={"dbc": "large-cell"})
    assert len(small) == 1 and "leave can.dbc unset" in small[0]["event"]
    assert notes() == []
