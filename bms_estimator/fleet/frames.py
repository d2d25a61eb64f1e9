"""A recorded CAN log -> its frames as arrays (:class:`FrameTable`), without a ``can.Message`` per frame where the format allows.

Readers
-------
``.log`` (candump -L)
    Parsed in bulk with pyarrow's CSV reader (three space-separated columns), the hex
    identifier and payload converted with a byte lookup table. Timestamps are cast by
    Arrow's correctly rounded decimal parser, so they equal python-can's ``float()``
    bit for bit. A file the bulk parser does not cover (CAN FD ``##``, remote ``R``,
    error frames, an ``R``/``T`` direction column, an odd-length payload) is read by
    python-can's :class:`can.io.CanutilsLogReader` instead, message by message. The
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

import gzip
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import DataError

__all__ = ["FRAME_SUFFIXES", "FrameTable", "read_frames", "write_mf4"]

EXTENDED_FLAG = 0x8000_0000  # key = arbitration id | EXTENDED_FLAG for 29-bit ids (as can/decoder.py)
FRAME_SUFFIXES = (".log", ".asc", ".blf", ".mf4")

_CAN_ERR_FLAG = 0x20000000
_HEX = np.full(256, 255, dtype=np.uint8)
for _i, _c in enumerate(b"0123456789abcdef"):
    _HEX[_c] = _i
for _i, _c in enumerate(b"ABCDEF"):
    _HEX[_c] = 10 + _i


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
    if not path.is_file():
        raise DataError(f"{path}: no such log file")
    kind = _suffix(path)
    if kind not in FRAME_SUFFIXES:
        raise DataError(f"{path}: unknown log format {kind or '(no suffix)'!r}; "
                        f"batch reads {', '.join(FRAME_SUFFIXES)}")
    try:
        if kind == ".log":
            table = _read_candump_bulk(path)
            if table is not None:
                return table
        if kind == ".mf4":
            return _read_mf4(path)
        import can

        if not path.name.lower().endswith(".gz"):
            _check_complete(path, kind)
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


def _check_complete(path: Path, kind: str) -> None:
    """A truncated ``.blf`` or ``.asc`` reads without an error in python-can (it stops at the cut): refuse it.

    BLF: the header states the file size its writer closed it with; ASC: writers close the
    file with ``End TriggerBlock``.
    """
    if kind == ".blf":
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


def _fixed_width(arr, width: int, pad_left: bool) -> np.ndarray | None:
    """An Arrow string array padded to ``width`` characters as an (M, width) uint8 array (None if longer)."""
    import pyarrow as pa
    import pyarrow.compute as pc

    if len(arr) == 0:
        return np.zeros((0, width), np.uint8)
    if pc.max(pc.utf8_length(arr)).as_py() > width:
        return None
    padded = (pc.utf8_lpad if pad_left else pc.utf8_rpad)(arr, width=width, padding="0")
    padded = padded.combine_chunks() if isinstance(padded, pa.ChunkedArray) else padded
    offsets = np.frombuffer(padded.buffers()[1], dtype=np.int32)[padded.offset: padded.offset + len(padded) + 1]
    buf = np.frombuffer(padded.buffers()[2], dtype=np.uint8)
    return buf[offsets[0]: offsets[0] + width * len(padded)].reshape(len(padded), width)


def _read_candump_bulk(path: Path) -> FrameTable | None:
    """The common candump layout in bulk; None when the file needs python-can's per-line reader."""
    import pyarrow as pa
    import pyarrow.compute as pc
    import pyarrow.csv as pcsv

    opener = gzip.open if path.suffix.lower() == ".gz" else open
    with opener(path, "rb") as fh:
        raw = fh.read()
    if not raw.strip():
        return FrameTable._build([], [], [], [], [])
    first = raw.lstrip().split(b"\n", 1)[0].strip()
    names = ["ts", "ch", "frame"] + (["dir"] if first[-2:].lower() in (b" r", b" t") else [])
    try:
        tab = pcsv.read_csv(
            pa.py_buffer(raw),
            read_options=pcsv.ReadOptions(column_names=names, block_size=1 << 24),
            parse_options=pcsv.ParseOptions(delimiter=" ", quote_char=False, ignore_empty_lines=True),
            convert_options=pcsv.ConvertOptions(column_types={n: pa.string() for n in names}),
        )
    except (pa.ArrowInvalid, pa.ArrowException):
        return None  # another column count somewhere: the per-line reader decides
    ts = tab.column("ts").combine_chunks()
    frame = tab.column("frame").combine_chunks()
    if ts.null_count or frame.null_count:
        return None
    if not (pc.all(pc.starts_with(ts, "(")).as_py() and pc.all(pc.ends_with(ts, ")")).as_py()):
        return None
    try:
        t = pc.cast(pc.utf8_slice_codeunits(ts, 1, -1), pa.float64()).to_numpy(zero_copy_only=False)
    except (pa.ArrowInvalid, pa.ArrowException):
        return None
    hashpos = pc.find_substring(frame, "#").to_numpy(zero_copy_only=False)
    if (hashpos < 0).any():
        return None
    id_len = hashpos
    # split at the first '#': identifier before, payload after
    parts = pc.split_pattern(frame, "#", max_splits=1)
    id_str = pc.list_element(parts, 0)
    data_str = pc.list_element(parts, 1)
    id_chars = _fixed_width(id_str, 8, pad_left=True)
    data_len = pc.utf8_length(data_str).to_numpy(zero_copy_only=False)
    if id_chars is None or (data_len % 2).any():
        return None  # an id longer than 8 hex digits, an FD frame ('##'), a remote frame 'R' (odd)
    data_chars = _fixed_width(data_str, 16, pad_left=False)
    if data_chars is None:
        return None  # CAN FD payloads: the per-line reader
    id_nib = _HEX[id_chars]
    data_nib = _HEX[data_chars]
    if (id_nib == 255).any() or (data_nib == 255).any():
        return None  # not hex (a remote frame 'R', garbage): the per-line reader reports it
    weights = (16 ** np.arange(7, -1, -1)).astype(np.int64)
    can_id = id_nib.astype(np.int64) @ weights
    if (can_id & _CAN_ERR_FLAG).any():
        return None  # error frames: the per-line reader's rules
    extended = id_len > 3
    data = (data_nib[:, 0::2] << 4) | data_nib[:, 1::2]
    key = (can_id & 0x1FFFFFFF) | np.where(extended, EXTENDED_FLAG, 0)
    m = len(t)
    return FrameTable(t.astype(float), key.astype(np.int64), (data_len // 2).astype(np.int16),
                      np.ascontiguousarray(data, dtype=np.uint8), np.zeros(m, dtype=bool))


def _read_mf4(path: Path) -> FrameTable:
    """Raw CAN frames of the bus-logging groups of an MF4 file (asammdf)."""
    from asammdf import MDF

    ts_parts, key_parts, len_parts, data_parts = [], [], [], []
    with MDF(str(path)) as mdf:
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
