"""The replay benchmark runs every path end to end (speed is printed by the bench, never asserted)."""

from __future__ import annotations

import pytest

from benchmarks.replay_speedup import bench_replay_speedup, daemon_available, prepare_frames


@pytest.fixture(scope="module")
def frames():
    return prepare_frames(40 / 3600, 7)  # 40 s of a 7-cell pack


@pytest.mark.parametrize("via", ["inline", "direct", "daemon"])
def test_bench_paths_process_every_frame(frames, via):
    if via == "daemon" and not daemon_available():
        pytest.skip("bms_estimator/service/daemon.py not available")
    r = bench_replay_speedup(40 / 3600, 7, via=via, frames=frames)
    assert r.via == via and r.notes == []
    assert r.frames == len(frames[0]) == 40 * (100 + 10 * 3 + 2)
    assert r.samples == 39  # the last period closes only with a later frame
    assert r.speedup > 0 and r.log_s == pytest.approx(40.0)
