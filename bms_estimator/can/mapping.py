"""Which CAN signals carry the estimator's inputs: the input *mapping*.

A mapping is plain configuration (TOML or a dict) validated by the pydantic
models below; the same code then reads any bus whose DBC describes the frames.
Two presets ship as package data (``bms_estimator/can/presets/*.toml``):

``bms_estimator`` (alias ``default``)
    the project's own DBC (``dbc/bms_estimator.dbc``).
``foxbms``
    the foxBMS 2 DBC (``foxbms.dbc`` v1.11.0): IVT-S current ``0x521``,
    IVT-S voltage 1 ``0x522``, ``AFE_CellVoltages`` ``0x270`` and
    ``AFE_CellTemperatures`` ``0x280``.

Unit conversion
---------------
Every channel converts the DBC's *physical* value (``raw * dbc_scale +
dbc_offset``, as cantools defines it) to SI units with::

    si = sign * scale * physical + offset

e.g. foxBMS currents are in mA with positive = discharge, so the preset has
``scale = 0.001, sign = -1`` (the estimator's convention: A, positive =
CHARGE). After conversion the value must lie in ``[valid_min, valid_max]``
(SI units) or it is dropped and counted.

Scalar channels (current, pack voltage)
---------------------------------------
``message`` + ``signal``; optional ``mux`` (only frames whose multiplexer has
that value) and ``invalid_if_nonzero`` (flag signals of the same frame: a
non-zero flag drops the value, counted as ``flagged_invalid``).

Per-cell channels (cell voltages, cell temperatures)
----------------------------------------------------
A list of signal groups, each naming a ``message`` and how its signals map
to 0-based cell indices. Two forms:

1. a rule: ``signal_pattern`` is a regular expression matched (``fullmatch``)
   against every signal name of the message; it must have a named group

   * ``cell`` - the cell index is in the signal name:
     ``cell = int(cell) + index_offset`` (foxBMS: ``CellVoltage_(?P<cell>\\d+)``), or
   * ``slot`` - the position in the frame:
     ``cell = mux * mux_stride + int(slot) + index_offset`` where ``mux`` is the
     frame's multiplexer value (our DBC: ``CellVoltage(?P<slot>\\d+)`` with
     ``mux_stride = 1`` because its multiplexer *is* the first cell's index; a
     DBC whose multiplexer counts 4-cell groups would use ``mux_stride = 4``).

2. an explicit ``table``: ``[{mux = 0, signals = {V_a = 0, V_b = 1}}, {mux = 1, ...}]``
   (``mux`` omitted for a non-multiplexed message).

The rule is expanded against the DBC once, when the decoder is built, into a
lookup ``mux value -> [(signal, cell index), ...]``; nothing is parsed per frame.
``invalid_flag`` is an optional template for a per-cell flag signal
(``"{signal}_invalidFlag"``; the regex groups are also available) and
``invalid_flag_value`` the flag value that means *invalid* (foxBMS: 1 - its
firmware treats a set bit as invalid even though the DBC's value table says
``0 "Invalid" 1 "Valid"``).

End-to-end checks (optional)
----------------------------
``[e2e.<message>]`` names, for an input message, an alive counter signal
(``counter``) and/or a CRC or checksum signal (``crc``, 8 bit, byte aligned,
with ``crc_algorithm``: ``crc8_sae_j1850`` (default), ``crc8_autosar``,
``xor8``, ``sum8``). A frame whose counter skips or repeats a value, or whose
CRC does not match, is dropped and counted (``e2e_counter``, ``e2e_crc``); see
:mod:`bms_estimator.can.e2e`. The ``bms_estimator`` preset checks the project DBC's
alive counters (every input frame) and PackMeasurement's CRC-8 by default. foxBMS: the
IVT-S current and voltage frames carry a 4-bit message counter (``IVT_MsgCount_Result_*``)
and no CRC; its preset checks those counters.

Not-available raw values
------------------------
A raw value whose DBC value-table name matches ``na_choice_pattern``
(default: NotAvailable / N/A / SNA / Invalid / Error) is dropped and counted
as ``not_available``.
"""

from __future__ import annotations

import re
import tomllib
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from ..errors import MappingError
from .signals import NOT_AVAILABLE_NAMES

__all__ = [
    "CanMapping",
    "CellSignals",
    "CellTemperatureSignals",
    "CellVoltageSignals",
    "CurrentSignal",
    "E2ECheck",
    "MappingError",
    "MuxTableEntry",
    "PackVoltageSignal",
    "ScalarSignal",
    "load_mapping",
    "mapping_to_dict",
    "preset_names",
    "preset_path",
]

PRESET_ALIASES: dict[str, str] = {"default": "bms_estimator"}
DEFAULT_NA_CHOICE_PATTERN = NOT_AVAILABLE_NAMES


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", validate_default=True)


class _Conversion(_Model):
    scale: float = Field(1.0, description="multiplies the DBC physical value")
    sign: Literal[1, -1] = Field(1, description="-1 flips the direction (e.g. discharge-positive sensors)")
    offset: float = Field(0.0, description="added after scale and sign, in SI units")
    valid_min: float = -float("inf")
    valid_max: float = float("inf")

    @field_validator("scale")
    @classmethod
    def _finite_nonzero(cls, v: float) -> float:
        if not (v == v) or v in (float("inf"), -float("inf")) or v == 0.0:
            raise ValueError("must be finite and non-zero")
        return v

    @model_validator(mode="after")
    def _range_order(self) -> _Conversion:
        if not self.valid_min < self.valid_max:
            raise ValueError("valid_min must be < valid_max")
        return self


class ScalarSignal(_Conversion):
    """One value per frame (pack current, pack voltage)."""

    message: str = Field(min_length=1)
    signal: str = Field(min_length=1)
    mux: int | None = Field(None, description="required multiplexer value; None = any")
    invalid_if_nonzero: list[str] = Field(default_factory=list)


class CurrentSignal(ScalarSignal):
    """Pack current in A, positive = charge."""

    valid_min: float = -5000.0
    valid_max: float = 5000.0


class PackVoltageSignal(ScalarSignal):
    """Pack (string) voltage in V."""

    valid_min: float = 0.0
    valid_max: float = 2000.0


class MuxTableEntry(_Model):
    mux: int | None = Field(None, description="multiplexer value; None for a non-multiplexed message")
    signals: dict[str, int] = Field(min_length=1, description="signal name -> 0-based cell index")

    @field_validator("signals")
    @classmethod
    def _non_negative(cls, v: dict[str, int]) -> dict[str, int]:
        bad = [k for k, i in v.items() if i < 0]
        if bad:
            raise ValueError(f"negative cell index for {bad}")
        return v


class CellSignals(_Conversion):
    """A group of per-cell signals in one message (see the module docstring)."""

    message: str = Field(min_length=1)
    signal_pattern: str | None = None
    mux_stride: int = Field(0, ge=0)
    index_offset: int = 0
    table: list[MuxTableEntry] | None = None
    invalid_flag: str | None = Field(None, description='flag signal template, e.g. "{signal}_invalidFlag"')
    invalid_flag_value: int = 1

    @field_validator("signal_pattern")
    @classmethod
    def _pattern(cls, v: str | None) -> str | None:
        if v is None:
            return v
        try:
            rx = re.compile(v)
        except re.error as exc:
            raise ValueError(f"not a regular expression: {exc}") from None
        groups = set(rx.groupindex)
        if not ({"cell", "slot"} & groups) or {"cell", "slot"} <= groups:
            raise ValueError("needs exactly one of the named groups (?P<cell>...) or (?P<slot>...)")
        return v

    @model_validator(mode="after")
    def _one_form(self) -> CellSignals:
        if (self.signal_pattern is None) == (self.table is None):
            raise ValueError("give exactly one of signal_pattern or table")
        return self


class CellVoltageSignals(CellSignals):
    """Cell voltages in V."""

    valid_min: float = 0.5
    valid_max: float = 5.5


class CellTemperatureSignals(CellSignals):
    """Cell temperatures in degC (sensor i is taken as cell i)."""

    valid_min: float = -60.0
    valid_max: float = 150.0


class E2ECheck(_Model):
    """End-to-end checks of one input message (see the module docstring)."""

    counter: str | None = Field(None, min_length=1, description="alive counter signal, +1 per frame")
    crc: str | None = Field(None, min_length=1, description="CRC/checksum signal: 8 bit, byte aligned")
    crc_algorithm: Literal["crc8_sae_j1850", "crc8_autosar", "xor8", "sum8"] = "crc8_sae_j1850"

    @model_validator(mode="after")
    def _something(self) -> E2ECheck:
        if self.counter is None and self.crc is None:
            raise ValueError("name a counter, a crc, or both")
        return self


class CanMapping(_Model):
    """The complete input mapping for one DBC."""

    description: str = ""
    cell_cycle_s: float | None = Field(
        None, gt=0, description="nominal refresh period of every cell value; staleness_s should exceed it"
    )
    na_choice_pattern: str = DEFAULT_NA_CHOICE_PATTERN
    current: CurrentSignal
    pack_voltage: PackVoltageSignal | None = None
    cell_voltages: list[CellVoltageSignals] = Field(min_length=1)
    cell_temperatures: list[CellTemperatureSignals] = Field(default_factory=list)
    e2e: dict[str, E2ECheck] = Field(default_factory=dict, description="message name -> its end-to-end checks")

    @field_validator("na_choice_pattern")
    @classmethod
    def _rx(cls, v: str) -> str:
        try:
            re.compile(v)
        except re.error as exc:
            raise ValueError(f"not a regular expression: {exc}") from None
        return v


# ----------------------------------------------------------------------- loading
def _presets_dir() -> Path:
    return Path(__file__).resolve().parent / "presets"


def preset_names() -> list[str]:
    """Names of the shipped presets (without aliases)."""
    return sorted(p.stem for p in _presets_dir().glob("*.toml"))


def preset_path(name: str) -> Path:
    """Path of a shipped preset by name or alias (``default``)."""
    real = PRESET_ALIASES.get(name, name)
    path = _presets_dir() / f"{real}.toml"
    if not path.is_file():
        raise MappingError(f"unknown mapping preset {name!r}; presets: {', '.join(preset_names())}, aliases: default")
    return path


def _validate(data: Mapping[str, Any], origin: str) -> CanMapping:
    try:
        return CanMapping.model_validate(dict(data))
    except ValidationError as exc:
        lines = [f"{'.'.join(str(p) for p in err['loc']) or '<root>'}: {err['msg']}" for err in exc.errors()]
        raise MappingError(f"invalid CAN mapping ({origin}):", lines) from None


def load_mapping(source: str | Path | Mapping[str, Any] | CanMapping) -> CanMapping:
    """Load a mapping from a preset name, a TOML file, a dict or a model.

    Raises :class:`MappingError` with one line per problem.
    """
    if isinstance(source, CanMapping):
        return source
    if isinstance(source, Mapping):
        return _validate(source, "inline table")
    text_source = str(source)
    if isinstance(source, str) and (source in PRESET_ALIASES or (_presets_dir() / f"{source}.toml").is_file()):
        path = preset_path(source)
    else:
        path = Path(text_source)
        if not path.is_file():
            raise MappingError(
                f"mapping {text_source!r} is neither a preset ({', '.join(preset_names())}, default) nor a file"
            )
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except (OSError, tomllib.TOMLDecodeError) as exc:
        raise MappingError(f"cannot read mapping {path}: {exc}") from None
    return _validate(data, str(path))


def mapping_to_dict(mapping: CanMapping) -> dict[str, Any]:
    """A TOML-able dict (no ``None`` values, infinities dropped) that loads back to the same mapping."""

    def clean(obj: Any) -> Any:
        if isinstance(obj, dict):
            return {k: clean(v) for k, v in obj.items() if v is not None and v not in (float("inf"), -float("inf"))}
        if isinstance(obj, list):
            return [clean(v) for v in obj]
        return obj

    return clean(mapping.model_dump(mode="python", exclude_none=True))
