"""A stated capacity far from the cell's (pack.capacity_ah 5x the Panasonic cell's 2.9 Ah), through the
service's own pipeline (frames handed to it directly): one warning naming the cells, the bound and the
config key, once; the Prometheus gauge, the pack payload and the /healthz and systemctl status texts count the cells."""

from __future__ import annotations

import numpy as np
import pytest
from structlog.testing import capture_logs

from bms_estimator.service import schema
from bms_estimator.service.daemon import Service

from test_daemon import CAPACITY_AH, N, cached_rows, channel, make_cfg

SAMPLES = 120


def _run(tmp_path, capacity_ah: float):
    svc = Service(make_cfg(tmp_path, channel(), pack={"capacity_ah": capacity_ah}))
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


def test_a_5x_stated_capacity_warns_once_and_the_gauge_counts_every_cell(tmp_path):
    svc, logs, gauge = _run(tmp_path, 5 * CAPACITY_AH)
    warned = _bound_warnings(logs)
    assert len(warned) == 1, warned  # once per transition, not once per sample
    w = warned[0]
    assert w["cells"] == list(range(N)) and w["n_cells"] == N and w["bound"] == "low"
    assert w["config_key"] == "pack.capacity_ah" and "pack.capacity_ah" in w["event"]
    assert w["stated_ah"] == pytest.approx(5 * CAPACITY_AH) and w["bound_ah"] == pytest.approx(0.6 * 5 * CAPACITY_AH)
    assert len(gauge) == SAMPLES and all(g == N for g in gauge)
    snap = svc.pipeline.last
    assert schema.pack_payload(snap)["cells_capacity_at_bound"] == N
    np.testing.assert_array_equal(snap.cells["capacity_at_bound"], -1.0)  # each cell's MQTT payload says which bound
    # /healthz's body and the systemctl status line say it too
    assert svc._health_status().endswith(f"; {N} cell(s) with the capacity at a bound: check pack.capacity_ah")
    assert svc._status_line().endswith(f", {N} cell(s) with the capacity at a bound: check pack.capacity_ah")
    # the EKF's capacity sits at 0.6 x 14.5 Ah: the count runs 3x too slow and the SOC is not to be trusted
    np.testing.assert_allclose(svc.estimator.capacity_ah, 0.6 * 5 * CAPACITY_AH)


def test_the_right_capacity_never_warns(tmp_path):
    svc, logs, gauge = _run(tmp_path, CAPACITY_AH)
    assert not _bound_warnings(logs)
    assert len(gauge) == SAMPLES and all(g == 0 for g in gauge)
    assert schema.pack_payload(svc.pipeline.last)["cells_capacity_at_bound"] == 0
    assert "capacity" not in svc._health_status() and "capacity" not in svc._status_line()
