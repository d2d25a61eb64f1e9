"""CAN frame -> input events, driven by a DBC and an input mapping.

:class:`FrameDecoder` turns one received :class:`can.Message` into a list of
:class:`Event` (pack current, pack voltage, cell voltage, cell temperature),
all in SI units (A with positive = charge, V, degC). It never raises: every
frame that cannot be used is counted in :class:`DecodeCounters` and yields
``[]``.

Speed: the mapping is expanded against the DBC once, at construction, into a
per-frame-id plan ``{mux value: [(signal, cell, a, b, limits, ...)]}`` with
the whole unit conversion folded into ``si = a * raw + b``. Per frame there is
one dict lookup, the raw values of the frame's signals and a short loop over
the mapped signals.

Raw values: when every signal a message's plan reads (mapped values, their
flags, the multiplexer) is an integer, they are taken straight from the payload
as bit fields, ``x = int.from_bytes(data, "little")`` (or ``"big"`` for
big-endian signals), ``u = (x >> shift) & (2^length - 1)`` (:func:`_bit_field`)
and, for a signed signal with sign bit ``h = 2^(length-1)``,
``raw = u - 2 (u & h)``; only the signals present with the
frame's multiplexer value are read, and a multiplexer value the DBC does not
define is ``bad_mux``, as cantools has it. That is what cantools'
``Message.decode(..., decode_choices=False, scaling=False)`` returns (tested on
random payloads of both shipped layouts) at about a third of its cost, and the
per-frame decode was the service's largest cost. Other messages (float signals,
nested multiplexing) are decoded by cantools.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field, fields
from enum import IntEnum
from collections.abc import Callable
from typing import NamedTuple

import can
import structlog
from cantools.database.can import Database, Message

from .e2e import CRC_ALGORITHMS, E2E_RESYNC_S, e2e_layout
from .mapping import CanMapping, CellSignals, E2ECheck, MappingError, ScalarSignal, load_mapping
from .signals import not_available_raws

__all__ = ["DecodeCounters", "Event", "EventKind", "FrameDecoder", "MappedSignal"]

log = structlog.get_logger(__name__)


class EventKind(IntEnum):
    CURRENT = 0  # A, positive = charge; cell = -1
    PACK_VOLTAGE = 1  # V; cell = -1
    CELL_VOLTAGE = 2  # V
    CELL_TEMPERATURE = 3  # degC


class Event(NamedTuple):
    kind: EventKind
    cell: int  # 0-based cell index; -1 for pack-level values
    value: float  # SI units


class MappedSignal(NamedTuple):
    """One DBC signal the decoder uses (see :meth:`FrameDecoder.layout`)."""

    message: str
    mux: int | None  # multiplexer value the signal is sent with (None = any / not multiplexed)
    kind: EventKind
    cell: int  # -1 for pack-level values
    signal: str
    a: float  # si = a * raw + b
    b: float


@dataclass
class DecodeCounters:
    """What :meth:`FrameDecoder.decode` saw. All counts since construction."""

    frames: int = 0  # frames passed to decode()
    decoded: int = 0  # frames of a mapped message that decoded
    events: int = 0  # events returned
    unknown_id: int = 0  # identifier not in the DBC (ignored)
    unmapped: int = 0  # in the DBC but nothing mapped (other messages, unmapped mux values)
    ignored: int = 0  # error frames and remote frames
    short_frame: int = 0  # fewer data bytes than the DBC length
    bad_mux: int = 0  # multiplexer value the DBC does not define
    decode_error: int = 0  # any other cantools decode failure
    non_finite: int = 0  # NaN/inf value (float signals)
    out_of_range: int = 0  # outside the mapping's [valid_min, valid_max]
    not_available: int = 0  # raw value named NotAvailable (or similar) in the DBC
    flagged_invalid: int = 0  # an invalid flag of the frame was set
    e2e_counter: int = 0  # frames dropped: the alive counter skipped or repeated a value
    e2e_crc: int = 0  # frames dropped: CRC/checksum mismatch
    internal_error: int = 0  # a bug; logged

    @property
    def errors(self) -> int:
        """Frames and values that were dropped because they were bad (not merely unused)."""
        return (
            self.short_frame
            + self.bad_mux
            + self.decode_error
            + self.non_finite
            + self.out_of_range
            + self.not_available
            + self.flagged_invalid
            + self.e2e_counter
            + self.e2e_crc
            + self.internal_error
        )

    def as_dict(self) -> dict[str, int]:
        d = {f.name: getattr(self, f.name) for f in fields(self)}
        d["errors"] = self.errors
        return d


# One mapped signal: (kind, cell, signal, a, b, lo, hi, na_raws, flags)
# flags: tuple of (flag_signal, invalid_value or None = "any non-zero")
_Entry = tuple[EventKind, int, str, float, float, float, float, frozenset, tuple]


@dataclass(slots=True)
class _E2EPlan:
    counter: str | None  # alive counter signal
    modulus: int  # counter values 0 .. modulus - 1
    crc: str | None  # CRC signal
    crc_byte: int  # its byte in the frame
    crc_fn: Callable[[bytes], int] | None
    crc_algorithm: str | None  # its name (the fleet's bulk decode computes it on arrays)
    last: dict = field(default_factory=dict)  # multiplexer value (None) -> (last counter value seen, its frame time)


@dataclass(slots=True)
class _MessagePlan:
    message: Message
    length: int
    mux_signal: str | None
    common: list  # entries valid for every multiplexer value
    by_mux: dict  # mux value -> entries (multiplexed messages only)
    e2e: _E2EPlan | None = None
    # bit-field fast path (module docstring), None = cantools: mux value (None when not
    # multiplexed) -> ((signal, start, mask, sign bit or 0), ...) of the signals read with it
    fields: dict | None = None
    mux_field: tuple | None = None  # (big-endian, shift, mask, sign bit or 0) of the multiplexer
    big_endian: bool = False  # some field is read from the big-endian integer


def _bit_field(sig, length_bytes: int) -> tuple[bool, int, int, int] | None:
    """``(big-endian, shift, mask, sign bit or 0)`` of an integer signal, else None.

    Little endian: the payload read as a little-endian integer, shifted by the signal's start
    (its least significant bit). Big endian: read as a big-endian integer; cantools' start is
    the most significant bit in the DBC's sawtooth numbering, at ``p = 8 (s // 8) + 7 - s % 8``
    counted from the first byte's top bit, so the shift is ``8 n - p - length``."""
    if sig.is_float or sig.length < 1:
        return None
    n, start = int(sig.length), int(sig.start)
    sign = (1 << (n - 1)) if sig.is_signed else 0
    if sig.byte_order == "little_endian":
        shift, big = start, False
    elif sig.byte_order == "big_endian":
        shift, big = 8 * length_bytes - (8 * (start // 8) + 7 - start % 8) - n, True
    else:
        return None
    if shift < 0 or shift + n > 8 * length_bytes:
        return None
    return big, shift, (1 << n) - 1, sign


def _compile_fields(plan: _MessagePlan) -> None:
    """Set ``plan.fields``/``plan.mux_field`` when the plan can be read as bit fields."""
    msg = plan.message
    sigs = {s.name: s for s in msg.signals}

    def used(entries: list) -> set[str]:
        return {e[2] for e in entries} | {f for e in entries for f, _ in e[8]}

    plan.fields, plan.mux_field, plan.big_endian = None, None, False  # cantools unless all fields pack
    # the alive counter an E2E check reads is read with every frame of the message
    e2e = {plan.e2e.counter} if plan.e2e is not None and plan.e2e.counter is not None else set()
    names = used(plan.common) | e2e | {n for entries in plan.by_mux.values() for n in used(entries)}
    if plan.mux_signal is not None:
        names.add(plan.mux_signal)
    packed = {}
    for name in names:
        sig = sigs.get(name)
        field = _bit_field(sig, plan.length) if sig is not None else None
        if field is None:
            return
        if sig.multiplexer_ids and sig.multiplexer_signal != plan.mux_signal:
            return  # nested multiplexing: cantools
        packed[name] = field
    plan.big_endian = any(f[0] for f in packed.values())
    if plan.mux_signal is None:
        plan.fields = {None: tuple((n, *packed[n]) for n in sorted(names))}
        return
    if sum(1 for s in msg.signals if s.is_multiplexer) != 1:
        return
    mux_ids = {m for s in msg.signals if s.multiplexer_signal == plan.mux_signal for m in (s.multiplexer_ids or ())}

    def present(name: str, mux: int) -> bool:
        ids = sigs[name].multiplexer_ids
        return not ids or mux in ids

    common = used(plan.common) | e2e
    fields = {}
    for mux in mux_ids:
        want = common | used(plan.by_mux.get(mux, []))
        fields[mux] = tuple((n, *packed[n]) for n in sorted(want) if n != plan.mux_signal and present(n, mux))
    plan.fields = fields
    plan.mux_field = packed[plan.mux_signal]


def _key(frame_id: int, extended: bool) -> int:
    return frame_id | (0x8000_0000 if extended else 0)


class FrameDecoder:
    """Decode frames of ``db`` according to ``mapping`` for a pack of ``n_cells``.

    ``mapping`` may be a :class:`CanMapping`, a preset name, a TOML path or a
    dict. Signals mapped to a cell index ``>= n_cells`` are left out (logged
    once). Raises :class:`MappingError` if the mapping does not fit the DBC.
    ``bit_fields=False`` decodes every frame with cantools (module docstring).
    """

    def __init__(self, db: Database, mapping: CanMapping | str | dict, n_cells: int, *,
                 bit_fields: bool = True) -> None:
        if n_cells < 1:
            raise ValueError("n_cells must be >= 1")
        self.db = db
        self.mapping = load_mapping(mapping)
        self.n_cells = int(n_cells)
        self.counters = DecodeCounters()
        self._known = {_key(m.frame_id, m.is_extended_frame) for m in db.messages}
        self._na_rx = re.compile(self.mapping.na_choice_pattern)
        self._plans: dict[int, _MessagePlan] = {}
        self.voltage_cells: set[int] = set()
        self.temperature_cells: set[int] = set()
        problems: list[str] = []
        self._build(problems)
        if problems:  # a message several signals use is missing once, not once per signal
            raise MappingError("CAN mapping does not fit the DBC:", list(dict.fromkeys(problems)))
        if bit_fields:
            for plan in self._plans.values():
                _compile_fields(plan)
        missing = self.n_cells - len(self.voltage_cells)
        if missing:
            log.warning(
                "can.mapping.cells_without_voltage",
                n_cells=self.n_cells,
                missing=missing,
                first_missing=min(set(range(self.n_cells)) - self.voltage_cells),
            )

    # ------------------------------------------------------------------ plan
    def _message(self, name: str, problems: list[str]) -> Message | None:
        try:
            return self.db.get_message_by_name(name)
        except KeyError:
            problems.append(f"message {name!r} not in the DBC")
            return None

    def _plan_for(self, msg: Message) -> _MessagePlan:
        key = _key(msg.frame_id, msg.is_extended_frame)
        plan = self._plans.get(key)
        if plan is None:
            muxes = [s for s in msg.signals if s.is_multiplexer]
            plan = _MessagePlan(msg, msg.length, muxes[0].name if muxes else None, [], {})
            self._plans[key] = plan
        return plan

    def _na_raws(self, sig) -> frozenset:
        return not_available_raws(sig, self._na_rx)

    def _conversion(self, sig, conv) -> tuple[float, float]:
        # si = sign*scale*(raw*dbc_scale + dbc_offset) + offset = a*raw + b
        k = conv.sign * conv.scale
        return k * float(sig.scale), k * float(sig.offset) + conv.offset

    def _build(self, problems: list[str]) -> None:
        m = self.mapping
        scalars: list[tuple[EventKind, ScalarSignal]] = [(EventKind.CURRENT, m.current)]
        if m.pack_voltage is not None:
            scalars.append((EventKind.PACK_VOLTAGE, m.pack_voltage))
        for kind, spec in scalars:
            self._build_scalar(kind, spec, problems)
        for spec in m.cell_voltages:
            self._build_cells(EventKind.CELL_VOLTAGE, spec, problems, self.voltage_cells)
        for spec in m.cell_temperatures:
            self._build_cells(EventKind.CELL_TEMPERATURE, spec, problems, self.temperature_cells)
        for name, check in m.e2e.items():
            self._build_e2e(name, check, problems)

    def _build_e2e(self, name: str, check: E2ECheck, problems: list[str]) -> None:
        msg = self._message(name, problems)
        if msg is None:
            return
        plan = self._plans.get(_key(msg.frame_id, msg.is_extended_frame))
        if plan is None:
            problems.append(f"e2e.{name}: not an input message of this mapping")
            return
        layout, bad = e2e_layout(msg, check)
        if layout is None:
            problems.extend(bad)
            return
        plan.e2e = _E2EPlan(layout.counter, layout.modulus, layout.crc, layout.crc_byte,
                            CRC_ALGORITHMS[layout.crc_algorithm] if layout.crc_algorithm else None,
                            layout.crc_algorithm)

    def _build_scalar(self, kind: EventKind, spec: ScalarSignal, problems: list[str]) -> None:
        msg = self._message(spec.message, problems)
        if msg is None:
            return
        names = {s.name: s for s in msg.signals}
        sig = names.get(spec.signal)
        if sig is None:
            problems.append(f"{kind.name.lower()}: signal {spec.signal!r} not in message {msg.name}")
            return
        for flag in spec.invalid_if_nonzero:
            if flag not in names:
                problems.append(f"{kind.name.lower()}: flag {flag!r} not in message {msg.name}")
        plan = self._plan_for(msg)
        a, b = self._conversion(sig, spec)
        flags = tuple((f, None) for f in spec.invalid_if_nonzero)
        entry = (kind, -1, sig.name, a, b, spec.valid_min, spec.valid_max, self._na_raws(sig), flags)
        if spec.mux is None:
            plan.common.append(entry)
        elif plan.mux_signal is None:
            problems.append(f"{kind.name.lower()}: mux given but {msg.name} is not multiplexed")
        else:
            plan.by_mux.setdefault(spec.mux, []).append(entry)

    def _build_cells(self, kind: EventKind, spec: CellSignals, problems: list[str], covered: set[int]) -> None:
        what = f"{kind.name.lower()} {spec.message}"
        msg = self._message(spec.message, problems)
        if msg is None:
            return
        plan = self._plan_for(msg)
        names = {s.name: s for s in msg.signals}
        # (mux or None, signal, cell, groups)
        triples: list[tuple[int | None, str, int, dict]] = []
        if spec.table is not None:
            for row in spec.table:
                for sname, cell in row.signals.items():
                    sig = names.get(sname)
                    if sig is None:
                        problems.append(f"{what}: signal {sname!r} not in the message")
                        continue
                    if row.mux is not None and plan.mux_signal is None:
                        problems.append(f"{what}: mux {row.mux} given but the message is not multiplexed")
                        continue
                    if row.mux is None and sig.multiplexer_ids:
                        problems.append(f"{what}: signal {sname!r} is multiplexed; give mux")
                        continue
                    if row.mux is not None and sig.multiplexer_ids and row.mux not in sig.multiplexer_ids:
                        problems.append(f"{what}: signal {sname!r} is not sent with mux {row.mux}")
                        continue
                    triples.append((row.mux, sname, cell + spec.index_offset, {}))
        else:
            rx = re.compile(spec.signal_pattern or "")
            by_slot = "slot" in rx.groupindex
            for sig in msg.signals:
                if sig.is_multiplexer:
                    continue
                mt = rx.fullmatch(sig.name)
                if mt is None:
                    continue
                groups = mt.groupdict()
                try:
                    number = int(groups["slot" if by_slot else "cell"])
                except (TypeError, ValueError):
                    problems.append(f"{what}: pattern group of {sig.name!r} is not an integer")
                    continue
                muxes = list(sig.multiplexer_ids or [None])
                if by_slot and muxes != [None] and spec.mux_stride == 0:
                    problems.append(f"{what}: slot rule on a multiplexed message needs mux_stride >= 1")
                    return
                for mux in muxes:
                    if by_slot:
                        cell = (mux or 0) * spec.mux_stride + number + spec.index_offset
                    else:
                        cell = number + spec.index_offset
                    triples.append((mux, sig.name, cell, groups))
            if not triples:
                problems.append(f"{what}: signal_pattern {spec.signal_pattern!r} matches no signal")
                return
        dropped = 0
        for mux, sname, cell, groups in triples:
            if cell < 0 or cell >= self.n_cells:
                dropped += 1
                continue
            sig = names[sname]
            flags: tuple = ()
            if spec.invalid_flag is not None:
                try:
                    flag_name = spec.invalid_flag.format(signal=sname, **groups)
                except (KeyError, IndexError, ValueError) as exc:
                    problems.append(f"{what}: invalid_flag template {spec.invalid_flag!r}: {exc}")
                    return
                if flag_name not in names:
                    problems.append(f"{what}: flag signal {flag_name!r} not in the message")
                    continue
                flags = ((flag_name, spec.invalid_flag_value),)
            a, b = self._conversion(sig, spec)
            entry = (kind, cell, sname, a, b, spec.valid_min, spec.valid_max, self._na_raws(sig), flags)
            if mux is None:
                plan.common.append(entry)
            else:
                plan.by_mux.setdefault(mux, []).append(entry)
            covered.add(cell)
        if dropped:
            log.info("can.mapping.cells_beyond_pack", group=what, n_cells=self.n_cells, signals_left_out=dropped)

    def _e2e_ok(self, plan: _MessagePlan, e2e: _E2EPlan, data: bytes, raw: dict, t: float) -> bool:
        """The frame's CRC and alive counter (see :mod:`bms_estimator.can.e2e`: a frame more than
        ``E2E_RESYNC_S`` after the previous one of its group starts afresh); counts a failure."""
        if e2e.crc_fn is not None:
            k = e2e.crc_byte
            if e2e.crc_fn(data[:k] + data[k + 1:]) != data[k]:
                self.counters.e2e_crc += 1
                return False
        if e2e.counter is not None:
            value = raw.get(e2e.counter)
            mux = raw.get(plan.mux_signal) if plan.mux_signal is not None else None
            last = e2e.last.get(mux)  # per multiplexer value of this frame id
            e2e.last[mux] = (value, t)
            if last is not None and not t - last[1] > E2E_RESYNC_S and value != (last[0] + 1) % e2e.modulus:
                self.counters.e2e_counter += 1
                return False
        return True

    def layout(self) -> list[MappedSignal]:
        """Every mapped signal with its frame, multiplexer value, cell and raw->SI conversion."""
        out: list[MappedSignal] = []
        for plan in self._plans.values():
            groups = [(None, plan.common)] + sorted(plan.by_mux.items(), key=lambda kv: kv[0])
            for mux, entries in groups:
                for kind, cell, sname, a, b, *_ in entries:
                    out.append(MappedSignal(plan.message.name, mux, kind, cell, sname, a, b))
        return out

    def can_filters(self) -> list[dict[str, int | bool]]:
        """python-can ``can_filters`` passing exactly the frames of the mapped messages (one exact
        match per id). On socketcan the kernel applies them, so the rest of a busy vehicle bus is
        never decoded in Python."""
        out: list[dict[str, int | bool]] = []
        for plan in self._plans.values():
            m = plan.message
            ext = bool(m.is_extended_frame)
            out.append({"can_id": int(m.frame_id), "can_mask": 0x1FFFFFFF if ext else 0x7FF, "extended": ext})
        return sorted(out, key=lambda f: (bool(f["extended"]), int(f["can_id"])))

    # ---------------------------------------------------------------- decode
    def decode(self, msg: can.Message) -> list[Event]:
        """Events carried by ``msg`` (possibly ``[]``). Never raises."""
        c = self.counters
        c.frames += 1
        try:
            plan = self._plans.get(msg.arbitration_id | (0x8000_0000 if msg.is_extended_id else 0))
            if plan is None:
                if _key(msg.arbitration_id, msg.is_extended_id) in self._known:
                    c.unmapped += 1
                else:
                    c.unknown_id += 1
                return []
            if msg.is_error_frame or msg.is_remote_frame:
                c.ignored += 1
                return []
            data = msg.data
            if data is None or len(data) < plan.length:
                c.short_frame += 1
                return []
            fields = plan.fields
            if fields is not None:
                payload = data[: plan.length]
                x = int.from_bytes(payload, "little")
                y = int.from_bytes(payload, "big") if plan.big_endian else 0
                if plan.mux_field is None:
                    mux, read = None, fields[None]
                else:
                    big, shift, mask, sign = plan.mux_field
                    mux = ((y if big else x) >> shift) & mask
                    mux -= (mux & sign) << 1
                    read = fields.get(mux)
                    if read is None:  # a multiplexer value the DBC does not define
                        c.bad_mux += 1
                        return []
                raw = {}
                for name, big, shift, mask, sign in read:
                    u = ((y if big else x) >> shift) & mask
                    raw[name] = u - ((u & sign) << 1)
                if mux is not None:
                    raw[plan.mux_signal] = mux
            else:
                try:
                    raw = plan.message.decode(bytes(data[: plan.length]), decode_choices=False, scaling=False)
                except Exception as exc:  # cantools DecodeError and friends
                    if plan.mux_signal is not None and "multiplexer" in str(exc):
                        c.bad_mux += 1
                    else:
                        c.decode_error += 1
                    return []
            e2e = plan.e2e
            if e2e is not None and not self._e2e_ok(plan, e2e, bytes(data[: plan.length]), raw, msg.timestamp):
                return []
            c.decoded += 1
            entries = plan.common
            if plan.mux_signal is not None:
                muxed = plan.by_mux.get(raw.get(plan.mux_signal))
                if muxed is not None:
                    entries = entries + muxed if entries else muxed
            if not entries:
                c.unmapped += 1
                return []
            out: list[Event] = []
            isfinite = math.isfinite
            new_tuple = tuple.__new__
            for kind, cell, sname, a, b, lo, hi, na_raws, flags in entries:
                value = raw.get(sname)
                if value is None:
                    continue
                if flags:
                    bad = False
                    for fname, fval in flags:
                        f = raw.get(fname, 0)
                        if (f != 0) if fval is None else (f == fval):
                            bad = True
                            break
                    if bad:
                        c.flagged_invalid += 1
                        continue
                if na_raws and value in na_raws:
                    c.not_available += 1
                    continue
                si = a * value + b
                if not isfinite(si):
                    c.non_finite += 1
                    continue
                if si < lo or si > hi:
                    c.out_of_range += 1
                    continue
                out.append(new_tuple(Event, (kind, cell, si)))  # Event(...) without its Python-level __new__
            c.events += len(out)
            return out
        except Exception:  # pragma: no cover - defensive: decode must never raise
            c.internal_error += 1
            log.exception("can.decode.internal_error", arbitration_id=getattr(msg, "arbitration_id", None))
            return []
