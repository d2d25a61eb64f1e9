"""Signal events as arrays -> the service's 1 s samples as arrays (bulk form of can/sampler.py).

Same timing model as :class:`~bms_estimator.can.sampler.SampleAssembler` (read its
docstring first); here it is evaluated on all frames at once:

1. Timestamps that are not finite or too large to resolve the grid are dropped
   (``bad_timestamps``), as the sampler drops them.
2. Resets: with ``r_i = max(t_s, ..., t_{i-1})`` the running maximum since the last
   reset, frame ``i`` is a rewind (reset, re-anchor) when ``r_i - t_i > rewind_s``,
   ignored (``backward_frames``) when ``t_i < r_i``, and else accepted. Between resets
   the accepted frames are in time order and ``r`` is the sampler's ``t_last``.
3. Grid segments: a frame with ``t_i - r_i > max_gap_s`` is a time jump: the period in
   progress is emitted, and the grid re-anchored at ``k_0 = ceil(t_i / p)``. (With
   ``max_gap_s >= 2 p``, which the service always has, ``t_i - r_i > max_gap_s`` implies
   ``t_i >= t_next``, the sampler's other condition.) Within a grid segment, period
   ``k`` (``[k p, (k+1) p)``) is emitted iff ``(k+1) p <= max t``.
4. A sample at period end ``E`` sees exactly the accepted events of its reset segment
   with ``t < E`` (a frame at ``t >= E`` closes the period before it is applied):
   latest voltage, temperature and pack voltage per cell by ``searchsorted``, and their
   staleness ``E - t_latest`` against the sampler's limits.
5. Current, zero-order hold: the pieces of period ``[S, E)`` are ``[S, c_lo)``,
   ``[c_lo, c_lo+1)``, ..., ``[c_hi-1, E)`` over the current events ``c`` in ``[S, E)``,
   each held at the latest current event before it, cut at that event's time plus
   ``current_hold_s``; ``q = sum i_j (e_j - s_j)`` and ``cov = sum (e_j - s_j)`` are
   accumulated with ``numpy.add.at`` (unbuffered, in index order: the sampler's own
   summation order), so ``current_a`` and ``current_coverage`` are bit-identical.

Only ``voltage_mode="latest"`` (the service's) is supported.
"""

from __future__ import annotations

import math

import numpy as np

from ..can.decoder import EventKind
from ..can.sampler import SampleAssembler, SamplerCounters
from .decode import EventArrays
from .samples import SampleArrays

__all__ = ["assemble_samples"]


def _latest(t_sorted: np.ndarray, v_sorted: np.ndarray, bounds: np.ndarray, ends: np.ndarray,
            ) -> tuple[np.ndarray, np.ndarray]:
    """(K, n) latest value and its time with ``t < end`` per cell (NaN / -inf if none).

    ``t_sorted``/``v_sorted`` hold the events grouped by cell, each group in apply order;
    cell ``c``'s group is ``[bounds[c], bounds[c+1])`` (``n = len(bounds) - 1``).
    """
    k, n = ends.shape[0], bounds.shape[0] - 1
    val = np.full((k, n), np.nan)
    vt = np.full((k, n), -np.inf)
    for c in range(n):
        lo, hi = int(bounds[c]), int(bounds[c + 1])
        if lo == hi:
            continue
        tc = t_sorted[lo:hi]
        pos = np.searchsorted(tc, ends, side="left") - 1
        has = pos >= 0
        p = np.where(has, pos, 0)
        val[:, c] = np.where(has, v_sorted[lo:hi][p], np.nan)
        vt[:, c] = np.where(has, tc[p], -np.inf)
    return val, vt


def _grid(t_acc: np.ndarray, anchors: list[int], anchor_kind: list[str], p: float,
          ) -> tuple[list[np.ndarray], int]:
    """Period indices emitted per grid segment of one reset segment; and the number of time jumps."""
    out: list[np.ndarray] = []
    jumps = 0
    for g, a in enumerate(anchors):
        end = anchors[g + 1] if g + 1 < len(anchors) else t_acc.size
        k0 = math.ceil(float(t_acc[a]) / p)
        t_max = float(t_acc[end - 1])  # accepted frames are in time order
        n = max(0, int(math.floor(t_max / p)) - k0)
        while (k0 + n + 1) * p <= t_max:
            n += 1
        while n > 0 and (k0 + n) * p > t_max:
            n -= 1
        if g + 1 < len(anchors) and anchor_kind[g + 1] == "gap":
            n += 1  # the period in progress is emitted at the jump
            jumps += 1
        out.append(np.arange(k0, k0 + n, dtype=np.int64))
    return out, jumps


def assemble_samples(t_frames: np.ndarray, events: EventArrays, sampler: SampleAssembler) -> SampleArrays:
    """The samples ``sampler`` (fresh, with its parameters) would emit for these frames and events.

    ``t_frames`` holds every frame's timestamp (every frame moves the sampler's clock,
    with or without events); ``events.frame`` indexes it. ``sampler`` is only read.
    """
    if sampler.voltage_mode != "latest":
        raise ValueError("bulk assembly supports voltage_mode='latest' only (the service's)")
    p = sampler.period_s
    if sampler.max_gap_s < 2.0 * p:
        raise ValueError("bulk assembly needs max_gap_s >= 2 period_s (the service's setting)")
    n = sampler.n_cells
    counters = SamplerCounters()
    t_all = np.asarray(t_frames, dtype=float)
    with np.errstate(invalid="ignore"):
        good = np.isfinite(t_all) & (np.spacing(np.abs(t_all)) <= sampler._time_resolution_s)  # noqa: SLF001
    counters.bad_timestamps = int(np.count_nonzero(~good))
    gidx = np.flatnonzero(good)
    tg = t_all[gidx]

    # resets (rewinds) and accepted frames
    accepted = np.zeros(tg.size, dtype=bool)
    reset_starts: list[int] = []
    gaps: list[int] = []
    s = 0
    while s < tg.size:
        reset_starts.append(s)
        rm = np.maximum.accumulate(tg[s:])
        prev, cur = rm[:-1], tg[s + 1:]
        rew = np.flatnonzero((prev - cur) > sampler.rewind_s)
        stop = s + 1 + int(rew[0]) if rew.size else tg.size
        span = slice(s + 1, stop)
        acc = cur[: stop - s - 1] >= prev[: stop - s - 1]
        accepted[s] = True
        accepted[span] = acc
        counters.backward_frames += int(np.count_nonzero(~acc))
        gap = np.flatnonzero((cur[: stop - s - 1] - prev[: stop - s - 1]) > sampler.max_gap_s)
        gaps.extend((s + 1 + gap).tolist())
        if rew.size:
            counters.rewinds += 1
        s = stop

    # per frame: which reset segment; event times
    frame_reset = np.full(t_all.size, -1, dtype=np.int64)
    seg_of_g = np.searchsorted(np.asarray(reset_starts, dtype=np.int64), np.arange(tg.size), side="right") - 1
    frame_reset[gidx[accepted]] = seg_of_g[accepted]
    # every frame's time good and accepted, one reset segment (a clean log): the events are all the
    # segment's; taken column by column when decode kept them so (no merge into frame order, no sort)
    by_columns = (events.columns is not None and len(reset_starts) == 1 and gidx.size == t_all.size
                  and bool(accepted.all()))
    if not by_columns:
        ev_reset = frame_reset[events.frame] if events.frame.size else np.zeros(0, np.int64)
        ev_t = t_all[events.frame] if events.frame.size else np.zeros(0)

    gap_set = np.asarray(gaps, dtype=np.int64)
    blocks: list[dict[str, np.ndarray]] = []
    for r, rs in enumerate(reset_starts):
        re_ = reset_starts[r + 1] if r + 1 < len(reset_starts) else tg.size
        local_acc = np.flatnonzero(accepted[rs:re_]) + rs  # accepted frames (positions in tg)
        t_acc = tg[local_acc]
        in_seg = gap_set[(gap_set >= rs) & (gap_set < re_)]
        anchors = [0] + np.searchsorted(local_acc, in_seg).tolist()
        kinds = ["start"] + ["gap"] * in_seg.size
        periods, jumps = _grid(t_acc, anchors, kinds, p)
        counters.time_jumps += jumps
        ks = np.concatenate(periods) if periods else np.zeros(0, np.int64)
        if ks.size == 0:
            continue
        starts = ks.astype(float) * p
        ends = (ks + 1).astype(float) * p
        if by_columns:
            grouped = _by_signal_columns(t_all, events.columns, n)
        else:
            mine = ev_reset == r
            if mine.all():  # one reset segment and every event's frame accepted: no copies
                grouped = _by_signal(ev_t, events.kind, events.cell, events.value, n)
            else:
                grouped = _by_signal(ev_t[mine], events.kind[mine], events.cell[mine], events.value[mine], n)
        blocks.append(_block(*grouped, starts, ends, n, sampler))

    k_total = sum(b["t_s"].size for b in blocks)
    if blocks:
        cat = {key: np.concatenate([b[key] for b in blocks]) for key in blocks[0]}
    else:
        cat = {"t_s": np.zeros(0), "current_a": np.zeros(0), "current_valid": np.zeros(0, bool),
               "current_coverage": np.zeros(0), "cell_voltage_v": np.zeros((0, n)),
               "cell_temperature_c": np.zeros((0, n)), "valid": np.zeros((0, n), bool),
               "pack_voltage_v": np.zeros(0), "fresh": np.zeros((0, n), bool)}
    counters.samples = k_total
    counters.stale_cell_samples = int(n * k_total - np.count_nonzero(cat["fresh"]))
    counters.current_invalid_samples = int(np.count_nonzero(~cat["current_valid"]))
    return SampleArrays(
        t_s=cat["t_s"], current_a=cat["current_a"], current_valid=cat["current_valid"],
        current_coverage=cat["current_coverage"], cell_voltage_v=cat["cell_voltage_v"],
        cell_temperature_c=cat["cell_temperature_c"], valid=cat["valid"], pack_voltage_v=cat["pack_voltage_v"],
        period_s=p, counters=counters.as_dict(),
    )


def _signal_key(kind, cell, n: int):
    """The (kind, cell) group's sort key: kinds in order, within a kind the pack-level value (cell -1) first."""
    return kind * (n + 1) + (cell + 1)


def _by_signal(t: np.ndarray, kind: np.ndarray, cell: np.ndarray, value: np.ndarray, n: int,
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(times, values, bounds) of events in apply order, grouped by (kind, cell), each group in apply order;
    group ``key`` (:func:`_signal_key`) is ``[bounds[key], bounds[key + 1])`` for keys ``0 .. 4 (n + 1) - 1``."""
    # one stable sort by (kind, cell) groups every signal's events, each group in apply order (a radix
    # sort on int16 keys): the slices in _block replace a mask per kind and a sort per kind
    key = _signal_key(kind.astype(np.int64), cell.astype(np.int64), n)
    if key.size and int(key.max()) <= np.iinfo(np.int16).max:
        key = key.astype(np.int16)
    order = np.argsort(key, kind="stable")
    bounds = np.searchsorted(key[order], np.arange(4 * (n + 1) + 1, dtype=key.dtype), side="left")
    return t[order], value[order], bounds


def _by_signal_columns(t_frames: np.ndarray, columns: list, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`_by_signal` of all the events of decode's signal columns (every frame's time given), without
    merging them into frame order and sorting them back: a column holds one group's events in frame
    order already. Columns of one group (rare) are merged by frame, ties in column order: the
    decoder's order within a frame, as the stable sort keeps it. The same arrays, element for element."""
    by_key: dict[int, list] = {}
    for col in columns:
        by_key.setdefault(_signal_key(col.kind, col.cell, n), []).append(col)
    keys = sorted(by_key)
    ts, vs = [], []
    times: dict[int, tuple[np.ndarray, np.ndarray]] = {}  # the signals of one message share one frame array
    for key in keys:
        cols = by_key[key]
        if len(cols) == 1:
            fr, v = cols[0].frame, cols[0].value
        else:
            fr = np.concatenate([c.frame for c in cols])
            v = np.concatenate([c.value for c in cols])
            o = np.argsort(fr, kind="stable")
            fr, v = fr[o], v[o]
        if id(fr) in times and times[id(fr)][0] is fr:
            ts.append(times[id(fr)][1])
        else:
            ts.append(t_frames[fr])
            times[id(fr)] = (fr, ts[-1])
        vs.append(v)
    first = np.concatenate(([0], np.cumsum([x.size for x in ts], dtype=np.int64)))
    at = np.searchsorted(np.asarray(keys, dtype=np.int64), np.arange(4 * (n + 1) + 1, dtype=np.int64), side="left")
    return (np.concatenate(ts) if ts else np.zeros(0), np.concatenate(vs) if vs else np.zeros(0), first[at])


def _block(ts: np.ndarray, vs: np.ndarray, bounds: np.ndarray, starts: np.ndarray,
           ends: np.ndarray, n: int, sampler: SampleAssembler) -> dict[str, np.ndarray]:
    """Samples of one reset segment: its events grouped by signal (:func:`_by_signal`), its period starts and ends."""
    p = sampler.period_s

    def rows(kind_: EventKind) -> np.ndarray:  # the group bounds of kind_'s cells 0..n-1 (or its cell -1)
        return bounds[int(kind_) * (n + 1):(int(kind_) + 1) * (n + 1) + 1]

    volts, v_t = _latest(ts, vs, rows(EventKind.CELL_VOLTAGE)[1:], ends)
    temps, temp_t = _latest(ts, vs, rows(EventKind.CELL_TEMPERATURE)[1:], ends)
    pv, pv_t = _latest(ts, vs, rows(EventKind.PACK_VOLTAGE)[:2], ends)
    i_lo, i_hi = rows(EventKind.CURRENT)[:2]
    ct, cv = ts[i_lo:i_hi], vs[i_lo:i_hi]

    # current: zero-order-hold pieces per period, summed in the sampler's order
    k = ends.size
    lo = np.searchsorted(ct, starts, side="left")
    hi = np.searchsorted(ct, ends, side="left")
    n_k = hi - lo
    counts = n_k + 1
    piece_sample = np.repeat(np.arange(k), counts)
    first = np.cumsum(counts) - counts
    j = np.arange(piece_sample.size) - np.repeat(first, counts)
    lo_p = lo[piece_sample]
    held = lo_p - 1 + j
    has_held = held >= 0
    h = np.where(has_held, held, 0)
    nxt = lo_p + j
    if ct.size:
        s = np.where(j == 0, starts[piece_sample], ct[np.maximum(nxt - 1, 0)])
        e_raw = np.where(j < n_k[piece_sample], ct[np.minimum(nxt, ct.size - 1)], ends[piece_sample])
        hold_end = ct[h] + sampler.current_hold_s
        e = np.minimum(e_raw, hold_end)
        ok = has_held & (e > s)
        d = (e - s)[ok]
        term = cv[h][ok] * d
    else:
        ok = np.zeros(piece_sample.size, bool)
        d = term = np.zeros(0)
    q = np.zeros(k)
    cov = np.zeros(k)
    np.add.at(q, piece_sample[ok], term)
    np.add.at(cov, piece_sample[ok], d)
    with np.errstate(invalid="ignore", divide="ignore"):
        coverage = np.minimum(1.0, cov / p)
        current = np.where(cov >= p * (1.0 - 1e-9), q / p, np.where(cov > 0.0, q / cov, np.nan))
    current_valid = (cov > 0.0) & (coverage >= sampler.min_current_coverage)

    end_col = ends[:, None]
    fresh = (end_col - v_t) <= sampler.staleness_s
    temps = np.where((end_col - temp_t) > sampler.temperature_staleness_s, np.nan, temps)
    pack = np.where((ends - pv_t[:, 0]) <= sampler.pack_voltage_staleness_s, pv[:, 0], np.nan)
    return {"t_s": ends, "current_a": current, "current_valid": current_valid, "current_coverage": coverage,
            "cell_voltage_v": volts, "cell_temperature_c": temps, "valid": fresh & current_valid[:, None],
            "pack_voltage_v": pack, "fresh": fresh}
