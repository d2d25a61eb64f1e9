"""The demo's frame source: the slices it hands to ``Service.feed`` and the frames in them."""

from __future__ import annotations

import math

import numpy as np
import pytest

from bms_estimator.demo.pipeline import FEED_SLICE, feed_slices, iter_frames
from bms_estimator.replay.encode_log import FrameArrays


def _frames(n: int, step_us: int = 10_000, t0_s: float = 5.0) -> FrameArrays:
    t_us = np.arange(n, dtype=np.int64) * step_us
    ids = np.where(np.arange(n) % 3 == 0, 0x10, 0x20).astype(np.int64)
    data = np.arange(n, dtype=np.uint64) * np.uint64(0x0101010101)
    return FrameArrays(t_us, ids, data, t0_s=t0_s, extended={0x10: True, 0x20: False})


def _covers(slices: list[tuple[int, int, float]], n: int) -> bool:
    return slices[0][0] == 0 and slices[-1][1] == n and all(a < b for a, b, _ in slices) and all(
        s[1] == t[0] for s, t in zip(slices, slices[1:]))


def test_max_speed_slices_are_fixed_size_and_due_at_once():
    fa = _frames(3 * FEED_SLICE + 5)
    slices = feed_slices(fa, math.inf)
    assert _covers(slices, len(fa)) and len(slices) == 4
    assert all(b - a == FEED_SLICE for a, b, _ in slices[:-1]) and all(due == 0.0 for *_, due in slices)


@pytest.mark.parametrize("speed", [1.0, 50.0, 1000.0])
def test_paced_slices_are_due_at_their_log_time_over_speed(speed):
    fa = _frames(20_000)  # 200 s of log at 10 ms
    slices = feed_slices(fa, speed, wall_step_s=0.02)
    assert _covers(slices, len(fa))
    rel_s = (fa.t_us - fa.t_us[0]) / 1e6
    for a, b, due in slices:
        assert due == pytest.approx(rel_s[a] / speed)  # a slice starts when its first frame is due
        assert rel_s[b - 1] - rel_s[a] < speed * 0.02  # and spans less than one wall step of log
    dues = [due for *_, due in slices]
    assert dues == sorted(dues)


def test_frames_carry_the_log_time_id_and_payload():
    fa = _frames(10)
    got = list(iter_frames(fa, 2, 7))
    want = list(fa.iter_messages(2, 7))
    assert len(got) == 5
    for f, m in zip(got, want):
        assert (f.timestamp, f.arbitration_id, f.is_extended_id, bytes(f.data)) == (
            m.timestamp, m.arbitration_id, m.is_extended_id, bytes(m.data))
        assert not f.is_error_frame and not f.is_remote_frame
    assert feed_slices(FrameArrays(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.uint64)), 10.0) == []


def test_a_slow_speed_makes_no_more_slices_than_frames():
    fa = _frames(1000, step_us=1_000_000)  # 1000 s of log, a frame a second
    slices = feed_slices(fa, 0.001, wall_step_s=0.02)  # a step of 20 us of log: one frame each
    assert _covers(slices, len(fa)) and len(slices) == len(fa)
    assert slices[-1][2] == pytest.approx(999 / 0.001)
