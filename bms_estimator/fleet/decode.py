"""Frames as arrays -> signal events as arrays, with vectorised bit extraction (bulk form of can/decoder.py).

The plan is :class:`~bms_estimator.can.decoder.FrameDecoder`'s own (built from the same
DBC and mapping, so the two cannot disagree on which signal is which cell and on the
conversion ``si = a * raw + b``). Per mapped frame id, on all its frames at once:

* the payload's first 8 bytes as one little-endian and one big-endian ``uint64``;
* a signal's raw value: Intel (little endian), LSB at ``start``:
  ``raw = (u_le >> start) & (2^len - 1)``; Motorola (big endian), cantools' ``start``
  is the MSB in the DBC's sawtooth numbering, at linear position
  ``m = 8 floor(start/8) + 7 - start mod 8`` counted from the first byte's MSB:
  ``raw = (u_be >> (64 - m - len)) & (2^len - 1)``; two's complement for signed
  signals, an IEEE view for float signals;
* then the decoder's rules, in its order: unknown id / unmapped, error and remote
  frames ignored, short frame, multiplexer value the DBC does not define (bad_mux),
  the end-to-end checks (:mod:`bms_estimator.can.e2e`: CRC of every frame with
  :func:`~bms_estimator.can.e2e.crc_rows`; then, over the frames whose CRC held, per
  multiplexer value in frame order, the alive counter ``c_k = (c_{k-1} + 1) mod m`` with
  the first frame of the table as the reference), invalid flag, NotAvailable raw value,
  non-finite, outside ``[valid_min, valid_max]``.

Messages longer than 8 bytes (CAN FD) are decoded frame by frame with the service's
decoder (the same result, at its speed). The counters equal
:class:`~bms_estimator.can.decoder.DecodeCounters` for the same frames.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..can.decoder import DecodeCounters, FrameDecoder
from ..can.e2e import E2E_RESYNC_S, crc_rows
from .frames import FrameTable

__all__ = ["EventArrays", "SignalColumn", "decode_frames", "signal_raw"]


@dataclass(frozen=True, eq=False)
class SignalColumn:
    """The events of one mapped signal: one kind and cell, its frames in order."""

    kind: int  # EventKind
    cell: int  # -1 for pack-level values
    frame: np.ndarray  # (e,) int64 frame indices, ascending, no frame twice
    value: np.ndarray  # (e,) float64, SI


class EventArrays:
    """E events in frame order (within one frame: the decoder's order).

    :func:`decode_frames` makes them from its signal columns (:attr:`columns`, in the
    decoder's order within a frame) and merges the columns into frame order on the first
    read of ``frame``, ``kind``, ``cell`` or ``value``: a reader that takes the events by
    signal (:mod:`.assemble`, where nothing reorders them) reads the columns instead and
    the merge is never done.
    """

    def __init__(self, frame: np.ndarray, kind: np.ndarray, cell: np.ndarray, value: np.ndarray) -> None:
        self._merged: tuple[np.ndarray, ...] | None = (frame, kind, cell, value)
        self.columns: list[SignalColumn] | None = None
        self._n_frames = 0
        self.size = int(frame.size)

    @classmethod
    def from_columns(cls, columns: list[SignalColumn], n_frames: int) -> EventArrays:
        """The events of ``columns`` (in the decoder's order within a frame) over ``n_frames`` frames."""
        ev = cls.__new__(cls)
        ev._merged, ev.columns, ev._n_frames = None, columns, int(n_frames)
        ev.size = sum(int(c.frame.size) for c in columns)
        return ev

    def _arrays(self) -> tuple[np.ndarray, ...]:
        if self._merged is None:
            self._merged = _merge_columns(self.columns, self._n_frames)
        return self._merged

    @property
    def frame(self) -> np.ndarray:  # (E,) int64 index of the frame in the FrameTable
        return self._arrays()[0]

    @property
    def kind(self) -> np.ndarray:  # (E,) int8 EventKind
        return self._arrays()[1]

    @property
    def cell(self) -> np.ndarray:  # (E,) int32, -1 for pack-level values
        return self._arrays()[2]

    @property
    def value(self) -> np.ndarray:  # (E,) float64, SI
        return self._arrays()[3]


def _words(data: np.ndarray, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The first 8 payload bytes of frames ``idx`` as little- and big-endian ``uint64`` (the values, native order)."""
    if data.shape[1] == 8 and data.flags.c_contiguous:  # one 8-byte word per frame: gather the words themselves
        u_le = data.view("<u8").ravel()[idx]
    else:
        u_le = np.ascontiguousarray(data[idx, :8]).view("<u8").ravel()
    return u_le, u_le.byteswap()


def signal_raw(sig, u_le: np.ndarray, u_be: np.ndarray) -> np.ndarray:
    """Raw values of cantools signal ``sig`` (int64, or float64 for float signals) from the payload words."""
    n = int(sig.length)
    mask = np.uint64((1 << n) - 1) if n < 64 else np.uint64(0xFFFF_FFFF_FFFF_FFFF)
    if sig.byte_order == "little_endian":
        raw = (u_le >> np.uint64(sig.start)) & mask
    else:
        msb = 8 * (sig.start // 8) + 7 - sig.start % 8
        raw = (u_be >> np.uint64(64 - msb - n)) & mask
    if sig.is_float:
        if n == 32:
            return raw.astype(np.uint32).view(np.float32).astype(np.float64)
        return raw.view(np.float64)
    if sig.is_signed:
        out = raw.astype(np.int64)
        if n < 64:
            out = np.where(out >= (1 << (n - 1)), out - (1 << n), out)
        return out
    return raw.astype(np.int64)


def _raw_range(sig) -> np.ndarray:
    """The smallest and largest raw value of an integer signal, as float64 (NaN for a float signal: no bound)."""
    n = int(sig.length)
    if sig.is_float or n >= 63:  # (a 64-bit unsigned raw is read as int64: no bound taken)
        return np.array([np.nan, np.nan])
    if sig.is_signed:
        return np.array([-(2.0 ** (n - 1)), 2.0 ** (n - 1) - 1.0])
    return np.array([0.0, 2.0 ** n - 1.0])


def _fits_words(msg) -> bool:
    return msg.length <= 8


def decode_frames(decoder: FrameDecoder, frames: FrameTable) -> tuple[EventArrays, DecodeCounters]:
    """All events of ``frames`` and the decoder counters, as ``decoder.decode`` would give frame by frame.

    ``decoder`` is only read (its plan); its own counters are not touched.
    """
    c = DecodeCounters()
    m = len(frames)
    c.frames = m
    plans = decoder._plans  # noqa: SLF001 - the plan is the decoder's; this is its bulk form
    known = np.array(sorted(decoder._known), dtype=np.int64)  # noqa: SLF001
    planned = np.array(sorted(plans), dtype=np.int64)
    in_plan = np.isin(frames.key, planned)
    n_other = m - int(np.count_nonzero(in_plan))
    in_db = np.isin(frames.key[~in_plan], known) if n_other else np.zeros(0, bool)  # (of the frames not planned)
    c.unmapped = int(np.count_nonzero(in_db))
    c.unknown_id = n_other - c.unmapped
    parts: list[SignalColumn] = []  # in the decoder's order within a frame
    # the frames of each planned id, in frame order: one stable sort of the plan index (radix, int16)
    # instead of a pass over all frames per id
    pos = np.searchsorted(planned, frames.key)
    slot = np.where(in_plan, pos, planned.size).astype(np.int16 if planned.size < 2**15 else np.int64)
    by_slot = np.argsort(slot, kind="stable")
    bounds = np.searchsorted(slot[by_slot], np.arange(planned.size + 1))
    for key, plan in plans.items():
        p = int(np.searchsorted(planned, key))
        idx = by_slot[bounds[p]:bounds[p + 1]]
        if idx.size == 0:
            continue
        ign = frames.ignored[idx]
        n_ign = int(np.count_nonzero(ign))
        c.ignored += n_ign
        if n_ign:
            idx = idx[~ign]
        short = frames.length[idx] < plan.length
        n_short = int(np.count_nonzero(short))
        c.short_frame += n_short
        if n_short:
            idx = idx[~short]
        if idx.size == 0:
            continue
        if not _fits_words(plan.message):
            _decode_per_frame(decoder, frames, idx, c, parts)
            continue
        u_le, u_be = _words(frames.data, idx)
        sigs = {s.name: s for s in plan.message.signals}
        mux = None
        if plan.mux_signal is not None:
            mux = signal_raw(sigs[plan.mux_signal], u_le, u_be)
            defined = np.array(sorted(plan.message._codecs["multiplexers"][plan.mux_signal]), dtype=np.int64)  # noqa: SLF001
            ok = np.isin(mux, defined)
            n_bad = int(np.count_nonzero(~ok))
            c.bad_mux += n_bad
            if n_bad:  # (none dropped, the usual log: no copies)
                idx, u_le, u_be, mux = idx[ok], u_le[ok], u_be[ok], mux[ok]
        if plan.e2e is not None:
            ok = _e2e_keep(plan, sigs, frames, idx, u_le, u_be, mux, c)
            if not ok.all():
                idx, u_le, u_be = idx[ok], u_le[ok], u_be[ok]
                mux = mux[ok] if mux is not None else None
        c.decoded += int(idx.size)
        # the rows of each entry group, in frame order: all rows for the common entries, per multiplexer
        # value the rows of that value (one stable sort of the values instead of a pass per value)
        groups: list[tuple[np.ndarray | None, list]] = []  # (rows, or None for all, entries)
        mapped = 0
        if plan.common:
            groups.append((None, plan.common))
        if mux is not None:
            order, values, bnd = _stable_groups(mux)
            at = {v: j for j, v in enumerate(values.tolist())}
            for mux_value, entries in plan.by_mux.items():
                j = at.get(mux_value)
                if j is not None and entries:
                    rows = order[bnd[j]:bnd[j + 1]]
                    mapped += rows.size
                    groups.append((rows, entries))
        c.unmapped += 0 if plan.common else int(idx.size) - mapped
        for rows, entries in groups:
            if rows is None:  # every row: the arrays as they are
                rows, le, be, mux_rows, frames_of_rows = np.arange(idx.size), u_le, u_be, mux, idx
            else:
                le, be = u_le[rows], u_be[rows]
                mux_rows = mux[rows] if mux is not None else None
                frames_of_rows = idx[rows]  # one array for all the group's signals: _merge_columns sees them share it
            for kind, cell, sname, a, b, lo, hi, na_raws, flags in entries:
                raw = signal_raw(sigs[sname], le, be)
                keep = np.ones(rows.size, dtype=bool)
                if flags:
                    bad = np.zeros(rows.size, dtype=bool)
                    for fname, fval in flags:
                        fsig = sigs[fname]
                        f = signal_raw(fsig, le, be)
                        if fsig.multiplexer_ids and mux_rows is not None:  # not decoded with this mux value: 0
                            f = np.where(np.isin(mux_rows, fsig.multiplexer_ids), f, 0)
                        bad |= (f != 0) if fval is None else (f == fval)
                    c.flagged_invalid += int(np.count_nonzero(bad))
                    keep &= ~bad
                if na_raws:
                    if len(na_raws) == 1:  # (the usual one: np.isin's set logic for a single value is 10x the compare)
                        na = keep & (raw == next(iter(na_raws)))
                    else:
                        na = keep & np.isin(raw, np.array(sorted(na_raws)))
                    c.not_available += int(np.count_nonzero(na))
                    keep &= ~na
                with np.errstate(all="ignore"):
                    si = a * raw.astype(np.float64) + b
                    # a*r+b is monotonic in r (also rounded): within [lo, hi] at the raw extremes, every value
                    # is finite and in range, and the two checks cannot drop anything
                    ends = a * _raw_range(sigs[sname]) + b
                if not (np.isfinite(ends).all() and lo <= ends.min() and ends.max() <= hi):
                    fin = np.isfinite(si)
                    c.non_finite += int(np.count_nonzero(keep & ~fin))
                    keep &= fin
                    rng = keep & ((si < lo) | (si > hi))
                    c.out_of_range += int(np.count_nonzero(rng))
                    keep &= ~rng
                if keep.all():
                    frame_of, value = frames_of_rows, si
                else:
                    k = np.flatnonzero(keep)
                    frame_of, value = idx[rows[k]], si[k]
                parts.append(SignalColumn(int(kind), cell, frame_of, value))
    ev = EventArrays.from_columns(parts, m)
    c.events = ev.size
    return ev, c


def _stable_groups(values: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(order, distinct, bounds)`` of integer ``values``: ``order`` their stable sort (a radix sort on
    int16 keys where the values fit), ``distinct`` the values ascending, the rows holding
    ``distinct[j]`` ``order[bounds[j]:bounds[j + 1]]``, ascending."""
    keys = values
    if values.size and int(values.min()) >= -(2**15) and int(values.max()) < 2**15:
        keys = values.astype(np.int16)
    order = np.argsort(keys, kind="stable")
    s = values[order]
    starts = np.flatnonzero(np.concatenate(([True], s[1:] != s[:-1]))) if s.size else np.zeros(0, np.int64)
    return order, s[starts], np.append(starts, s.size)


def _merge_columns(parts: list[SignalColumn], m: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(frame, kind, cell, value) of the columns' events in frame order, within a frame in the decoder's
    order, by placement instead of a sort.

    A column is one signal's events (frame indices ascending, no frame twice); the columns of a
    frame come in the list in the decoder's order (``decode_frames`` appends them so). With
    ``n_f`` the events of frame ``f``, the frame column is ``f`` repeated ``n_f`` times, and
    ``f`` owns the slots ``[o_f, o_f + n_f)`` (``o`` the running sum of ``n``). Consecutive
    parts over the same frames (the signals of one message, none dropped) form a block of
    ``P`` columns: its frames' next free slots are read once, column ``j`` goes to slot + j.
    """
    blocks: list[tuple[np.ndarray, list]] = []  # (frames, [(kind, cell, values), ...])
    for col in parts:
        fr, k, c, v = col.frame, col.kind, col.cell, col.value
        last = blocks[-1][0] if blocks else None
        if last is not None and (last is fr or (last.size == fr.size and np.array_equal(last, fr))):
            blocks[-1][1].append((k, c, v))
        else:
            blocks.append((fr, [(k, c, v)]))
    counts = np.zeros(m, np.int64)
    for fr, cols in blocks:
        counts[fr] += len(cols)  # (frames unique within a part: a fancy increment counts them)
    frame = np.repeat(np.arange(m, dtype=np.int64), counts)
    nxt = np.cumsum(counts) - counts  # next free slot per frame
    kind = np.empty(frame.size, np.int8)
    cell = np.empty(frame.size, np.int32)
    value = np.empty(frame.size)
    for fr, cols in blocks:
        slot = nxt[fr]
        for j, (k, c, v) in enumerate(cols):
            at = slot + j if j else slot
            kind[at] = k
            cell[at] = c
            value[at] = v
        nxt[fr] = slot + len(cols)
    return frame, kind, cell, value


def _e2e_keep(plan, sigs: dict, frames: FrameTable, idx: np.ndarray, u_le: np.ndarray, u_be: np.ndarray,
              mux: np.ndarray | None, c: DecodeCounters) -> np.ndarray:
    """Which of the frames ``idx`` pass the plan's end-to-end checks (the decoder's ``_e2e_ok`` on arrays); counts the rest."""
    e2e = plan.e2e
    keep = np.ones(idx.size, dtype=bool)
    if e2e.crc_algorithm is not None:
        data = frames.data[idx, : plan.length]
        k = e2e.crc_byte
        bad = crc_rows(e2e.crc_algorithm, np.delete(data, k, axis=1)) != data[:, k]
        c.e2e_crc += int(np.count_nonzero(bad))
        keep &= ~bad
    if e2e.counter is not None:
        rows = np.flatnonzero(keep)
        value = signal_raw(sigs[e2e.counter], u_le[rows], u_be[rows])
        if mux is not None:
            group = mux[rows]
            order = _stable_groups(group)[0]  # frame order within each multiplexer value
        else:  # one group: frame order
            group = np.zeros(rows.size, np.int64)
            order = np.arange(rows.size)
        g, v, t = group[order], value[order], frames.t_s[idx[rows]][order]
        skip = np.zeros(rows.size, dtype=bool)
        # not the first frame of its multiplexer value, nor the first after E2E_RESYNC_S without one
        with np.errstate(invalid="ignore"):
            follows = (g[1:] == g[:-1]) & ~(t[1:] - t[:-1] > E2E_RESYNC_S)
        skip[order[1:]] = follows & (v[1:] != (v[:-1] + 1) % e2e.modulus)
        c.e2e_counter += int(np.count_nonzero(skip))
        keep[rows[skip]] = False
    return keep


def _decode_per_frame(decoder: FrameDecoder, frames: FrameTable, idx: np.ndarray, c: DecodeCounters,
                      parts: list) -> None:
    """Frames of a message wider than 8 bytes: the service's decoder, one frame at a time."""
    import can

    saved, decoder.counters = decoder.counters, DecodeCounters()
    try:
        for i in idx.tolist():
            key = int(frames.key[i])
            msg = can.Message(timestamp=float(frames.t_s[i]), arbitration_id=key & 0x1FFFFFFF,
                              is_extended_id=bool(key & 0x8000_0000), is_fd=True,
                              data=bytes(frames.data[i, : int(frames.length[i])]))
            for kind, cell, value in decoder.decode(msg):
                parts.append(SignalColumn(int(kind), cell, np.array([i]), np.array([value])))
        per = decoder.counters
    finally:
        decoder.counters = saved
    for name in ("decoded", "unmapped", "bad_mux", "decode_error", "non_finite", "out_of_range",
                 "not_available", "flagged_invalid", "e2e_counter", "e2e_crc", "internal_error"):
        setattr(c, name, getattr(c, name) + getattr(per, name))
