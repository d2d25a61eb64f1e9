"""The bench helper runs and measures the realistic frame mix (no timing asserts)."""

from __future__ import annotations

import math

from benchmarks.can_frames import bench, bench_frames_per_s, synth_frames
from bms_estimator.can.decoder import FrameDecoder
from bms_estimator.can.sampler import SampleAssembler


def test_bench_runs_and_reports_a_rate():
    rate = bench_frames_per_s(n_cells=20, seconds=0.1)
    assert math.isfinite(rate) and rate > 0


def test_synthetic_mix_is_the_documented_one(project_db, foxbms_db):
    # project DBC, 200 cells: 100 current frames/s + 67 voltage frames every 100 ms + 34 temperature frames/s
    r = bench(200, 0.05, stream_s=2.0)
    assert r.frames_per_bus_second == 100 + 67 * 10 + 34
    assert r.samples > 0
    # foxBMS, 200 cells: current + pack voltage (separate frames), 4 cells and 6 sensors per frame, 180 sensors
    r = bench(200, 0.05, db=foxbms_db, mapping="foxbms", stream_s=2.0)
    assert r.frames_per_bus_second == 100 + 100 + 50 * 10 + 30


def test_synthetic_stream_decodes_to_complete_valid_samples(project_db):
    n = 10
    frames = synth_frames(project_db, "default", n, 3.0)
    dec, smp = FrameDecoder(project_db, "default", n), SampleAssembler(n)
    out = []
    for m in frames:
        out += smp.feed_frame(dec.decode(m), m.timestamp)
    assert len(out) == 2 and all(s.valid.all() and s.current_valid for s in out)
    assert not any(math.isnan(x) for s in out for x in s.cell_temperature_c)
    assert dec.counters.errors == 0
