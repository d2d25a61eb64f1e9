"""SampleAssembler: frame-time grid, charge-exact current, staleness, time anomalies."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from structlog.testing import capture_logs

from bms_estimator.can.decoder import Event, EventKind
from bms_estimator.can.sampler import Sample, SampleAssembler

I, PV, V, T = EventKind.CURRENT, EventKind.PACK_VOLTAGE, EventKind.CELL_VOLTAGE, EventKind.CELL_TEMPERATURE
TICK = 1.0 / 128  # binary-exact time step, so shifted/scaled streams are bit-identical


def stream(n_cells: int, seconds: float, t0: float = 0.0, seed: int = 0) -> list[tuple[float, list[Event]]]:
    """(timestamp, events of one frame) list: current every 2 ticks, each cell every 13 ticks."""
    rng = np.random.default_rng(seed)
    out = []
    n_ticks = int(seconds / TICK)
    for k in range(n_ticks):
        t = t0 + k * TICK
        if k % 2 == 0:
            out.append((t, [Event(I, -1, float(rng.integers(-400, 400)) / 8)]))
        if k % 13 == 0:
            out.append((t, [Event(V, c, 3.0 + float(rng.integers(0, 1000)) / 1024) for c in range(n_cells)]
                        + [Event(PV, -1, 400.0)]))
        if k % 128 == 5:
            out.append((t, [Event(T, c, 20.0 + c) for c in range(n_cells)]))
    return out


def run(sampler: SampleAssembler, frames, *, per_event: bool = False) -> list[Sample]:
    out: list[Sample] = []
    for t, events in frames:
        if per_event:
            for e in events:
                out += sampler.feed(e, t)
        else:
            out += sampler.feed_frame(events, t)
    return out


def same(a: list[Sample], b: list[Sample], *, t_scale: float = 1.0, t_shift: float = 0.0) -> None:
    assert len(a) == len(b) > 0
    for x, y in zip(a, b):
        assert y.t_s == x.t_s * t_scale + t_shift
        assert (x.current_a == y.current_a) or (math.isnan(x.current_a) and math.isnan(y.current_a))
        np.testing.assert_array_equal(x.cell_voltage_v, y.cell_voltage_v)
        np.testing.assert_array_equal(x.cell_temperature_c, y.cell_temperature_c)
        np.testing.assert_array_equal(x.valid, y.valid)
        assert x.current_valid == y.current_valid
        assert x.pack_voltage_v == y.pack_voltage_v or (math.isnan(x.pack_voltage_v) and math.isnan(y.pack_voltage_v))


# ------------------------------------------------------------ frame time only
def test_output_depends_only_on_frame_timestamps():
    frames = stream(5, 20.0, t0=100.0)
    ref = run(SampleAssembler(5), frames)
    assert len(ref) == 19
    # event by event or frame by frame: identical
    same(ref, run(SampleAssembler(5), frames, per_event=True))
    # the same log starting 1024 periods later: identical apart from t_s
    shifted = [(t + 1024.0, ev) for t, ev in frames]
    same(ref, run(SampleAssembler(5), shifted), t_shift=1024.0)
    # time axis and every time constant scaled by 2: identical values
    scaled = [(2 * t, ev) for t, ev in frames]
    s2 = SampleAssembler(5, period_s=2.0, staleness_s=5.0, current_hold_s=1.0, max_gap_s=10.0,
                         rewind_s=10.0, temperature_staleness_s=60.0)
    same(ref, run(s2, scaled), t_scale=2.0)


def test_grid_is_anchored_on_whole_periods_and_emits_on_the_next_frame():
    s = SampleAssembler(1, period_s=1.0)
    assert s.next_boundary_s is None
    assert s.feed(Event(V, 0, 3.3), 10.25) == []
    assert s.next_boundary_s == 12.0  # first complete period is [11, 12)
    for k in range(1, 40):  # current every 50 ms up to 11.95 s
        assert s.feed(Event(I, -1, 1.0), 10.0 + k * 0.05) == []
    out = s.feed(Event(I, -1, 2.0), 12.0)  # a frame exactly on the boundary closes the period
    assert [o.t_s for o in out] == [12.0]
    assert out[0].cell_voltage_v[0] == 3.3
    assert out[0].valid[0]


# --------------------------------------------------------------- current
@settings(max_examples=60, deadline=None)
@given(
    steps=st.lists(st.tuples(st.integers(1, 40), st.integers(-2000, 2000)), min_size=50, max_size=400),
    t0=st.integers(0, 1000),
)
def test_current_is_charge_exact(steps, t0):
    """Sum of mean current x period == integral of the zero-order-held current over the same span."""
    p = 0.25
    s = SampleAssembler(1, period_s=p, current_hold_s=1.0, min_current_coverage=0.0)
    t = float(t0)
    frames = []
    for dt_ms, i in steps:
        frames.append((t, i / 10.0))
        t += dt_ms / 1000.0
    samples = []
    for ft, i in frames:
        samples += s.feed_frame([Event(I, -1, i)], ft)
    if not samples:
        return
    start = samples[0].t_s - p
    end = samples[-1].t_s
    # reference ZOH integral over [start, end]
    q = 0.0
    for (ta, ia), (tb, _) in zip(frames, frames[1:] + [(math.inf, 0.0)]):
        a, b = max(ta, start), min(tb, end)
        if b > a:
            q += ia * (b - a)
    got = sum(x.current_a * p for x in samples)
    assert got == pytest.approx(q, rel=1e-9, abs=1e-9)
    assert all(x.current_valid and x.current_coverage == pytest.approx(1.0) for x in samples)


def test_current_mean_is_time_weighted():
    s = SampleAssembler(1, period_s=1.0)
    s.feed(Event(I, -1, 0.0), 0.0)
    s.feed(Event(I, -1, 10.0), 0.25)  # 10 A for 0.5 s
    s.feed(Event(I, -1, -4.0), 0.75)  # -4 A for 0.25 s
    s.feed(Event(I, -1, 1.0), 0.95)  # 1 A for 0.05 s  (hold 0.5 s covers to the boundary)
    (out,) = s.feed(Event(I, -1, 0.0), 1.0)
    assert out.current_a == pytest.approx(0.0 * 0.25 + 10 * 0.5 - 4 * 0.2 + 1 * 0.05)


def test_current_gap_invalidates_the_sample():
    s = SampleAssembler(2, period_s=1.0, current_hold_s=0.1)
    s.feed_frame([Event(V, 0, 3.0), Event(V, 1, 3.1)], 0.0)
    s.feed(Event(I, -1, 5.0), 0.0)
    s.feed(Event(I, -1, 5.0), 0.5)  # nothing after 0.6 s
    (out,) = s.feed_frame([Event(V, 0, 3.0), Event(V, 1, 3.1)], 1.0)
    assert not out.current_valid
    assert out.current_coverage == pytest.approx(0.2)  # [0, 0.1] and [0.5, 0.6]
    assert out.current_a == pytest.approx(5.0)  # mean over the covered part
    assert not out.valid.any()  # no usable current -> no usable cell
    assert s.counters.current_invalid_samples == 1
    (out2,) = s.feed_frame([Event(V, 0, 3.0)], 2.0)
    assert math.isnan(out2.current_a) and out2.current_coverage == 0.0


# ------------------------------------------------------------- staleness
def test_stale_and_missing_cells_are_flagged():
    s = SampleAssembler(3, period_s=1.0, staleness_s=1.5, temperature_staleness_s=2.0)
    out = []
    for k in range(50):
        t = k * 0.1
        out += s.feed(Event(I, -1, 1.0), t)
        out += s.feed(Event(V, 0, 3.3), t)
        if t < 1.0:
            out += s.feed(Event(V, 1, 3.4), t)
            out += s.feed(Event(T, 1, 30.0), t)
    by_t = {o.t_s: o for o in out}
    assert set(by_t) == {1.0, 2.0, 3.0, 4.0}
    # cell 2: never seen -> NaN and invalid; cell 1: last value at 0.9 s
    for o in out:
        assert o.valid[0] and not o.valid[2] and math.isnan(o.cell_voltage_v[2])
    assert by_t[2.0].valid[1] and not by_t[3.0].valid[1]
    assert by_t[3.0].cell_voltage_v[1] == 3.4  # stale value kept, but flagged
    assert by_t[2.0].cell_temperature_c[1] == 30.0 and math.isnan(by_t[3.0].cell_temperature_c[1])
    assert s.counters.stale_cell_samples == 4 + 2  # cell 2 in all four, cell 1 in two


def test_mean_voltage_mode():
    s = SampleAssembler(1, period_s=1.0, voltage_mode="mean", current_hold_s=5.0)
    s.feed(Event(I, -1, 0.0), 0.0)
    s.feed(Event(V, 0, 3.0), 0.1)
    s.feed(Event(V, 0, 3.2), 0.6)
    (a,) = s.feed(Event(I, -1, 0.0), 1.0)
    assert a.cell_voltage_v[0] == pytest.approx(3.1)
    (b,) = s.feed(Event(I, -1, 0.0), 2.0)  # nothing new in [1, 2): latest value
    assert b.cell_voltage_v[0] == pytest.approx(3.2) and b.valid[0]


# ------------------------------------------------------- time anomalies
def test_short_gap_emits_a_few_flagged_samples():
    s = SampleAssembler(1, period_s=1.0, staleness_s=1.0, max_gap_s=5.0)
    for k in range(10):
        s.feed_frame([Event(I, -1, 1.0), Event(V, 0, 3.3)], k * 0.1)
    out = s.feed_frame([Event(I, -1, 1.0), Event(V, 0, 3.3)], 4.2)
    assert [o.t_s for o in out] == [1.0, 2.0, 3.0, 4.0]
    assert out[0].valid[0] and not any(o.valid[0] for o in out[1:])
    assert s.counters.time_jumps == 0


def test_long_gap_reanchors_without_fabricating_samples():
    s = SampleAssembler(1, period_s=1.0, max_gap_s=5.0)
    for k in range(25):
        s.feed_frame([Event(I, -1, 1.0), Event(V, 0, 3.3)], k * 0.1)
    out = s.feed_frame([Event(I, -1, 1.0), Event(V, 0, 3.3)], 3600.05)
    assert [o.t_s for o in out] == [3.0]  # only the period in progress (it had real data)
    assert s.counters.time_jumps == 1
    assert s.next_boundary_s == 3602.0  # new grid: first complete period [3601, 3602)
    more = []
    for k in range(1, 30):
        more += s.feed_frame([Event(I, -1, 2.0), Event(V, 0, 3.4)], 3600.05 + k * 0.1)
    assert [o.t_s for o in more] == [3602.0]
    assert more[0].valid[0] and more[0].current_a == pytest.approx(2.0)


def test_backward_frames_are_ignored_and_big_rewinds_restart():
    s = SampleAssembler(1, period_s=1.0, rewind_s=5.0)
    for k in range(15):
        s.feed_frame([Event(I, -1, 1.0), Event(V, 0, 3.3)], 100 + k * 0.1)
    assert s.feed(Event(V, 0, 9.9), 100.5) == []  # 0.9 s back: ignored
    assert s.counters.backward_frames == 1
    out = s.feed_frame([Event(I, -1, 1.0), Event(V, 0, 3.3)], 102.0)
    assert out[-1].cell_voltage_v[0] == 3.3  # the ignored 9.9 V never got in
    # a new log starting at t = 5 s
    assert s.feed_frame([Event(I, -1, -1.0), Event(V, 0, 3.0)], 5.0) == []
    assert s.counters.rewinds == 1
    out = []
    for k in range(1, 25):
        out += s.feed_frame([Event(I, -1, -1.0), Event(V, 0, 3.0)], 5.0 + k * 0.1)
    assert [o.t_s for o in out] == [6.0, 7.0]
    assert all(o.cell_voltage_v[0] == 3.0 and o.current_a == -1.0 for o in out)


def test_bad_timestamps_values_and_indices_are_counted():
    s = SampleAssembler(2)
    assert s.feed(Event(V, 0, 3.0), math.nan) == []
    assert s.feed(Event(V, 0, 3.0), math.inf) == []
    s.feed(Event(V, 0, math.nan), 1.0)
    s.feed(Event(I, -1, math.inf), 1.0)
    s.feed(Event(V, 2, 3.0), 1.0)
    s.feed(Event(T, -1, 3.0), 1.0)
    c = s.counters
    assert (c.bad_timestamps, c.non_finite_values, c.bad_cell_index, c.internal_errors) == (2, 2, 2, 0)


# ---------------------------------------------------------------- fuzz
event_st = st.tuples(
    st.sampled_from(list(EventKind) + [7]),
    st.integers(-3, 6),
    st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.integers(-10, 10)),
)
frame_st = st.tuples(
    st.one_of(
        st.floats(-0.05, 0.5),  # mostly forward steps, some small back steps
        st.floats(-20, 20),
        st.sampled_from([math.nan, math.inf, -math.inf, 1e9]),
    ),
    st.lists(event_st, max_size=4),
)


@settings(max_examples=200, deadline=None)
@given(frames=st.lists(frame_st, max_size=120), mode=st.sampled_from(["latest", "mean"]))
def test_random_streams_never_raise(frames, mode):
    n = 4
    s = SampleAssembler(n, period_s=0.5, staleness_s=1.0, max_gap_s=3.0, rewind_s=2.0, voltage_mode=mode)
    t = 0.0
    last_t_s = -math.inf
    rewinds = 0
    for dt, events in frames:
        t_frame = t + dt if math.isfinite(dt) and abs(dt) < 1e6 else dt
        if math.isfinite(t_frame):
            t = t_frame
        out = s.feed_frame([Event(*e) for e in events], t_frame)
        if s.counters.rewinds != rewinds:
            rewinds, last_t_s = s.counters.rewinds, -math.inf
        for o in out:
            assert o.t_s > last_t_s
            last_t_s = o.t_s
            assert o.cell_voltage_v.shape == o.valid.shape == o.cell_temperature_c.shape == (n,)
            assert np.isfinite(o.cell_voltage_v[o.valid]).all()
            if o.current_valid:
                assert math.isfinite(o.current_a)
    assert s.counters.internal_errors == 0


@pytest.mark.parametrize("huge", [1e300, 1e21, 2.0**60])
def test_huge_sender_timestamps_are_refused_not_looped_on(huge):
    """A sender's garbage clock (virtual bus, log time, hardware stamps): at 1e300 a double cannot tell
    t from t + period, and the grid never advanced (a livelock; at 1e21 one frame made 65,536 samples).
    Such frames are counted and ignored; the stream around them is untouched."""
    s = SampleAssembler(2, period_s=1.0, staleness_s=2.5, max_gap_s=5.0, rewind_s=5.0)
    ref = SampleAssembler(2, period_s=1.0, staleness_s=2.5, max_gap_s=5.0, rewind_s=5.0)
    out, want = [], []
    for k in range(40):
        t = 100.0 + 0.5 * k
        frame = [Event(I, -1, 1.0), Event(V, 0, 3.6), Event(V, 1, 3.7)]
        out += s.feed_frame(frame, t)
        want += ref.feed_frame(frame, t)
        if k in (10, 11, 30):
            assert s.feed_frame(frame, huge) == [] and s.feed_frame(frame, -huge) == []
    assert s.counters.bad_timestamps == 6
    assert len(out) == len(want) == 19
    same(out, want)


# ------------------------------------------------ limits are inclusive
def test_a_value_as_old_as_its_staleness_limit_is_still_fresh():
    """A value OLDER than its staleness limit is stale: one exactly that old at a period's end is still used.
    Voltage, temperature and pack voltage arrive once at t = 0; current every 0.25 s keeps the
    samples coming. Cell voltage and pack voltage (its limit defaults to ``staleness_s`` = 2 s, not
    the temperature's) are fresh at the ends 1 and 2 s, stale from 3 s; the temperature (4 s) is
    kept up to the end 4 s and NaN from 5 s."""
    s = SampleAssembler(1, period_s=1.0, staleness_s=2.0, temperature_staleness_s=4.0)
    out = s.feed_frame([Event(I, -1, 1.0), Event(V, 0, 3.3), Event(T, 0, 25.0), Event(PV, -1, 400.0)], 0.0)
    for k in range(1, 25):
        out += s.feed_frame([Event(I, -1, 1.0)], 0.25 * k)
    by_t = {o.t_s: o for o in out}
    assert sorted(by_t) == [1.0, 2.0, 3.0, 4.0, 5.0, 6.0]
    assert [bool(by_t[t].valid[0]) for t in sorted(by_t)] == [True, True, False, False, False, False]
    assert [by_t[t].pack_voltage_v == 400.0 for t in sorted(by_t)] == [True, True, False, False, False, False]
    assert [by_t[t].cell_temperature_c[0] == 25.0 for t in sorted(by_t)] == [True] * 4 + [False] * 2


def test_a_current_covering_exactly_the_minimum_coverage_is_valid():
    """``current_valid`` is False if LESS than ``min_current_coverage`` of the period was covered:
    two current frames at 0 and 0.25 s held 0.25 s each cover exactly half of [0, 1)."""
    s = SampleAssembler(1, period_s=1.0, current_hold_s=0.25, min_current_coverage=0.5)
    s.feed_frame([Event(I, -1, 2.0), Event(V, 0, 3.3)], 0.0)
    s.feed_frame([Event(I, -1, 2.0)], 0.25)
    (out,) = s.feed_frame([Event(V, 0, 3.3)], 1.0)
    assert out.current_coverage == 0.5
    assert out.current_valid and out.valid[0]
    assert out.current_a == 2.0


def test_mean_voltage_counts_only_the_values_within_the_period():
    """``voltage_mode="mean"``: the mean of the values received WITHIN the period. A frame before
    the first complete period [1, 2) only primes the latest value: (3.2 + 3.4) / 2 = 3.3, not
    (3.0 + 3.2 + 3.4) / 3."""
    s = SampleAssembler(1, period_s=1.0, voltage_mode="mean", current_hold_s=5.0)
    s.feed_frame([Event(I, -1, 0.0), Event(V, 0, 3.0)], 0.25)
    s.feed(Event(V, 0, 3.2), 1.25)
    s.feed(Event(V, 0, 3.4), 1.75)
    (out,) = s.feed(Event(I, -1, 0.0), 2.0)
    assert out.t_s == 2.0
    assert out.cell_voltage_v[0] == pytest.approx(3.3, abs=1e-12)


def test_a_gap_of_exactly_max_gap_s_is_bridged_not_a_time_jump():
    """Only a frame MORE than ``max_gap_s`` after the previous one is a time jump. 5 s after the last
    frame at 0.5 s, the five periods ending 1 .. 5 s are all emitted by the frame at 5.5 s (the
    first with the cell's data, the rest flagged stale) and the grid is not re-anchored."""
    s = SampleAssembler(1, period_s=1.0, staleness_s=1.0, max_gap_s=5.0)
    for k in range(6):
        s.feed_frame([Event(I, -1, 1.0), Event(V, 0, 3.3)], 0.1 * k)
    out = s.feed_frame([Event(I, -1, 1.0), Event(V, 0, 3.3)], 5.5)
    assert [o.t_s for o in out] == [1.0, 2.0, 3.0, 4.0, 5.0]
    assert [bool(o.valid[0]) for o in out] == [True, False, False, False, False]
    assert s.counters.time_jumps == 0 and s.next_boundary_s == 6.0


def test_frames_dropped_as_backward_are_said_in_the_log_not_once_per_frame():
    """Two senders whose clocks disagree by 0.3 s (the current through a gateway ahead of the cell
    frames' one): every cell frame is older than the newest current frame and is dropped, so every
    cell is stale. The counter alone did not say why; a log line does, with how far back and a hint,
    at the 1st, 10th, 100th, 1000th... dropped frame, not at each."""
    s = SampleAssembler(2, period_s=1.0, staleness_s=2.5, rewind_s=5.0)
    with capture_logs() as logs:
        for k in range(300):  # 30 s
            t = 100.0 + 0.1 * k
            s.feed(Event(I, -1, 1.0), t + 0.3)
            s.feed_frame([Event(V, 0, 3.6), Event(V, 1, 3.6)], t + 0.002)
    assert s.counters.backward_frames == 300
    said = [e for e in logs if e["event"] == "can.sampler.backward_frames"]
    assert [e["backward_frames"] for e in said] == [1, 10, 100]
    assert said[0]["log_level"] == "warning" and said[0]["behind_s"] == pytest.approx(0.298)
    assert "clock" in said[0]["hint"]


def test_a_frame_exactly_rewind_s_back_is_ignored_not_a_restart():
    """Backward by UP TO ``rewind_s`` is ignored (``backward_frames``); only more is a rewind that drops
    the state: 5 s back with ``rewind_s = 5`` keeps the cell's 3.3 V and the grid."""
    s = SampleAssembler(1, period_s=1.0, rewind_s=5.0)
    for k in range(5):
        s.feed_frame([Event(I, -1, 1.0), Event(V, 0, 3.3)], 10.0 + 0.25 * k)
    assert s.feed_frame([Event(V, 0, 9.9)], 6.0) == []
    assert (s.counters.backward_frames, s.counters.rewinds) == (1, 0)
    (out,) = s.feed_frame([Event(I, -1, 1.0)], 12.0)
    assert out.t_s == 12.0 and out.cell_voltage_v[0] == 3.3


def test_a_negative_cell_index_is_counted_and_never_lands_on_the_last_cell():
    """Cell indices outside ``[0, n_cells)`` are ignored and counted: -1 must not be taken as Python's
    "last element" (cell 1 of 2 would publish 9.9 V)."""
    s = SampleAssembler(2, period_s=1.0)
    s.feed_frame([Event(I, -1, 1.0), Event(V, 0, 3.3), Event(V, 1, 3.4)], 0.0)
    s.feed_frame([Event(V, -1, 9.9), Event(T, -1, 99.0)], 0.5)
    (out,) = s.feed_frame([Event(I, -1, 1.0)], 1.0)
    assert s.counters.bad_cell_index == 2
    assert list(out.cell_voltage_v) == [3.3, 3.4]
    assert np.isnan(out.cell_temperature_c).all()


def test_a_minimum_current_coverage_above_one_is_refused():
    with pytest.raises(ValueError, match="min_current_coverage"):
        SampleAssembler(1, min_current_coverage=1.5)


def test_a_temperatures_age_counts_from_its_own_frame():
    """A temperature's age is ``end - its frame's time``: received at 0.75 s, it is 1.25 s old at the
    end 2 s (kept under a 1.5 s limit) and 2.25 s old at 3 s (NaN)."""
    s = SampleAssembler(1, period_s=1.0, temperature_staleness_s=1.5)
    out = s.feed_frame([Event(I, -1, 1.0), Event(V, 0, 3.3)], 0.0)
    out += s.feed_frame([Event(T, 0, 25.0)], 0.75)
    for k in range(1, 13):
        out += s.feed_frame([Event(I, -1, 1.0), Event(V, 0, 3.3)], 0.25 * k)
    assert [o.t_s for o in out] == [1.0, 2.0, 3.0]
    assert [o.cell_temperature_c[0] == 25.0 for o in out] == [True, True, False]
