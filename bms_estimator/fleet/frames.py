"""A recorded CAN log -> its frames as arrays (:class:`FrameTable`), without a ``can.Message`` per frame where the format allows.

Readers
-------
``.log`` (candump -L)
    Parsed in bulk with numpy on the file's bytes: the fields are cut at the offsets of
    ``(``, ``.``, ``)``, the spaces and ``#``, the hex identifier and payload converted with
    byte arithmetic, the timestamp from its decimal digits by one exact division, so it
    equals python-can's ``float()`` bit for bit (:func:`_read_candump_bulk`). A file the
    bulk parser does not cover (CAN FD ``##``, remote ``R``, error frames, tabs or double
    spaces, a mixed column count, an odd-length payload, more than 15 timestamp digits) is
    read by python-can's :class:`can.io.CanutilsLogReader` instead, message by message. The
    optional direction column (``R``/``T``) is read and not used, as python-can does.
``.asc``, ``.blf``
    python-can's readers, message by message (the formats force it: ASC lines have
    many layouts, BLF is zlib-compressed object containers); the messages go straight
    into arrays. Measured cost: see the README's fleet section.
``.mf4``
    asammdf, the raw ``CAN_DataFrame`` bus-logging channels (ID, IDE, DataLength,
    DataBytes and the group's master time) of every CAN group, in time order. The
    payload is decoded by :mod:`.decode` with the service's DBC and mapping, not by
    asammdf's own signal decoding, so that NotAvailable, invalid flags and range
    checks are the service's.

A file that cannot be read raises :class:`~bms_estimator.errors.DataError` naming the
file and the problem, and so does a truncated ``.blf`` (smaller than its header states) or
``.asc`` (without its closing ``End TriggerBlock``), which python-can would read up to the
cut without a word (an empty file gives an empty table, which the caller reports).
"""

from __future__ import annotations

import gc
import gzip
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import DataError, one_line_error

__all__ = ["FRAME_SUFFIXES", "FrameTable", "read_frames", "write_mf4"]

EXTENDED_FLAG = 0x8000_0000  # key = arbitration id | EXTENDED_FLAG for 29-bit ids (as can/decoder.py)
FRAME_SUFFIXES = (".log", ".asc", ".blf", ".mf4")

_CAN_ERR_FLAG = 0x20000000


@dataclass(frozen=True, eq=False)
class FrameTable:
    """M frames in log order: what a receiver would have been handed, as arrays."""

    t_s: np.ndarray  # (M,) float64 timestamp
    key: np.ndarray  # (M,) int64 arbitration id | EXTENDED_FLAG for extended ids
    length: np.ndarray  # (M,) int16 payload bytes (0 for remote and error frames)
    data: np.ndarray  # (M, W) uint8 payload, zero-padded, W >= 8
    ignored: np.ndarray  # (M,) bool: error or remote frame (the decoder ignores them)

    def __len__(self) -> int:
        return int(self.t_s.shape[0])

    @classmethod
    def from_messages(cls, messages) -> FrameTable:
        """Arrays from python-can messages (one Python step per message)."""
        t: list[float] = []
        key: list[int] = []
        length: list[int] = []
        ign: list[bool] = []
        payloads: list[bytes] = []
        for m in messages:
            t.append(m.timestamp)
            key.append(m.arbitration_id | (EXTENDED_FLAG if m.is_extended_id else 0))
            ign.append(bool(m.is_error_frame or m.is_remote_frame))
            d = bytes(m.data) if m.data is not None else b""
            length.append(len(d))
            payloads.append(d)
        return cls._build(t, key, length, ign, payloads)

    @classmethod
    def _build(cls, t, key, length, ign, payloads) -> FrameTable:
        m = len(t)
        lengths = np.asarray(length, dtype=np.int16).reshape(m)
        width = max(8, int(lengths.max()) if m else 8)
        joined = b"".join(p.ljust(width, b"\0") for p in payloads)
        data = np.frombuffer(joined, dtype=np.uint8).reshape(m, width).copy() if m else np.zeros((0, width), np.uint8)
        return cls(np.asarray(t, dtype=float).reshape(m), np.asarray(key, dtype=np.int64).reshape(m), lengths,
                   data, np.asarray(ign, dtype=bool).reshape(m))


def _suffix(path: Path) -> str:
    suffixes = [s.lower() for s in path.suffixes]
    if suffixes and suffixes[-1] == ".gz":
        suffixes = suffixes[:-1]
    return suffixes[-1] if suffixes else ""


def read_frames(path: str | Path) -> FrameTable:
    """All frames of a ``.log``/``.asc``/``.blf`` (optionally ``.gz``) or ``.mf4`` file.

    Raises :class:`DataError` for a missing, unreadable or malformed file.
    """
    path = Path(path)
    if path.is_dir():
        raise DataError(f"{path}: a directory, not a log file")
    if not path.is_file():
        raise DataError(f"{path}: no such log file")
    kind = _suffix(path)
    if kind not in FRAME_SUFFIXES:
        raise DataError(f"{path}: unknown log format {kind or '(no suffix)'!r}; "
                        f"batch reads {', '.join(FRAME_SUFFIXES)}")
    try:
        check_log_complete(path, kind)
        if kind == ".log":
            table = _read_candump_bulk(path)
            if table is not None:
                return table
        if kind == ".mf4":
            return _read_mf4(path)
        import can

        reader = can.LogReader(str(path))
        try:
            return FrameTable.from_messages(reader)
        finally:
            stop = getattr(reader, "stop", None)
            if stop is not None:
                stop()
    except DataError:
        raise
    except Exception as exc:  # noqa: BLE001 - every reader raises its own kinds on a corrupt file
        text = str(exc).strip().splitlines()
        raise DataError(f"{path}: cannot read the log: {type(exc).__name__}: {text[0] if text else ''}") from None


def check_log_complete(path: Path, kind: str) -> None:
    """A truncated ``.blf``, ``.asc`` or candump ``.log`` reads up to the cut, or fails on its cut line: refuse it.

    BLF: the header states the file size its writer closed it with; ASC: writers close the
    file with ``End TriggerBlock``; candump: every writer ends each line with a line end, so a
    last byte that is not one is a cut line (python-can read it as a shortened frame, or failed
    with "not enough values to unpack"). A ``.gz`` file is not checked (its own CRC finds a cut). An empty
    file is refused as one (a ``.blf`` read "unpack requires a buffer of 72 bytes").
    """
    if path.stat().st_size == 0:  # (a .blf read "unpack requires a buffer of 72 bytes")
        raise DataError(f"{path}: empty log (the file is 0 bytes): no CAN frame in it")
    if path.name.lower().endswith(".gz"):
        return
    if kind == ".log":
        size = path.stat().st_size
        if size:
            with open(path, "rb") as fh:
                first = fh.read(1)
                fh.seek(size - 1)
                last = fh.read(1)
            if first == b"(" and last not in (b"\n", b"\r"):  # (not a candump line at all: the reader says so)
                raise DataError(f"{path}: its last line has no line end: the log is truncated")
    elif kind == ".blf":
        from can.io.blf import BLFReader

        reader = BLFReader(str(path))
        try:
            stated = int(reader.file_size)
        finally:
            reader.stop()
        actual = path.stat().st_size
        if stated and actual < stated:
            raise DataError(f"{path}: truncated BLF file ({actual} of the {stated} bytes its header states)")
    elif kind == ".asc":
        with path.open("rb") as fh:
            fh.seek(max(0, path.stat().st_size - 4096))
            tail = fh.read()
        if tail.strip() and b"end triggerblock" not in tail.lower():
            raise DataError(f"{path}: truncated ASC file (no 'End TriggerBlock' at its end)")


#: lines parsed per block by the bulk candump reader (bounds its (lines, 16) temporaries to ~100 MB)
_BLOCK_LINES = 1 << 20
#: most decimal digits of a timestamp the bulk reader converts itself (mantissa < 2**53: exact in a float64)
_TS_DIGITS = 15


def _positions(buf: np.ndarray, char: bytes, lines: int) -> np.ndarray | None:
    """Offsets of ``char`` in ``buf``, when it occurs exactly ``lines`` times (once per line), else None."""
    pos = np.flatnonzero(buf == ord(char))
    return pos if pos.size == lines else None


def _read_candump_bulk(path: Path) -> FrameTable | None:
    """The common candump layout in bulk, with numpy on the raw bytes; None when a line needs python-can's reader.

    Every line must be ``(SECONDS.FRACTION) CHANNEL ID#DATA`` with an optional ``R``/``T``
    direction column (read, not used, as python-can does), single spaces, the same column
    count on every line, an identifier of 1..8 and a payload of 0..16 hex digits. Fields are
    found by the offsets of ``(``, ``.``, ``)``, the spaces and ``#`` (each once per line).

    Timestamps: the digits give an integer mantissa ``m`` (at most 15 digits, so exact in a
    float64) and a fraction length ``f``; ``m / 10**f`` is one IEEE division of two exact
    numbers, hence the correctly rounded value of the decimal, which is what Python's
    ``float()`` returns: bit for bit python-can's timestamp.
    """
    opener = gzip.open if path.suffix.lower() == ".gz" else open
    with opener(path, "rb") as fh:
        raw = fh.read()
    if not raw or raw.isspace():  # (not raw.strip(): that copies the whole file)
        return FrameTable._build([], [], [], [], [])
    if b"\r" in raw:
        raw = raw.replace(b"\r\n", b"\n")
    if not raw.endswith(b"\n"):
        raw += b"\n"
    buf = np.frombuffer(raw, dtype=np.uint8)
    ends = np.flatnonzero(buf == 10)
    starts = np.concatenate(([0], ends[:-1] + 1))
    if (ends == starts).any():  # blank lines: skip them, as python-can does
        keep = ends > starts
        raw = b"\n".join(raw[a:b] for a, b in zip(starts[keep].tolist(), ends[keep].tolist())) + b"\n"
        buf = np.frombuffer(raw, dtype=np.uint8)
        ends = np.flatnonzero(buf == 10)
        starts = np.concatenate(([0], ends[:-1] + 1))
    lines = ends.size
    spaces = np.flatnonzero(buf == 32)
    if spaces.size not in (2 * lines, 3 * lines):
        return None
    spaces = spaces.reshape(lines, -1)
    dots, hashes = _positions(buf, b".", lines), _positions(buf, b"#", lines)
    if dots is None or hashes is None:
        return None  # a CAN FD frame ('##'), a timestamp without a fraction, ...
    frame_end = ends
    if spaces.shape[1] == 3:  # the direction column: one character, R or T
        frame_end = spaces[:, 2]
        if ((ends - frame_end) != 2).any() or not np.isin(buf[ends - 1], np.frombuffer(b"RrTt", np.uint8)).all():
            return None
    close = spaces[:, 0] - 1
    id_start = spaces[:, 1] + 1
    if not ((buf[starts] == ord("(")).all() and (buf[close] == ord(")")).all()
            and ((starts < dots) & (dots < close)).all() and ((id_start < hashes) & (hashes < frame_end)).all()):
        return None
    out = [_candump_block(buf, starts[a:a + _BLOCK_LINES], dots[a:a + _BLOCK_LINES], close[a:a + _BLOCK_LINES],
                          id_start[a:a + _BLOCK_LINES], hashes[a:a + _BLOCK_LINES], frame_end[a:a + _BLOCK_LINES])
           for a in range(0, lines, _BLOCK_LINES)]
    if any(part is None for part in out):
        return None
    t, key, length, data = (np.concatenate(col) for col in zip(*out))
    return FrameTable(t, key, length, data, np.zeros(lines, dtype=bool))


def _by_length(first: np.ndarray, count: np.ndarray):
    """Groups of the fields ``[first, first + count)`` of equal length: (length, line indices or slice, first)."""
    present = np.flatnonzero(np.bincount(count))
    if present.size == 1:
        yield int(present[0]), slice(None), first
        return
    for c in present.tolist():
        sel = np.flatnonzero(count == c)
        yield c, sel, first[sel]


def _rows(buf: np.ndarray, first: np.ndarray, width: int) -> np.ndarray:
    """``buf[first[k]:first[k] + width]`` for every k, as a (len(first), width) array (one row copy each)."""
    if width == 0:
        return np.zeros((first.size, 0), np.uint8)
    return np.lib.stride_tricks.sliding_window_view(buf, width)[first]


def _hex_digits(chars: np.ndarray) -> np.ndarray | None:
    """The values of hex digit characters (uint8 array of ``0-9a-fA-F``), None if any is another character.

    Arithmetic instead of a 256-entry table lookup (a third faster): ``c | 32`` folds ``A-F`` onto
    ``a-f``; a digit's value is ``(c & 15) + 9 (c >> 6)`` (``0-9``: ``c >> 6`` is 0; letters: 1).
    """
    low = chars | 32
    ok = (chars >= 48) & (chars <= 57)
    ok |= (low >= 97) & (low <= 102)
    if not ok.all():
        return None
    return (chars & 15) + 9 * (chars >> 6)


_DEC = np.full(256, 255, dtype=np.uint8)
_DEC[np.frombuffer(b"0123456789", np.uint8)] = np.arange(10, dtype=np.uint8)


def _candump_block(buf, starts, dots, close, id_start, hashes, frame_end):
    """Timestamps, keys, lengths and payloads of one block of candump lines (None: leave it to python-can)."""
    m = starts.size
    n_int, n_frac = dots - starts - 1, close - dots - 1
    if (n_int < 1).any() or (n_int + n_frac > _TS_DIGITS).any():
        return None
    t = np.empty(m)
    # groups of equal width (dot included) and fraction length: key = width * 16 + n_frac (n_frac < 15)
    for key, sel, first in _by_length(starts + 1, (close - starts - 1) * 16 + n_frac):
        w, f = divmod(key, 16)
        digits = _DEC[np.delete(_rows(buf, first, w), w - 1 - f, axis=1)]
        if (digits == 255).any():
            return None
        mantissa = digits.astype(np.int64) @ (10 ** np.arange(w - 2, -1, -1, dtype=np.int64))
        t[sel] = mantissa.astype(np.float64) / 10.0**f  # both exact: one correctly rounded division
    id_len, data_len = hashes - id_start, frame_end - hashes - 1
    if (id_len < 1).any() or (id_len > 8).any() or (data_len % 2).any() or (data_len > 16).any():
        return None  # an empty or over-long id, a remote frame ('R': odd), a payload over 8 bytes
    can_id = np.empty(m, np.int64)
    for w, sel, first in _by_length(id_start, id_len):
        nib = _hex_digits(_rows(buf, first, w))
        if nib is None:
            return None
        if w == 8:  # (the 29-bit ids) nibble pairs -> 4 bytes -> one big-endian uint32
            can_id[sel] = ((nib[:, 0::2] << 4) | nib[:, 1::2]).view(">u4").ravel()
        else:
            can_id[sel] = nib.astype(np.int64) @ (16 ** np.arange(w - 1, -1, -1, dtype=np.int64))
    if (can_id & _CAN_ERR_FLAG).any():
        return None  # error frames: the per-line reader's rules
    data = np.zeros((m, 8), np.uint8)
    for w, sel, first in _by_length(hashes + 1, data_len):
        nib = _hex_digits(_rows(buf, first, w))
        if nib is None:
            return None  # not hex (a remote frame 'R', garbage): the per-line reader reports it
        data[sel, : w // 2] = (nib[:, 0::2] << 4) | nib[:, 1::2]
    key = (can_id & 0x1FFFFFFF) | np.where(id_len > 3, EXTENDED_FLAG, 0)
    return t, key.astype(np.int64), (data_len // 2).astype(np.int16), data


def _open_mdf(path: Path):
    """asammdf's reader of ``path``; :class:`DataError` when it cannot open the file (a truncated one: "seek out
    of range"). The reader asammdf leaves half-built then fails again in its ``__del__`` when the garbage
    collector frees it, which Python printed as a traceback per file (from the worker): collected here, muted."""
    from asammdf import MDF

    try:
        return MDF(str(path))
    except Exception as exc:  # noqa: BLE001 - asammdf raises its own kinds, and ValueError, on a bad file
        problem = one_line_error(exc)
    hook = sys.unraisablehook
    sys.unraisablehook = lambda u: None if _from_asammdf(u.object) else hook(u)
    try:
        gc.collect()
    finally:
        sys.unraisablehook = hook
    raise DataError(f"{path}: cannot read the MF4 file (truncated or corrupt?): {problem}")


def _from_asammdf(obj) -> bool:
    return str(getattr(obj, "__module__", "")).startswith("asammdf")


def _read_mf4(path: Path) -> FrameTable:
    """Raw CAN frames of the bus-logging groups of an MF4 file (asammdf)."""
    ts_parts, key_parts, len_parts, data_parts = [], [], [], []
    with _open_mdf(path) as mdf:
        for index, group in enumerate(mdf.groups):
            names = {ch.name for ch in group.channels}
            if "CAN_DataFrame.ID" not in names or "CAN_DataFrame.DataBytes" not in names:
                continue
            ident = mdf.get("CAN_DataFrame.ID", group=index, raw=True)
            if len(ident.timestamps) == 0:
                continue
            payload = mdf.get("CAN_DataFrame.DataBytes", group=index, raw=True).samples
            ide = (mdf.get("CAN_DataFrame.IDE", group=index, raw=True).samples.astype(bool)
                   if "CAN_DataFrame.IDE" in names else np.zeros(len(ident.timestamps), bool))
            dlen = (mdf.get("CAN_DataFrame.DataLength", group=index, raw=True).samples.astype(np.int16)
                    if "CAN_DataFrame.DataLength" in names else np.full(len(ident.timestamps), payload.shape[1]))
            ids = ident.samples.astype(np.int64)
            ide = ide | ((ids & EXTENDED_FLAG) != 0)  # some loggers set bit 31 for extended ids
            ts_parts.append(np.asarray(ident.timestamps, dtype=float))
            key_parts.append((ids & 0x1FFFFFFF) | np.where(ide, EXTENDED_FLAG, 0))
            len_parts.append(dlen)
            width = max(8, payload.shape[1])
            buf = np.zeros((len(ids), width), np.uint8)
            buf[:, : payload.shape[1]] = payload
            data_parts.append(buf)
    if not ts_parts:
        return FrameTable._build([], [], [], [], [])
    width = max(d.shape[1] for d in data_parts)
    data = np.concatenate([np.pad(d, ((0, 0), (0, width - d.shape[1]))) for d in data_parts])
    t = np.concatenate(ts_parts)
    order = np.argsort(t, kind="stable")
    return FrameTable(t[order], np.concatenate(key_parts)[order], np.concatenate(len_parts)[order].astype(np.int16),
                      data[order], np.zeros(len(t), bool))


def write_mf4(frames: FrameTable, path: str | Path) -> Path:
    """Write ``frames`` as an ASAM MDF 4.11 bus-logging file (one ``CAN_DataFrame`` group, as CAN loggers do).

    For tests and benchmarks: the file reads back with :func:`read_frames` bit for bit, and
    asammdf's ``extract_bus_logging`` decodes it with a DBC. Error and remote frames are
    not written (they have no data frame record).
    """
    from asammdf import MDF, Signal
    from asammdf.blocks.source_utils import Source

    keep = ~frames.ignored
    m = int(np.count_nonzero(keep))
    width = frames.data.shape[1]
    dt = np.dtype([("CAN_DataFrame.BusChannel", "<u1"), ("CAN_DataFrame.ID", "<u4"), ("CAN_DataFrame.IDE", "<u1"),
                   ("CAN_DataFrame.DLC", "<u1"), ("CAN_DataFrame.DataLength", "<u1"),
                   ("CAN_DataFrame.DataBytes", "<u1", (width,))])
    rec = np.zeros(m, dt)
    rec["CAN_DataFrame.BusChannel"] = 1
    rec["CAN_DataFrame.ID"] = frames.key[keep] & 0x1FFFFFFF
    rec["CAN_DataFrame.IDE"] = (frames.key[keep] & EXTENDED_FLAG) != 0
    rec["CAN_DataFrame.DLC"] = frames.length[keep]
    rec["CAN_DataFrame.DataLength"] = frames.length[keep]
    rec["CAN_DataFrame.DataBytes"] = frames.data[keep]
    src = Source(name="CAN1", path="CAN1", comment="", source_type=Source.SOURCE_BUS, bus_type=Source.BUS_TYPE_CAN)
    mdf = MDF(version="4.11")
    mdf.append([Signal(samples=rec, timestamps=frames.t_s[keep], name="CAN_DataFrame", source=src)],
               acq_name="CAN1", acq_source=src, common_timebase=True)
    path = Path(path)
    mdf.save(str(path), overwrite=True)
    mdf.close()
    return path
