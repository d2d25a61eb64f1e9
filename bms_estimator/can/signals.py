"""One DBC signal's raw encoding and the NotAvailable rule, once for the project.

* :data:`NOT_AVAILABLE_NAMES`: a raw value whose DBC value-table name matches this means
  "no value" (``NotAvailable``, ``N/A``, ``SNA``, ``Invalid``, ``Error``). The decoder drops
  such values; the encoders send the signal's first such raw value for NaN.
* :class:`SignalCodec`: physical -> raw (rounded to the resolution, clamped to the signal's
  ``[minimum, maximum]``, NaN -> NotAvailable, or the minimum's raw value without one);
  the decoder's raw -> SI is the same scale and offset composed with the mapping's
  conversion (``can/decoder.py``). ``unit_factor`` scales an SI input to the signal's unit first (1000 for a
  signal in mOhm that is handed ohms).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = ["NOT_AVAILABLE_NAMES", "SignalCodec", "not_available_raws"]

#: value-table names that mean "no value" (case-insensitive, whole name)
NOT_AVAILABLE_NAMES = r"(?i)not[ _-]?available|n/?a|sna|invalid|error"


def not_available_raws(sig: Any, pattern: str | re.Pattern[str] = NOT_AVAILABLE_NAMES) -> frozenset[int]:
    """The raw values of ``sig`` (a cantools signal) whose value-table name means "no value"."""
    rx = re.compile(pattern) if isinstance(pattern, str) else pattern
    return frozenset(int(raw) for raw, name in (sig.choices or {}).items() if rx.fullmatch(str(name)))


@dataclass(frozen=True, slots=True)
class SignalCodec:
    name: str
    scale: float
    offset: float
    raw_min: int
    raw_max: int
    na_raw: int
    unit_factor: float = 1.0
    choices_by_name: dict[str, int] | None = None

    @classmethod
    def from_signal(cls, sig: Any, unit_factor: float = 1.0) -> SignalCodec:
        scale, offset = float(sig.scale), float(sig.offset)
        lo = -(1 << (sig.length - 1)) if sig.is_signed else 0
        hi = (1 << (sig.length - 1)) - 1 if sig.is_signed else (1 << sig.length) - 1
        if sig.minimum is not None:
            lo = max(lo, math.ceil((sig.minimum - offset) / scale - 1e-9))
        if sig.maximum is not None:
            hi = min(hi, math.floor((sig.maximum - offset) / scale + 1e-9))
        na = not_available_raws(sig)
        return cls(
            name=sig.name, scale=scale, offset=offset, raw_min=int(lo), raw_max=int(hi),
            na_raw=min(na) if na else int(lo), unit_factor=float(unit_factor),
            choices_by_name={str(n): int(r) for r, n in (sig.choices or {}).items()},
        )

    def raw(self, values: Any) -> np.ndarray:
        """Physical (times ``unit_factor``) -> raw int64, vectorised; never raises, never warns."""
        return self.raw_and_clamped(values)[0]

    def raw_and_clamped(self, values: Any) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`raw`, and where a finite value lay outside the signal's range and was clamped to its end."""
        x = np.asarray(values, dtype=float)
        with np.errstate(all="ignore"):
            r = np.rint((x * self.unit_factor - self.offset) / self.scale)
            nan = np.isnan(r)
            clamped = np.isfinite(x) & ((r < self.raw_min) | (r > self.raw_max))
            r = np.clip(np.where(nan, self.raw_min, r), self.raw_min, self.raw_max)
        return np.asarray(np.where(nan, self.na_raw, r), dtype=np.int64), clamped
