r"""Estimator state -> CAN frames of the project's DBC (``dbc/bms_estimator.dbc``).

Frames (all 8-byte classic CAN, 29-bit identifiers; exact bit layouts and
scalings are in the DBC's ``CM_`` comments):

``CellStateA`` (0x1B5E0100), one per cell
    ``CellIndex`` (mux) | ``Soc`` % | ``R0`` mOhm | ``R1`` mOhm | ``C0`` mV
``CellStateB`` (0x1B5E0101), one per cell, right after its CellStateA
    ``CellIndex`` (mux) | ``C1`` F | ``R2`` mOhm | ``C2`` F
``PackSummary`` (0x1B5E0110) + ``PackElectrical`` (0x1B5E0111)
    min/mean/max SOC and their cells, rolling counter; mean current, pack
    voltage, number of valid cells
``EstimatorStatus`` (0x1B5E0120) + ``EstimatorCounters`` (0x1B5E0121)
    uptime, sample count; error counters and service state
``PackLimits2s/10s/30s`` (0x1B5E0112..14), ``PackEnergy`` (0x1B5E0115), ``PackHealth`` (0x1B5E0116)
    state of power, energy and health (schema.CAN_PACK_SOX_SIGNALS), when the snapshot has them
    and the DBC has the message; SOH fractions are sent in %

Inputs are SI (ohm, F, V, A); the encoder converts to the DBC's units from each
signal's ``unit`` (``mOhm``, ``mV``, ...), so it follows the DBC if a scaling is
changed there. SOC is a fraction 0..1 unless ``soc_unit="percent"``.

Value policy - the encoder never raises for any float input:

* finite values and +-inf are rounded to the signal's resolution and clamped
  to its ``[minimum, maximum]``;
* NaN (and None) -> the signal's ``NotAvailable`` raw value from the DBC's value
  table, or the raw value of ``minimum`` when the signal has none;
* counters saturate at the signal maximum.

A finite value clamped (a cell the DBC's range was not made for: the project DBC's C1 ends at 13106.8 F,
C2 at 131068 F, CapacityMean at 65.534 Ah, R0/R1 step 8 uOhm; a 57 Ah cell's C1 is about 30000 F) is
counted in ``clamped_values`` and logged once per signal (WARNING ``can.encode.clamped``, naming the
signal, the value and the range): before, the frame carried the range's end with nothing to say so.
The remedy is a DBC scaled for the cell (``can.dbc``; units such as ``kF`` and ``uOhm`` are followed).
Not so ``TimeToEmpty``/``TimeToFull`` (:data:`SATURATING_SIGNALS`), whose 4094 min the DBC defines as "not
discharging (charging) or 68 h and more": an idle pack's, sent as meant, neither counted nor logged.

Cells without a usable index (NaN, negative, above the multiplexer's range)
are skipped and counted in ``skipped_cells``.

Speed: the per-cell frames (two per cell, 400 for a 200-cell pack every second) are
packed with numpy over the cells: each signal's raw values are masked to their
length (two's complement for signed ones) and shifted to their bit position in
the frame's little-endian 64-bit word,

.. math:: w_j = \sum_s (r_{s,j} \bmod 2^{L_s}) \cdot 2^{b_s},

with the positions :math:`b_s` taken from the DBC (:class:`_FramePacker`). This gives
the bytes ``cantools`` would (tested); a message with a big-endian signal keeps
``cantools`` frame by frame.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any, Literal

import can
import numpy as np
import structlog
from cantools.database.can import Database, Message

from ..service.schema import CAN_PACK_SOX_SIGNALS, CAN_STATUS_SIGNALS, soc_stats
from .signals import SignalCodec

if TYPE_CHECKING:
    from ..service.pipeline import Snapshot

__all__ = ["StateEncoder"]

log = structlog.get_logger(__name__)

#: (message, signal) whose range end the DBC defines as "that much and more" (PackEnergy: 4094 min = not
#: discharging / charging, or 68 h and more): clamped to it as meant, not counted or logged as a clamp
SATURATING_SIGNALS: frozenset[tuple[str, str]] = frozenset({("PackEnergy", "TimeToEmpty"), ("PackEnergy", "TimeToFull")})

#: factor from the SI value handed to the encoder to the DBC signal's unit
UNIT_FROM_SI: dict[str, float] = {
    "": 1.0,
    "Ohm": 1.0,
    "mOhm": 1e3,
    "uOhm": 1e6,
    "V": 1.0,
    "mV": 1e3,
    "A": 1.0,
    "mA": 1e3,
    "F": 1.0,
    "kF": 1e-3,
    "s": 1.0,
    "%": 1.0,
    "degC": 1.0,
    "W": 1.0,
    "kW": 1e-3,
    "Wh": 1.0,
    "kWh": 1e-3,
    "Ah": 1.0,
    "min": 1.0 / 60.0,
}

def _to_float(v: Any) -> float:
    try:
        return float(v)
    except (TypeError, ValueError, OverflowError):
        return math.nan


def _floats(values: Any) -> np.ndarray:
    """Anything array-like -> float array; elements that are not numbers become NaN."""
    try:
        return np.asarray(math.nan if values is None else values, dtype=float)
    except (TypeError, ValueError, OverflowError):
        try:
            arr = np.asarray(values, dtype=object)
        except Exception:
            return np.asarray(math.nan)
        return np.array([_to_float(v) for v in arr.reshape(-1)], dtype=float).reshape(arr.shape)


class _FramePacker:
    """One message's data bytes for many frames at once, vectorised (see the module docstring).

    ``pack(raws)`` takes raw int64 arrays (one per signal, broadcast against each other)
    and returns an ``(n, length)`` uint8 array; signals not given are 0, as ``cantools``
    encodes them with ``padding=False``. Only for messages of little-endian signals
    within 64 bits (:meth:`for_message` returns None otherwise).
    """

    def __init__(self, length: int, layout: dict[str, tuple[int, int]]) -> None:
        self.length = length
        self.layout = layout  # signal -> (start bit, length)

    @classmethod
    def for_message(cls, msg: Message) -> _FramePacker | None:
        if msg.length > 8 or any(s.byte_order != "little_endian" for s in msg.signals):
            return None
        return cls(msg.length, {s.name: (int(s.start), int(s.length)) for s in msg.signals})

    def pack(self, raws: Mapping[str, np.ndarray], n: int) -> np.ndarray:
        word = np.zeros(n, dtype=np.uint64)
        for name, raw in raws.items():
            start, length = self.layout[name]
            mask = np.uint64((1 << length) - 1)
            bits = np.asarray(raw, dtype=np.int64).astype(np.uint64) & mask  # two's complement for < 0
            word |= bits << np.uint64(start)
        return word.astype("<u8").view(np.uint8).reshape(n, 8)[:, : self.length]


class StateEncoder:
    """Encode estimator outputs into :class:`can.Message` lists.

    ``db`` is the project's DBC (or one with the same message and signal
    names). Construction raises ``KeyError`` if a required message is missing;
    the ``encode_*`` methods never raise.
    """

    CELL_A = "CellStateA"
    CELL_B = "CellStateB"
    SUMMARY = "PackSummary"
    ELECTRICAL = "PackElectrical"
    STATUS = "EstimatorStatus"
    COUNTERS = "EstimatorCounters"

    def __init__(self, db: Database) -> None:
        self.db = db
        self._msgs: dict[str, Message] = {}
        self._codecs: dict[str, dict[str, SignalCodec]] = {}
        for name in (self.CELL_A, self.CELL_B, self.SUMMARY, self.ELECTRICAL, self.STATUS, self.COUNTERS):
            msg = db.get_message_by_name(name)
            self._msgs[name] = msg
            self._codecs[name] = {s.name: self._codec(s) for s in msg.signals}
        self._packers = {name: _FramePacker.for_message(self._msgs[name]) for name in (self.CELL_A, self.CELL_B)}
        unknown = [f"{m}.{sig}" for m in (self.STATUS, self.COUNTERS) for sig in self._codecs[m]
                   if sig not in CAN_STATUS_SIGNALS]
        if unknown:
            raise KeyError(f"status signal(s) {', '.join(unknown)} carry no known counter "
                           f"(known: {', '.join(CAN_STATUS_SIGNALS)})")
        # SOP/SOE/SOH messages: optional (a DBC without them sends none)
        self._sox_msgs = [m for m in CAN_PACK_SOX_SIGNALS if m in {x.name for x in db.messages}]
        for name in self._sox_msgs:
            msg = db.get_message_by_name(name)
            self._msgs[name] = msg
            self._codecs[name] = {s.name: self._codec(s) for s in msg.signals}
            unknown = [sig for sig in self._codecs[name] if sig not in CAN_PACK_SOX_SIGNALS[name]]
            if unknown:
                raise KeyError(f"{name} signal(s) {', '.join(unknown)} carry no known figure "
                               f"(known: {', '.join(CAN_PACK_SOX_SIGNALS[name])})")
        self.skipped_cells = 0
        self.encode_failures = 0
        self.clamped_values = 0  # finite values beyond their signal's range, sent as its end
        self._clamp_logged: set[tuple[str, str]] = set()
        self._summary_counter = 0

    def _raw(self, message: str, codec: SignalCodec, values: Any) -> np.ndarray:
        """``codec.raw(values)``; the values it clamps are counted and logged (once per signal), but for the
        signals whose range end the DBC defines as "that much and more" (:data:`SATURATING_SIGNALS`)."""
        if (message, codec.name) in SATURATING_SIGNALS:
            return codec.raw(values)
        raw, out = codec.raw_and_clamped(values)
        if out.any():
            self.clamped_values += int(np.count_nonzero(out))
            if (message, codec.name) not in self._clamp_logged:
                self._clamp_logged.add((message, codec.name))
                x = np.asarray(values, dtype=float)
                worst = float(np.reshape(x, -1)[int(np.argmax(np.reshape(np.where(out, np.abs(x), -1.0), -1)))])
                sig = self._msgs[message].get_signal_by_name(codec.name)
                lo, hi = (codec.raw_min * codec.scale + codec.offset), (codec.raw_max * codec.scale + codec.offset)
                log.warning("can.encode.clamped: a value beyond its DBC signal's range is sent as the range's end "
                            "(a cell the DBC was not scaled for? can.dbc takes one that is)", message=message,
                            signal=codec.name, value=worst * codec.unit_factor, range=f"{lo:g}..{hi:g}",
                            unit=sig.unit or "")
        return raw

    @staticmethod
    def _codec(sig) -> SignalCodec:
        return SignalCodec.from_signal(sig, UNIT_FROM_SI.get(sig.unit or "", 1.0))

    def _frame(self, name: str, raws: dict[str, int], timestamp: float | None) -> can.Message | None:
        msg = self._msgs[name]
        try:
            data = msg.encode(raws, scaling=False, strict=False, padding=False)
        except Exception:  # pragma: no cover - the raws are in range by construction
            self.encode_failures += 1
            log.exception("can.encode.failed", message=name)
            return None
        return can.Message(
            arbitration_id=msg.frame_id,
            is_extended_id=msg.is_extended_frame,
            data=data,
            is_fd=False,
            timestamp=0.0 if timestamp is None else float(timestamp),
        )

    # ----------------------------------------------------------------- cells
    def encode_cells(
        self,
        cell_index: Any,
        soc: Any,
        r0_ohm: Any,
        r1_ohm: Any,
        c1_f: Any,
        r2_ohm: Any,
        c2_f: Any,
        c0_v: Any,
        *,
        soc_unit: Literal["fraction", "percent"] = "fraction",
        timestamp: float | None = None,
    ) -> list[can.Message]:
        """Two frames per cell (CellStateA, CellStateB), interleaved per cell.

        All value arguments broadcast against ``cell_index`` (scalars allowed).
        """
        try:
            idx = _floats(cell_index).reshape(-1)
            n = idx.size
            soc_scale = 100.0 if soc_unit == "fraction" else 1.0
            cols = {}
            for key, values in (
                ("soc", soc),
                ("r0", r0_ohm),
                ("r1", r1_ohm),
                ("c1", c1_f),
                ("r2", r2_ohm),
                ("c2", c2_f),
                ("c0", c0_v),
            ):
                flt = _floats(values).reshape(-1)
                # a column that does not broadcast against the cells is sent as NotAvailable
                cols[key] = np.broadcast_to(flt, (n,)) if flt.size in (1, n) else np.full(n, math.nan)
            a, b = self._codecs[self.CELL_A], self._codecs[self.CELL_B]
            with np.errstate(all="ignore"):  # huge * 100 -> inf is fine (clamped); never a warning
                cols["soc"] = cols["soc"] * soc_scale
            ca, cb = self.CELL_A, self.CELL_B
            raw_a = {
                "Soc": a["Soc"].raw(cols["soc"]),
                "R0": self._raw(ca, a["R0"], cols["r0"]),
                "R1": self._raw(ca, a["R1"], cols["r1"]),
                "C0": self._raw(ca, a["C0"], cols["c0"]),
            }
            raw_b = {"C1": self._raw(cb, b["C1"], cols["c1"]), "R2": self._raw(cb, b["R2"], cols["r2"]),
                     "C2": self._raw(cb, b["C2"], cols["c2"])}
            mux_max = min(a["CellIndex"].raw_max, b["CellIndex"].raw_max)
            with np.errstate(invalid="ignore"):
                usable = np.isfinite(idx) & (idx == np.floor(idx)) & (idx >= 0) & (idx <= mux_max)
            self.skipped_cells += int(n - np.count_nonzero(usable))
            keep = np.flatnonzero(usable)
            ci = idx[keep].astype(np.int64)
            raw_a = {"CellIndex": ci, **{k: v[keep] for k, v in raw_a.items()}}
            raw_b = {"CellIndex": ci, **{k: v[keep] for k, v in raw_b.items()}}
            if self._packers[self.CELL_A] is None or self._packers[self.CELL_B] is None:
                return self._cells_one_by_one(raw_a, raw_b, keep.size, timestamp)
            data_a = self._packers[self.CELL_A].pack(raw_a, keep.size)
            data_b = self._packers[self.CELL_B].pack(raw_b, keep.size)
        except Exception:  # pragma: no cover - defensive
            self.encode_failures += 1
            log.exception("can.encode_cells.failed")
            return []
        ma, mb = self._msgs[self.CELL_A], self._msgs[self.CELL_B]
        id_a, ext_a, id_b, ext_b = ma.frame_id, ma.is_extended_frame, mb.frame_id, mb.is_extended_frame
        ts = 0.0 if timestamp is None else float(timestamp)
        out: list[can.Message] = []
        for da, db in zip(data_a.tolist(), data_b.tolist()):  # interleaved: A then B of each cell
            out.append(can.Message(arbitration_id=id_a, is_extended_id=ext_a, data=da, is_fd=False, timestamp=ts))
            out.append(can.Message(arbitration_id=id_b, is_extended_id=ext_b, data=db, is_fd=False, timestamp=ts))
        return out

    def _cells_one_by_one(self, raw_a: dict[str, np.ndarray], raw_b: dict[str, np.ndarray], n: int,
                          timestamp: float | None) -> list[can.Message]:
        """``cantools`` frame by frame: a DBC whose cell frames the packer cannot build."""
        lists_a = {k: v.tolist() for k, v in raw_a.items()}
        lists_b = {k: v.tolist() for k, v in raw_b.items()}
        out: list[can.Message] = []
        for j in range(n):
            for name, lists in ((self.CELL_A, lists_a), (self.CELL_B, lists_b)):
                frame = self._frame(name, {k: v[j] for k, v in lists.items()}, timestamp)
                if frame is not None:
                    out.append(frame)
        return out

    # ------------------------------------------------------------------ pack
    def encode_pack_summary(
        self,
        soc: Any,
        current_a: Any = math.nan,
        pack_voltage_v: Any = math.nan,
        *,
        valid: Any = None,
        cell_index: Any = None,
        cells_valid: Any = None,
        soc_unit: Literal["fraction", "percent"] = "fraction",
        timestamp: float | None = None,
    ) -> list[can.Message]:
        """PackSummary + PackElectrical from per-cell SOC.

        Statistics use the cells where ``valid`` (default: all) is true and SOC
        is not NaN; ``cell_index`` (default ``0..N-1``) names the cells.
        ``cells_valid`` defaults to the number of such cells.
        """
        try:
            s = _floats(soc).reshape(-1)
            n = s.size
            use = ~np.isnan(s)
            if valid is not None:
                v = np.asarray(valid).reshape(-1)
                if v.size == n:
                    use &= v.astype(bool)
            idx = np.arange(n, dtype=float)
            if cell_index is not None:
                ci = _floats(cell_index).reshape(-1)
                if ci.size == n:
                    idx = ci
            st = soc_stats(s, use)
            smin, smean, smax = st.soc_min, st.soc_mean, st.soc_max
            if st.n:
                cmin, cmax = idx[st.soc_min_cell], idx[st.soc_max_cell]
            else:
                cmin = cmax = math.nan
            nvalid = int(use.sum()) if cells_valid is None else _to_float(cells_valid)
            if soc_unit == "fraction":
                with np.errstate(all="ignore"):
                    smin, smean, smax = smin * 100.0, smean * 100.0, smax * 100.0
            cs = self._codecs[self.SUMMARY]
            summary = {
                "SocMin": int(cs["SocMin"].raw(smin)),
                "SocMean": int(cs["SocMean"].raw(smean)),
                "SocMax": int(cs["SocMax"].raw(smax)),
                "SocMinCell": int(cs["SocMinCell"].raw(cmin)),
                "SocMaxCell": int(cs["SocMaxCell"].raw(cmax)),
                "SummaryCounter": self._summary_counter,
            }
            self._summary_counter = (self._summary_counter + 1) % (cs["SummaryCounter"].raw_max + 1)
            ce = self._codecs[self.ELECTRICAL]
            electrical = {
                "PackCurrent": int(ce["PackCurrent"].raw(_to_float(current_a))),
                "PackVoltage": int(ce["PackVoltage"].raw(_to_float(pack_voltage_v))),
                "CellsValid": int(ce["CellsValid"].raw(nvalid)),
            }
        except Exception:  # pragma: no cover - defensive
            self.encode_failures += 1
            log.exception("can.encode_pack_summary.failed")
            return []
        return [m for m in (self._frame(self.SUMMARY, summary, timestamp),
                            self._frame(self.ELECTRICAL, electrical, timestamp)) if m is not None]

    # ---------------------------------------------------------------- status
    def status_keys(self) -> list[str]:
        """Keys understood by :meth:`encode_status` (``schema.CAN_STATUS_SIGNALS``)."""
        return [CAN_STATUS_SIGNALS[s] for m in (self.STATUS, self.COUNTERS) for s in self._codecs[m]]

    def encode_status(self, counters: Mapping[str, Any] | Any, *, timestamp: float | None = None) -> list[can.Message]:
        """EstimatorStatus + EstimatorCounters.

        ``counters`` is a mapping or an object (e.g. a dataclass) with the keys
        of :meth:`status_keys`: ``uptime_s, samples, decode_errors, rejections,
        stale_cells, time_jumps, backward_frames, estimator_state`` (the state
        may be a number or a value-table name such as ``"Running"``). Missing
        keys encode as 0 (counters saturate at their maximum).
        """
        def raw(mname: str, sname: str, codec) -> int:
            key = CAN_STATUS_SIGNALS[sname]
            value = counters.get(key, 0) if isinstance(counters, Mapping) else getattr(counters, key, 0)
            if isinstance(value, str) and value in codec.choices_by_name:
                return codec.choices_by_name[value]
            return int(codec.raw(_to_float(value)))

        return self._encode_each((self.STATUS, self.COUNTERS), raw, timestamp, "can.encode_status.failed")

    def _encode_each(self, names, raw, timestamp: float | None, event: str) -> list[can.Message]:
        """One frame per message name, each signal's raw value from ``raw(message, signal, codec)``;
        a message that fails to encode is counted and logged, and the others still go out."""
        out: list[can.Message] = []
        for mname in names:
            try:
                raws = {sname: raw(mname, sname, codec) for sname, codec in self._codecs[mname].items()}
            except Exception:  # pragma: no cover - defensive
                self.encode_failures += 1
                log.exception(event, message=mname)
                continue
            frame = self._frame(mname, raws, timestamp)
            if frame is not None:
                out.append(frame)
        return out

    # ------------------------------------------------------------------- SOX
    def encode_pack_sox(self, values: Mapping[str, Any], *, timestamp: float | None = None) -> list[can.Message]:
        """PackLimits*/PackEnergy/PackHealth from pack figures in SI (A, W, Wh, s, Ah; SOH as a
        fraction, sent in %): the keys of ``schema.CAN_PACK_SOX_SIGNALS``; a missing key is NotAvailable."""
        def raw(name: str, sname: str, codec) -> int:
            value = _to_float(values.get(CAN_PACK_SOX_SIGNALS[name][sname], math.nan))
            if self._msgs[name].get_signal_by_name(sname).unit == "%":
                value *= 100.0
            return int(self._raw(name, codec, value))

        return self._encode_each(self._sox_msgs, raw, timestamp, "can.encode_pack_sox.failed")

    # -------------------------------------------------------------- snapshot
    def encode_snapshot(self, snap: Snapshot) -> list[can.Message]:
        """Every output frame of one :class:`~bms_estimator.service.pipeline.Snapshot`: the
        cells' CellStateA/B, PackSummary + PackElectrical, EstimatorStatus + Counters."""
        c, t = snap.cells, snap.t_s
        frames = self.encode_cells(np.arange(snap.n_cells), c["soc"], c["r0_ohm"], c["r1_ohm"], c["c1_f"],
                                   c["r2_ohm"], c["c2_f"], c["c0_v"], timestamp=t)
        frames += self.encode_pack_summary(c["soc"], snap.current_a, snap.pack_voltage_v,
                                           cells_valid=snap.cells_valid, timestamp=t)
        frames += self.encode_status(snap.counters, timestamp=t)
        if snap.pack_sox:
            frames += self.encode_pack_sox({**snap.pack_sox, "capacity_ah_mean": snap.capacity_ah_mean}, timestamp=t)
        return frames
