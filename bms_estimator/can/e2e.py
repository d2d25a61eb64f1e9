"""End-to-end protection of input frames: an alive (message) counter and a CRC or checksum.

The mapping names them per input message (``[e2e.<message>]``, see
:mod:`bms_estimator.can.mapping`); the decoder drops a frame that fails and counts it
(``e2e_counter``, ``e2e_crc``). The project's DBC carries them on every input frame and its
preset checks them by default; :class:`E2EStamper` is the sender's side (``encode-log``,
the demo's feed, the benches and the tests make their frames with it).

Counter: an unsigned signal of ``L`` bits that the sender increments by one per frame
(per multiplexer value for a multiplexed message), modulo :math:`2^L` (or its DBC maximum
+ 1). A frame is accepted when

.. math:: c_k = (c_{k-1} + 1) \\bmod m,

the first frame after start is accepted as the reference, and so is a frame more than
``E2E_RESYNC_S`` (5 s, the sampler's default gap) of frame time after the previous frame of its
group: a sender that slept while the vehicle was parked wakes with its counters restarted, which
is no lost or injected frame (each group's first frame after a wake was dropped and counted: a
false alarm of about 100 frames per wake for 200 cells). A frame whose counter is not the
next one (a skipped value: a lost or injected frame; a repeated value: a frozen sender) is
dropped, and the counter re-synchronises on it, so one lost frame on the bus costs the frame
after it too and nothing more. A frame dropped for its CRC is checked no further: its counter
is not trusted and does not move the reference, so after a corrupted frame the sender's next
one is dropped as a skip too, and after an injected one it is accepted.

CRC: an 8-bit, byte-aligned signal; the CRC is computed over the frame's other data bytes in
their order (the CRC byte left out) and must equal it. Algorithms (``crc_algorithm``):

* ``crc8_sae_j1850``: polynomial 0x1D, initial value 0xFF, final XOR 0xFF (AUTOSAR E2E profile 1/2's CRC-8);
* ``crc8_autosar``: polynomial 0x2F, initial value 0xFF, final XOR 0xFF (CRC-8H2F);
* ``xor8``: XOR of the bytes; ``sum8``: their sum modulo 256 (simple checksums).

Each has a scalar form (``CRC_ALGORITHMS``, one frame) and an array form
(:func:`crc_rows`, one CRC per row of an ``(n, L)`` byte array: the same table walked
column by column), so the fleet's bulk decode and ``encode-log`` give the decoder's bytes.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from ..errors import MappingError
from .mapping import CanMapping, E2ECheck, load_mapping

if TYPE_CHECKING:  # pragma: no cover
    from cantools.database.can import Database, Message

__all__ = [
    "CRC_ALGORITHMS",
    "E2E_RESYNC_S",
    "E2ELayout",
    "E2EStamper",
    "crc8_autosar",
    "crc8_sae_j1850",
    "crc_rows",
    "e2e_layout",
    "sum8",
    "xor8",
]

#: CRC-8 parameters (polynomial, initial value, final XOR) by ``crc_algorithm`` name
_CRC8_PARAMS = {"crc8_sae_j1850": (0x1D, 0xFF, 0xFF), "crc8_autosar": (0x2F, 0xFF, 0xFF)}


def _crc8_table(poly: int) -> tuple[int, ...]:
    table = []
    for byte in range(256):
        crc = byte
        for _ in range(8):
            crc = ((crc << 1) ^ poly) & 0xFF if crc & 0x80 else (crc << 1) & 0xFF
        table.append(crc)
    return tuple(table)


_TABLES = {name: _crc8_table(poly) for name, (poly, _, _) in _CRC8_PARAMS.items()}


def _crc8(name: str) -> Callable[[bytes], int]:
    table = _TABLES[name]
    _, init, xorout = _CRC8_PARAMS[name]

    def crc(data: bytes) -> int:
        c = init
        for b in data:
            c = table[c ^ b]
        return c ^ xorout

    return crc


crc8_sae_j1850 = _crc8("crc8_sae_j1850")
crc8_autosar = _crc8("crc8_autosar")


def xor8(data: bytes) -> int:
    c = 0
    for b in data:
        c ^= b
    return c


def sum8(data: bytes) -> int:
    return sum(data) & 0xFF


#: frame-time seconds without a frame of a counter group after which its counter starts afresh (module docstring)
E2E_RESYNC_S = 5.0

#: ``crc_algorithm`` name -> function of the protected bytes
CRC_ALGORITHMS: dict[str, Callable[[bytes], int]] = {
    "crc8_sae_j1850": crc8_sae_j1850,
    "crc8_autosar": crc8_autosar,
    "xor8": xor8,
    "sum8": sum8,
}


def crc_rows(algorithm: str, data: np.ndarray) -> np.ndarray:
    """``CRC_ALGORITHMS[algorithm]`` of every row of ``data`` (``(n, L)`` uint8), as ``(n,)`` uint8."""
    data = np.asarray(data, dtype=np.uint8)
    if data.ndim != 2:
        raise ValueError("data must be (frames, bytes)")
    if algorithm == "xor8":
        return np.bitwise_xor.reduce(data, axis=1) if data.shape[1] else np.zeros(len(data), np.uint8)
    if algorithm == "sum8":
        return (data.sum(axis=1, dtype=np.int64) & 0xFF).astype(np.uint8)
    if algorithm not in _CRC8_PARAMS:
        raise ValueError(f"unknown crc_algorithm {algorithm!r}")
    table = np.array(_TABLES[algorithm], dtype=np.uint8)
    _, init, xorout = _CRC8_PARAMS[algorithm]
    c = np.full(len(data), init, dtype=np.uint8)
    for col in range(data.shape[1]):
        c = table[c ^ data[:, col]]
    return c ^ np.uint8(xorout)


# ------------------------------------------------------------------- layout
@dataclass(frozen=True)
class E2ELayout:
    """Where the checks of one message sit in its payload (little-endian bit numbering)."""

    message: str
    length: int  # payload bytes
    counter: str | None  # alive counter signal
    counter_field: tuple[int, int] | None  # (start bit, bits) of an Intel counter, else None
    modulus: int  # counter values 0 .. modulus - 1
    crc: str | None
    crc_byte: int  # -1 without a CRC
    crc_algorithm: str | None
    mux_field: tuple[int, int] | None  # (start bit, bits) of an Intel multiplexer: counters run per value


def _intel_field(sig: Any) -> tuple[int, int] | None:
    return (int(sig.start), int(sig.length)) if sig.byte_order == "little_endian" else None


def e2e_layout(msg: Message, check: E2ECheck) -> tuple[E2ELayout | None, list[str]]:
    """The layout of ``check`` in ``msg``, or the problems that make it unusable."""
    name = msg.name
    problems: list[str] = []
    names = {s.name: s for s in msg.signals}
    modulus, crc_byte, counter_field = 0, -1, None
    if check.counter is not None:
        sig = names.get(check.counter)
        if sig is None:
            problems.append(f"e2e.{name}: counter signal {check.counter!r} not in the message")
        elif sig.is_signed or sig.multiplexer_ids:
            problems.append(f"e2e.{name}: counter {check.counter!r} must be unsigned and not multiplexed")
        else:
            top = (1 << sig.length) - 1
            if sig.maximum is not None and sig.scale == 1 and sig.offset == 0:
                top = min(top, int(sig.maximum))
            modulus = top + 1
            counter_field = _intel_field(sig)
    if check.crc is not None:
        sig = names.get(check.crc)
        if sig is None:
            problems.append(f"e2e.{name}: crc signal {check.crc!r} not in the message")
        else:
            lsb = sig.start if sig.byte_order == "little_endian" else sig.start - 7
            if sig.length != 8 or lsb % 8 != 0 or sig.multiplexer_ids:
                problems.append(f"e2e.{name}: crc {check.crc!r} must be 8 bit, byte aligned, not multiplexed")
            else:
                crc_byte = lsb // 8
    if problems:
        return None, problems
    muxes = [s for s in msg.signals if s.is_multiplexer]
    mux_field = _intel_field(muxes[0]) if len(muxes) == 1 else None
    return E2ELayout(name, int(msg.length), check.counter, counter_field, modulus, check.crc, crc_byte,
                     check.crc_algorithm if check.crc is not None else None, mux_field), []


# ------------------------------------------------------------------- sender
def _get(x: int, field: tuple[int, int]) -> int:
    return (x >> field[0]) & ((1 << field[1]) - 1)


class E2EStamper:
    """The sender's side of the checks: the next alive counter value and the CRC, written into frames.

    Built from a DBC and a mapping (its ``[e2e.*]`` tables; a preset name, TOML path, dict or
    :class:`~bms_estimator.can.mapping.CanMapping`). The counter runs per frame id and
    multiplexer value, from 0, in the order frames are stamped. Frames of other messages pass
    unchanged. Intel (little-endian) counters are written as bit fields, others (foxBMS' IVT-S)
    through cantools; :meth:`stamp_rows` takes Intel counters only.
    """

    def __init__(self, db: Database, mapping: CanMapping | str | dict = "default") -> None:
        m = load_mapping(mapping)
        self._layouts: dict[int, E2ELayout] = {}
        self._messages: dict[int, Message] = {}
        problems: list[str] = []
        for name, check in m.e2e.items():
            try:
                msg = db.get_message_by_name(name)
            except KeyError:
                problems.append(f"e2e.{name}: message not in the DBC")
                continue
            layout, bad = e2e_layout(msg, check)
            if bad:
                problems += bad
                continue
            self._layouts[int(msg.frame_id)] = layout
            self._messages[int(msg.frame_id)] = msg
        if problems:
            raise MappingError("E2E checks do not fit the DBC:", problems)
        self._next: dict[tuple[int, int | None], int] = {}
        self._db = db

    def encode(self, name: str, values: dict[str, Any], *, scaling: bool = True, strict: bool = True) -> bytes:
        """cantools' ``encode_message`` of ``values``, stamped: the counter and CRC signals may be left
        out (then the next value and the right CRC); a counter or CRC that ``values`` names is kept."""
        msg = self._db.get_message_by_name(name)
        layout = self._layouts.get(int(msg.frame_id))
        if layout is None:
            return bytes(self._db.encode_message(name, values, scaling=scaling, strict=strict))
        checks = [k for k in (layout.counter, layout.crc) if k is not None]
        data = bytes(self._db.encode_message(name, {**{k: 0 for k in checks}, **values}, scaling=scaling,
                                             strict=strict))
        counter = None
        if layout.counter is not None and layout.counter in values:
            counter = self._counter_of(int(msg.frame_id), layout, data)
        out = self.stamp(msg.frame_id, data, counter=counter)
        if layout.crc is not None and layout.crc in values:
            k = layout.crc_byte
            out = out[:k] + data[k: k + 1] + out[k + 1:]
        return out

    def layout(self, frame_id: int) -> E2ELayout | None:
        return self._layouts.get(int(frame_id))

    def _counter_put(self, layout: E2ELayout, x: int, value: int) -> int:
        start, bits = layout.counter_field  # type: ignore[misc]
        mask = ((1 << bits) - 1) << start
        return (x & ~mask) | ((value % layout.modulus) << start)

    @staticmethod
    def _crc_put(layout: E2ELayout, data: bytearray) -> None:
        if layout.crc_algorithm is not None:
            k = layout.crc_byte
            data[k] = CRC_ALGORITHMS[layout.crc_algorithm](bytes(data[:k] + data[k + 1:]))

    def _raw(self, frame_id: int, data: bytes) -> dict[str, int]:
        return self._messages[frame_id].decode(data, decode_choices=False, scaling=False)

    def _counter_of(self, frame_id: int, layout: E2ELayout, data: bytes) -> int:
        if layout.counter_field is not None:
            return _get(int.from_bytes(data[: layout.length], "little"), layout.counter_field)
        return int(self._raw(frame_id, data)[layout.counter])  # a big-endian counter: cantools

    def _mux_of(self, frame_id: int, layout: E2ELayout, data: bytes) -> int | None:
        if layout.mux_field is not None:
            return _get(int.from_bytes(data[: layout.length], "little"), layout.mux_field)
        muxes = [sg.name for sg in self._messages[frame_id].signals if sg.is_multiplexer]
        return int(self._raw(frame_id, data)[muxes[0]]) if muxes else None

    def _with_counter(self, frame_id: int, layout: E2ELayout, data: bytes, value: int) -> bytes:
        n = layout.length
        if layout.counter_field is not None:
            x = self._counter_put(layout, int.from_bytes(data[:n], "little"), value)
            return x.to_bytes(n, "little") + bytes(data[n:])
        raw = self._raw(frame_id, data)
        raw[layout.counter] = value % layout.modulus
        out = bytearray(self._messages[frame_id].encode(raw, scaling=False, strict=False, padding=False))
        mask = bytearray(self._messages[frame_id].encode(
            {k: 0 for k in raw}, scaling=False, strict=False, padding=True))  # 1 where no signal
        return bytes((o & ~m) | (d & m) for o, m, d in zip(out, mask, bytearray(data[:n]))) + bytes(data[n:])

    def stamp(self, frame_id: int, data: bytes, *, counter: int | None = None) -> bytes:
        """``data`` with the next counter value (or ``counter``) and its CRC."""
        frame_id = int(frame_id)
        layout = self._layouts.get(frame_id)
        data = bytes(data)
        if layout is None or len(data) < layout.length:  # not protected, or too short to be
            return data
        if layout.counter is not None:
            key = (frame_id, self._mux_of(frame_id, layout, data))
            value = self._next.get(key, 0) if counter is None else int(counter)
            self._next[key] = (value + 1) % layout.modulus
            data = self._with_counter(frame_id, layout, data, value)
        out = bytearray(data)
        self._crc_put(layout, out)
        return bytes(out)

    def next_after(self, frame_id: int, data: bytes) -> bytes:
        """A copy of ``data`` carrying the counter value after its own (a sender repeating a frame)."""
        layout = self._layouts.get(int(frame_id))
        if layout is None or layout.counter is None:
            return self.stamp(frame_id, data)
        own = self._counter_of(int(frame_id), layout, bytes(data))
        return self.stamp(frame_id, data, counter=(own + 1) % layout.modulus)

    def stamp_rows(self, frame_id: int, payload: np.ndarray) -> np.ndarray:
        """Vectorised :meth:`stamp` of ``n`` frames of one message in sending order: ``payload``
        is ``(n,)`` uint64 (8-byte little-endian payloads); returns the stamped copy."""
        payload = np.asarray(payload, dtype=np.uint64).copy()
        layout = self._layouts.get(int(frame_id))
        if layout is None or payload.size == 0:
            return payload
        if layout.length != 8 or (layout.counter is not None and layout.counter_field is None):
            raise ValueError(f"{layout.message}: stamp_rows handles 8-byte frames with a little-endian counter only")
        if layout.counter is not None:
            if layout.mux_field is not None:
                s, b = layout.mux_field
                mux = ((payload >> np.uint64(s)) & np.uint64((1 << b) - 1)).astype(np.int64)
            else:
                mux = np.zeros(payload.size, np.int64)
            values, inv = np.unique(mux, return_inverse=True)
            order = np.argsort(inv, kind="stable")
            counts = np.bincount(inv)
            first = np.concatenate([[0], np.cumsum(counts)[:-1]])
            rank = np.empty(payload.size, np.int64)
            rank[order] = np.arange(payload.size) - np.repeat(first, counts)
            muxed = layout.mux_field is not None
            start = np.array([self._next.get((int(frame_id), int(v) if muxed else None), 0) for v in values])
            counter = (start[inv] + rank) % layout.modulus
            for v, s0, cnt in zip(values, start, counts):
                self._next[(int(frame_id), int(v) if muxed else None)] = int((s0 + cnt) % layout.modulus)
            cs, cb = layout.counter_field  # type: ignore[misc]
            mask = np.uint64(((1 << cb) - 1) << cs)
            payload = (payload & ~mask) | (counter.astype(np.uint64) << np.uint64(cs))
        if layout.crc_algorithm is not None:
            k = layout.crc_byte
            b8 = payload.astype("<u8").view(np.uint8).reshape(-1, 8)
            crc = crc_rows(layout.crc_algorithm, np.delete(b8, k, axis=1))
            payload = (payload & ~np.uint64(0xFF << (8 * k))) | (crc.astype(np.uint64) << np.uint64(8 * k))
        return payload
