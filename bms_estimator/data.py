"""Measured cell recordings: the I/O edge (the only module that reads recording CSVs).

File layout (``<cell>/<ambient>/<test>.csv[.gz]`` in the shared data set)::

    time_s,current_a,voltage_v,temperature_c[,chamber_temperature_c]
    0.000,0.00000,4.18398,25.866,25.00
    ...

A header row is required; ``time_s``, ``current_a`` and ``voltage_v`` must be
present (once each: names are case-sensitive), ``temperature_c`` is optional, any
other column is ignored.  Current is positive for charge.  Values are comma-separated,
RFC 4180 quoting allowed (``"0.000000","-0.08877",...``); ``#`` starts a comment.
Every data row has as many fields as the header.

Loading (:func:`load_recording`)
--------------------------------
1. Parse with ``np.loadtxt`` (vectorised C parser).  Only when that fails is the
   file scanned line by line, so that the :class:`DataError` can name the line
   and the column that is wrong.  A file with columns the loader does not use
   has its rows' field counts checked after it (loadtxt reads only the used
   columns of a row); with every column used, loadtxt checks them itself.
2. Validate: every used value finite, at least 2 rows, time never decreasing
   (``t[k] < t[k-1]`` is an error naming line ``k``), the voltage a single cell's
   (within ``CELL_VOLTAGE_RANGE_V``: a column in mV, or a pack's voltage, is an
   error naming the line), the temperature, where given, a cell's (within
   ``CELL_TEMPERATURE_RANGE_C``: a column in kelvin, say, is an error naming the
   line), and the current positive for charge (below).
   An empty or ``nan`` temperature (a sensor that dropped out for some rows) is
   read as not logged there: linearly interpolated in time between the logged
   ones (held beyond the first and last), with a warning naming how many; a
   column with no value at all is read as absent.  An empty current, voltage or
   time is an error naming its line.
3. Drop repeated timestamps (``t[k] == t[k-1]``), keeping the last sample: under
   the zero-order hold below, the earlier one holds for no time at all.
4. Resample when the native step ``median(diff(t))`` is below ``resample_s``
   (see below).  Uniform logs already at or above the requested step and any
   call with ``resample_s=None`` are returned unresampled; a non-uniform one is
   put on a grid of its own step (Resampling, 5.).

Sign of the current
-------------------
A step of the current moves the terminal voltage the same way at once (the ohmic
drop, ``dv = R0 di``), so with current positive for charge the 1-sample steps
``di_k = i_k - i_{k-1}`` and ``dv_k`` correlate positively: +0.31..+0.99 on every
file of the measured data set, at its own step and at 1 s (1 s drive cycles above 0.88).
A correlation below ``SIGN_CORRELATION_MIN`` (over at least ``SIGN_MIN_STEPS``
steps where the current changes) means the file counts discharge as positive,
and is an error: every coulomb count would run the wrong way.

Resampling (charge-preserving bin means)
----------------------------------------
The logged signal ``y`` (current, voltage, temperature) is read as held between
samples (zero-order hold: ``y(t) = y[k]`` on ``[t_k, t_{k+1})``), the convention
under which the coulomb count is ``Q = sum_k I[k] (t_{k+1} - t_k)``.  With bins
``B_j = [j Ts, (j+1) Ts)`` on the file's own time axis:

1. ``Y(t) = integral_{t_0}^{t} y dt`` is piecewise linear, known exactly at the
   sample times (``np.cumsum``) and evaluated at the bin edges by ``np.interp``.
2. The bin value is the time average over the covered part of the bin,
   ``a_j = max(j Ts, t_0)``, ``b_j = min((j+1) Ts, t_last)``::

       y_j = (Y(b_j) - Y(a_j)) / (b_j - a_j)

   so for the current ``sum_j y_j (b_j - a_j) = Q`` exactly: every ampere-second
   of the file is kept.  A bin of zero covered length (only the final sample,
   sitting exactly on a bin start) takes that sample's value.
3. The resampled sample ``j`` is stamped at the bin *start* ``j Ts``, so holding
   it over ``[j Ts, (j+1) Ts)`` - the ZOH convention of the ECM - reproduces
   the bin's charge.  Current and voltage are averaged over the same bins, so
   their relative timing is unchanged.
4. Bins that contain no sample (logging gaps) are counted in
   :attr:`CellRecording.gaps_filled` and marked in :attr:`CellRecording.filled`
   (one boolean per bin: what a user of the 1 s grid needs to tell a logged bin
   from a made-up one, e.g. the SOP back-test resting over the long gaps as the
   service does).  Voltage and temperature there are filled
   by linear interpolation between the neighbouring non-empty bins.  The
   current keeps its step-1 value (the held current of the last sample before
   the gap), because that is what the native coulomb count ``sum I dt``
   integrates: with linear interpolation a gap just before a pulse (the HPPC
   files have 1.2 s gaps at pulse edges) would invent charge that was never
   logged.  Hence ``sum_j I_j (b_j - a_j) == sum_k I[k] (t_{k+1} - t_k)``
   holds exactly for every file, gaps included.
5. A file logged at the grid's own step (median step ``Ts``) whose time axis has
   a hole (a step over ``1.5 Ts``) goes through the same bins: each logged sample
   is its own bin, and the hole becomes unlogged bins, as the same drive logged
   at 0.1 s gives.  Before, its hole was one step of the time axis: the coulomb
   count and the reference (``sum I Ts`` per sample) skipped the hole's held
   charge, a short hole (up to the sampler's 5 s, fed as stale samples) was not
   fed at all, and ``soc --trace`` had no rows there, where the 0.1 s file's had.
   A file logged at or above the grid's step whose time axis is not uniform
   (a step over 1.5 or under 0.5 of its median: a hole, or a record between its
   regular ones, as a logger that also records on a change writes) is put on a
   grid of its own median step the same way (``dt_s`` is that step; its holes
   are unlogged bins): every command counts the charge and runs the model with
   one sample period, so its holes' charge was skipped and its extra records
   counted a whole step each (a 10 s log of the LG 25 degC la92 drive with 15 %
   of its records missing: reference capacity 2.47 Ah instead of 2.82 Ah, exit 0).
   A uniform file at or above the grid's step is read as logged.
"""

from __future__ import annotations

import contextlib
import csv
import gzip
import io
import math
import os
import re
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .core.ecm import soc_from_current
from .core.ocv import CELL_TEMPERATURE_RANGE_C  # (the tables' temperature_c is held to it too)
from .errors import DataError

__all__ = [
    "CellRecording",
    "check_charge_span",
    "DataError",
    "load_recording",
    "read_file_bytes",
    "save_recording",
    "shared_data_dir",
]

REQUIRED_COLUMNS = ("time_s", "current_a", "voltage_v")
OPTIONAL_COLUMNS = ("temperature_c",)

#: a single cell's terminal voltage lies in this range [V]; outside it the column is in mV or a pack's
CELL_VOLTAGE_RANGE_V = (-1.0, 10.0)
#: correlation of the current's and the voltage's 1-sample steps below which the current is discharge-positive
SIGN_CORRELATION_MIN = -0.2
#: steps with a current change needed before the sign is judged
SIGN_MIN_STEPS = 30
#: A cell cannot move more than its capacity between its fullest and its emptiest point; a recording whose
#: coulomb count spans more than this many times the stated capacity has its current in mA, its time not in
#: seconds, or a stated capacity that is not the cell's (the data set's drive-cycle, C/20 and HPPC files span
#: 0.19-1.03 of their nominal capacity at 1 s; its hppc_steps files, logged every minute, go to `ocv` only).
CHARGE_SPAN_MAX = 1.5
#: Most samples a recording may resample to (58 days at 1 s; the data set's longest file, 27 h of HPPC, has
#: 97,600): a logging gap of years (a clock jump, a time in ms) made millions of empty bins and ended in a
#: MemoryError, before the charge check could name the file.
RESAMPLED_SAMPLES_MAX = 5_000_000


@dataclass(frozen=True, eq=False)
class CellRecording:
    """One measured (or simulated) recording of a single cell.

    Attributes:
        time_s: sample times [s], strictly increasing, float64.
        current_a: cell current [A], positive = charge.
        voltage_v: terminal voltage [V].
        temperature_c: cell temperature [degC] or ``None`` when not logged.
        source: file path or a name.
        gaps_filled: number of resampling bins that held no sample and were
            filled by linear interpolation (0 when not resampled).
        filled: per sample, True where its resampling bin held no sample of the
            file (voltage and temperature interpolated, current held: module
            docstring, "Resampling"); all False when not resampled or not given.
            ``filled.sum() == gaps_filled`` for a loaded file.

    The arrays are converted to read-only float64 arrays; copy before editing.
    """

    time_s: np.ndarray
    current_a: np.ndarray
    voltage_v: np.ndarray
    temperature_c: np.ndarray | None = None
    source: str = ""
    gaps_filled: int = field(default=0)
    filled: np.ndarray | None = None

    def __post_init__(self) -> None:
        n = None
        for name in ("time_s", "current_a", "voltage_v", "temperature_c"):
            value = getattr(self, name)
            if value is None:
                if name != "temperature_c":
                    raise ValueError(f"CellRecording.{name} is required")
                continue
            arr = np.array(value, dtype=np.float64, copy=True)
            if arr.ndim != 1:
                raise ValueError(f"CellRecording.{name} must be 1-D, got shape {arr.shape}")
            if n is None:
                n = arr.size
            elif arr.size != n:
                raise ValueError(
                    f"CellRecording.{name} has {arr.size} samples, time_s has {n}"
                )
            arr.setflags(write=False)
            object.__setattr__(self, name, arr)
        object.__setattr__(self, "source", str(self.source))
        object.__setattr__(self, "gaps_filled", int(self.gaps_filled))
        filled = np.zeros(n, dtype=bool) if self.filled is None else np.array(self.filled, dtype=bool, copy=True)
        if filled.shape != (n,):
            raise ValueError(f"CellRecording.filled has shape {filled.shape}, time_s has {n} samples")
        filled.setflags(write=False)
        object.__setattr__(self, "filled", filled)

    def __len__(self) -> int:
        return int(self.time_s.size)

    @property
    def dt_s(self) -> float:
        """Median sample step [s] (``nan`` for fewer than 2 samples)."""
        if self.time_s.size < 2:
            return math.nan
        return float(np.median(np.diff(self.time_s)))

    @property
    def duration_s(self) -> float:
        """``time_s[-1] - time_s[0]`` [s]."""
        if self.time_s.size == 0:
            return 0.0
        return float(self.time_s[-1] - self.time_s[0])


# ---------------------------------------------------------------------------
# loading


def read_file_bytes(path: Path) -> bytes:
    """The bytes of the file ``path``, decompressed where its name ends in ``.gz`` (any case): the one reader
    of recordings and OCV tables.  Raises what reading raises (``OSError``; ``EOFError`` / ``zlib.error`` /
    ``gzip.BadGzipFile`` for a cut or non-gzip ``.gz``); each caller says it in its own terms."""
    if path.name.lower().endswith(".gz"):
        with gzip.open(path, "rb") as fh:
            return fh.read()
    return path.read_bytes()


def _read_text(path: Path) -> tuple[str, bytes]:
    """The file's text, and its (decompressed) bytes."""
    try:
        raw = read_file_bytes(path)
    except FileNotFoundError:
        raise
    except (OSError, EOFError) as exc:  # corrupt gzip, unreadable file
        raise DataError(f"{path}: cannot read file ({exc})") from exc
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        text = _decode_other_text(path, raw, exc)
        raw = text.encode("utf-8")  # (the field-count check reads the bytes: one encoding for both)
    return text, raw


#: the first bytes of files a lab or vehicle exports that are not CSV text, and what to do with each
_NOT_CSV = ((b"MDF     ", "an MDF/MF4 measurement file", "export its time, current, voltage and temperature channels "
                                                        "to CSV (a bus-logging .mf4 of the pack's CAN frames goes to "
                                                        "'bms-estimator batch')"),
            (b"LOGG", "a BLF CAN log", "encode the drive with 'bms-estimator batch'"),
            (b"PK\x03\x04", "a zip archive (an Excel workbook?)", "save the sheet as CSV"),
            (b"\xd0\xcf\x11\xe0", "an OLE document (an .xls workbook?)", "save the sheet as CSV"))


def _decode_other_text(path: Path, raw: bytes, exc: UnicodeDecodeError) -> str:
    """The text of a file that is not UTF-8: UTF-16 with its byte-order mark (as Windows tools write), or a
    Windows-1252 / Latin-1 text (a cycler's export with 'degC' written as '\xb0C' in a header or comment: its numbers
    are ASCII either way); a binary file is named by what it is, with the way to CSV."""
    for magic, what, fix in _NOT_CSV:
        if raw.startswith(magic):
            raise DataError(f"{path}: {what}, not CSV text: the offline commands read CSV "
                            f"(time_s,current_a,voltage_v[,temperature_c]); {fix}") from None
    if raw[:2] in (b"\xff\xfe", b"\xfe\xff"):
        try:
            return raw.decode("utf-16")
        except UnicodeDecodeError:
            pass
    elif b"\x00" not in raw:
        try:
            return raw.decode("cp1252")
        except UnicodeDecodeError:  # the five bytes cp1252 leaves undefined: Latin-1 reads every byte
            return raw.decode("latin-1")
    raise DataError(f"{path}: not UTF-8 text ({exc})") from None


def _split_fields(line: str) -> list[str]:
    """The fields of one CSV line as ``np.loadtxt(..., quotechar='"', comments="#")`` reads them: RFC 4180
    quoting (``"0.5"``, ``"a,b"``, ``""""``), and a ``#`` outside quotes starts a comment."""
    if '"' not in line:
        return line.split("#", 1)[0].split(",")
    hashes = (k for k, c in enumerate(line) if c == "#" and line.count('"', 0, k) % 2 == 0)
    return next(csv.reader([line[:next(hashes, len(line))]]), [""])


def _parse_header(path: Path, text: str) -> tuple[list[str], int]:
    """Return (column names, 1-based line number of the header)."""
    pos, lineno = 0, 0
    while pos < len(text):
        end = text.find("\n", pos)
        end = len(text) if end < 0 else end
        line, pos, lineno = text[pos:end], end + 1, lineno + 1
        stripped = line.strip()
        if not stripped or stripped.startswith("#"):
            continue
        names = [c.strip() for c in next(csv.reader([stripped]))]
        try:
            float(names[0])
        except ValueError:
            return names, lineno
        raise DataError(
            f"{path}: no header row (line {lineno} starts with a number); "
            f"expected a header with columns {','.join(REQUIRED_COLUMNS)}"
        )
    raise DataError(f"{path}: file is empty (no header row)")


def _check_columns(path: Path, names: list[str], header_line: int) -> None:
    """Refuse a header without a required column (with a hint when it is only the delimiter or the case that
    differs) or with a column this loader reads given twice."""
    missing = [c for c in REQUIRED_COLUMNS if c not in names]
    if missing:
        hint = ""
        joined = ",".join(names)
        delimiter = next((name for d, name in ((";", "semicolon"), ("\t", "tab")) if d in joined), None)
        if delimiter:
            hint = f"; the header looks {delimiter}-delimited: this tool reads comma-separated values"
        else:
            lower = {n.lower(): n for n in names}
            near = [f"{lower[c]!r} to {c}" for c in missing if c in lower]
            if near:
                hint = f"; column names are case-sensitive: rename {', '.join(near)}"
            else:
                hint = _lab_column_hint(missing, names)
        raise DataError(
            f"{path}: missing column(s) {', '.join(missing)} "
            f"(header has: {', '.join(names)}){hint}"
        )
    for c in (*REQUIRED_COLUMNS, *OPTIONAL_COLUMNS):
        if names.count(c) > 1:
            columns = ", ".join(str(k + 1) for k, n in enumerate(names) if n == c)
            raise DataError(f"{path}: line {header_line}: column '{c}' appears {names.count(c)} times in the "
                            f"header (columns {columns}): which one holds the data is ambiguous; rename or drop one")


#: per column this loader reads: words a lab's name for it holds, its unit, and other units with their factor to it
_LAB_COLUMNS = {
    "time_s": (("test_time", "test time", "time"), "s", {"ms": "x 0.001", "min": "x 60", "h": "x 3600"}),
    "current_a": (("current", "curr", "i/", "<i>", "i ["), "A", {"ma": "x 0.001"}),
    "voltage_v": (("voltage", "volt", "ewe", "ecell", "u/", "u ["), "V", {"mv": "x 0.001"}),
    "temperature_c": (("temperature", "temp", "aux_t"), "degC", {"k": "- 273.15", "degf": "(F - 32) / 1.8",
                                                                 "f": "(F - 32) / 1.8"}),
}
_UNIT_RE = re.compile(r"[(\[/_ ]\s*(ms|min|h|s|ma|a|mv|v|k|degf|f|c|degc|°c)\s*\)?\]?\s*$")


def _lab_column_hint(missing: list[str], names: list[str]) -> str:
    """``'; rename ...'`` for the columns of a lab's export (Arbin 'Current(A)', BioLogic 'I/mA', 'time [s]'):
    which header name looks like each missing column, the factor when its unit is another (mA, ms, h), and the
    units and sign this loader reads. The error named the missing columns and the header, not the way from one
    to the other (nor that current_a is in A, positive = charge)."""
    renames = []
    for col in [*missing, *(c for c in OPTIONAL_COLUMNS if c not in names)]:
        words, unit, others = _LAB_COLUMNS[col]
        found = next((n for n in names if any(w in n.lower() for w in words) and "date" not in n.lower()
                      and not (col == "time_s" and "step" in n.lower())), None)
        if found is None:
            continue
        m = _UNIT_RE.search(found.lower())
        got = m.group(1) if m else None
        if got in others:
            renames.append(f"{found!r} to {col} in {unit} ({others[got]})")
        else:
            renames.append(f"{found!r} to {col}")
    what = ("this tool reads time_s in s, current_a in A (positive = charge), voltage_v in V and, optionally, "
            "temperature_c in degC")
    return f"; {what}: rename {', '.join(renames)}" if renames else f"; {what}"


def _locate_bad_value(path: Path, text: str, header_line: int, names: list[str],
                      usecols: list[int]) -> DataError:
    """Slow path: find the first line that np.loadtxt could not parse."""
    lines = text.splitlines()
    for lineno in range(header_line + 1, len(lines) + 1):
        line = lines[lineno - 1]
        stripped = line.strip()
        if not stripped or stripped.startswith("#"):
            continue
        fields = _split_fields(line)
        if len(fields) != len(names):
            return _field_count_error(path, lineno, len(fields), len(names))
        for col in usecols:
            value = fields[col].strip()
            if value == "":
                return DataError(f"{path}: line {lineno}: empty value in column '{names[col]}'")
            try:
                float(value)
            except ValueError:
                hint = ""
                if re.fullmatch(r"[-+]?\d*,\d+(?:[eE][-+]?\d+)?", value):  # "4,19155": a decimal comma, quoted
                    hint = ": a decimal comma? this tool reads a point as the decimal mark (4.19, not 4,19)"
                elif lineno == _first_data_line(lines, header_line) and not any(
                        _is_number(fields[c]) for c in usecols):
                    hint = ": a row of units under the header? delete it, or start it with '#'"
                elif names[col] == "time_s" and re.search(r"\d[-/.:]\d\d?[-/.: T]\d", value):
                    hint = ": time_s is seconds as a number; convert the timestamps (their seconds since the first)"
                return DataError(
                    f"{path}: line {lineno}: non-numeric value {value!r} in column '{names[col]}'{hint}"
                )
    return DataError(f"{path}: could not parse the numeric rows")


def _first_data_line(lines: list[str], header_line: int) -> int:
    """The 1-based number of the first line after the header that is neither blank nor a comment."""
    return next((k for k in range(header_line + 1, len(lines) + 1)
                 if lines[k - 1].strip() and not lines[k - 1].lstrip().startswith("#")), 0)


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


#: every byte but a comma and a line end (``bytes.translate``'s delete argument)
_NOT_COMMA_OR_LINE_END = bytes(c for c in range(256) if c not in b",\n")


def _field_count_error(path: Path, lineno: int, found: int, expected: int) -> DataError:
    return DataError(f"{path}: line {lineno} has {found} fields, the header has {expected}")


def _check_field_counts(path: Path, encoded: bytes, header_line: int, n: int) -> None:
    """Refuse a data row with more (or fewer) fields than the ``n`` of the header, which
    ``np.loadtxt(usecols=...)`` reads without a word when the columns it uses are there: the row's values
    would be read under the wrong names.

    Fast path (the usual file: no quote, no comment, no blank line): its rows' commas and line ends, all other
    bytes deleted (``bytes.translate``, one pass in C), read ``(n - 1)`` commas and a line end per row.  Else
    the commas are counted per line (vectorised), and the few lines whose count differs (blank, comments,
    quoted commas, or wrong) are split one by one."""
    body = 0
    for _ in range(header_line):  # (the header is on line header_line: the rows start after its line end)
        body = encoded.find(b"\n", body) + 1
    if body and encoded.find(b'"', body) < 0 and encoded.find(b"#", body) < 0:
        structure = encoded[body:].translate(None, _NOT_COMMA_OR_LINE_END)
        if not structure.endswith(b"\n"):
            structure += b"\n"
        if structure == (b"," * (n - 1) + b"\n") * structure.count(b"\n"):
            return
    raw = np.frombuffer(encoded, dtype=np.uint8)
    ends = np.flatnonzero(raw == ord("\n"))
    if ends.size == 0 or ends[-1] != raw.size - 1:
        ends = np.r_[ends, raw.size]
    starts = np.r_[0, ends[:-1] + 1]
    commas = np.diff(np.searchsorted(np.flatnonzero(raw == ord(",")), ends), prepend=0)
    for k in np.flatnonzero(commas != n - 1):
        if k < header_line:  # (k: the 0-based index of line k + 1; the header is line header_line)
            continue
        line = raw[starts[k]:ends[k]].tobytes().decode("utf-8")
        stripped = line.strip()
        if not stripped or stripped.startswith("#"):
            continue
        found = len(_split_fields(line))
        if found != n:
            raise _field_count_error(path, int(k) + 1, found, n)


def _data_line_numbers(text: str, header_line: int) -> np.ndarray:
    """1-based file line numbers of the data rows (rows np.loadtxt returns)."""
    lines = text.splitlines()
    nums = [
        k
        for k in range(header_line + 1, len(lines) + 1)
        if lines[k - 1].strip() and not lines[k - 1].lstrip().startswith("#")
    ]
    return np.asarray(nums, dtype=np.int64)


def load_recording(path: str | os.PathLike, *, resample_s: float | None = 1.0) -> CellRecording:
    """Load a recording CSV (``.csv`` or ``.csv.gz``), validate it, optionally resample.

    Args:
        path: file in the shared-data layout (header row required).
        resample_s: target step ``Ts`` [s].  When the native median step is below
            it, the data is averaged into bins ``[k Ts, (k+1) Ts)`` (module
            docstring).  ``None`` never resamples.

    Returns:
        :class:`CellRecording` with ``source = str(path)``.

    Raises:
        FileNotFoundError: the file does not exist.
        DataError: missing column, non-numeric / empty / NaN value (with its line
            number), fewer than 2 rows, time going backwards (with its line), a
            voltage outside a single cell's range (with its line), a temperature outside
            a cell's (with its line), a current that is positive for discharge.
    """
    path = Path(path)
    if resample_s is not None and not (math.isfinite(resample_s) and resample_s > 0):
        raise ValueError(f"resample_s must be a positive number or None, got {resample_s!r}")
    text, encoded = _read_text(path)
    names, header_line = _parse_header(path, text)
    _check_columns(path, names, header_line)
    wanted = list(REQUIRED_COLUMNS) + [c for c in OPTIONAL_COLUMNS if c in names]
    usecols = [names.index(c) for c in wanted]
    # with every column used, loadtxt reads them all and refuses a row with a field more or less itself (at no
    # cost); with unused columns it reads only the used ones, and the rows' field counts are checked after it
    every_column = sorted(usecols) == list(range(len(names)))

    try:
        data = _parse_rows(text, header_line, None if every_column else usecols)
    except ValueError:
        # an empty temperature (a sensor that dropped out) is read as not logged there; any other value
        # that is not a number is an error naming its line
        data = None
        if "temperature_c" in names:
            with contextlib.suppress(ValueError):
                data = _parse_rows(text, header_line, None if every_column else usecols,
                                   {names.index("temperature_c"): _temperature_or_nan})
        if data is None:
            raise _locate_bad_value(path, text, header_line, names, usecols) from None
    if not every_column:
        _check_field_counts(path, encoded, header_line, len(names))
    elif data.shape[0]:
        if data.shape[1] != len(names):  # every row has the same wrong count (else loadtxt refused it)
            lineno = int(_data_line_numbers(text, header_line)[0])
            raise _field_count_error(path, lineno, data.shape[1], len(names))
        if usecols != list(range(len(names))):
            data = data[:, usecols]

    if data.shape[0] < 2:
        raise DataError(f"{path}: needs at least 2 data rows, found {data.shape[0]}")

    if data.shape[1] > 3:
        data = _fill_missing_temperature(path, text, header_line, data)
    bad = ~np.isfinite(data)
    if bad.any():
        row, col = np.argwhere(bad)[0]
        lineno = int(_data_line_numbers(text, header_line)[row])
        raise DataError(
            f"{path}: line {lineno}: value {float(data[row, col])!r} in column '{wanted[col]}' "
            "is not a finite number"
        )

    checks = [(2, CELL_VOLTAGE_RANGE_V, "is not a single cell's terminal voltage (expected {lo:g}..{hi:g} V; "
                                        "is the column in mV, or a pack's voltage?)")]
    if data.shape[1] > 3:
        checks.append((3, CELL_TEMPERATURE_RANGE_C, "is not a cell temperature (expected {lo:g}..{hi:g} degC; "
                                                    "is the column in kelvin or Fahrenheit?)"))
    for col, (lo, hi), what in checks:
        off = np.flatnonzero((data[:, col] < lo) | (data[:, col] > hi))
        if off.size:
            row = int(off[0])
            lineno = int(_data_line_numbers(text, header_line)[row])
            raise DataError(f"{path}: line {lineno}: {wanted[col]} {float(data[row, col])!r} "
                            + what.format(lo=lo, hi=hi))

    t = data[:, 0]
    dt = np.diff(t)
    back = np.flatnonzero(dt < 0)
    if back.size:
        row = int(back[0]) + 1
        lineno = int(_data_line_numbers(text, header_line)[row])
        # a second recording appended (its time from 0 again), or rows out of order
        joined = t[row] <= t[0] + 0.01 * (t[row - 1] - t[0]) and np.all(np.diff(t[row:]) >= 0)
        hint = (": a second recording appended here, its time from the start again? add the first's end time to its "
                "time_s" if joined else ": sort the rows by time_s")
        raise DataError(
            f"{path}: time goes backwards at data row {row} (line {lineno}): "
            f"{float(t[row - 1])!r} -> {float(t[row])!r} s{hint}"
        )
    keep = np.r_[dt > 0, True]  # drop repeated timestamps, keep the last: the earlier one holds for no time
    data = data[keep]
    if data.shape[0] < 2:
        raise DataError(f"{path}: needs at least 2 distinct timestamps, found {data.shape[0]}")

    time_s, current_a, voltage_v = data[:, 0], data[:, 1], data[:, 2]
    temperature_c = data[:, 3] if data.shape[1] > 3 else None

    native_dt = float(np.median(np.diff(time_s)))
    _warn_if_time_is_not_in_seconds(path, native_dt)
    grid_s = None  # the step of the grid the file is put on (None: read as logged)
    if resample_s is not None:
        steps = np.diff(time_s)
        if native_dt < resample_s:
            grid_s = resample_s
        elif float(np.max(steps)) > 1.5 * native_dt or float(np.min(steps)) < 0.5 * native_dt:
            # a file logged at or above the grid's step whose time axis is not uniform - a hole (a step over 1.5
            # of its own), or records between its regular ones (under half of it: a logger that also records on
            # a change) - is put on a grid of its own step ("Resampling", 5.): the commands count the charge and
            # run the model with one sample period, so a 10 s log with 15 % of its records missing counted the
            # LG la92 drive to a capacity of 2.48 Ah, not 2.82 Ah, without a word.  A uniform file is read as
            # logged.
            grid_s = resample_s if abs(native_dt - resample_s) <= 1e-6 * resample_s else native_dt
    if grid_s is not None:
        resample_s = grid_s
        _check_resampled_size(path, text, header_line, time_s, float(resample_s))
        cols = [current_a, voltage_v] + ([temperature_c] if temperature_c is not None else [])
        t_new, values, empty = _resample_bins(
            time_s, np.column_stack(cols), float(resample_s), (False,) + (True,) * (len(cols) - 1)
        )
        rec = CellRecording(
            time_s=t_new,
            current_a=values[:, 0],
            voltage_v=values[:, 1],
            temperature_c=values[:, 2] if temperature_c is not None else None,
            source=str(path),
            gaps_filled=int(np.count_nonzero(empty)),
            filled=empty,
        )
    else:
        rec = CellRecording(time_s, current_a, voltage_v, temperature_c, str(path), 0)
    _check_current_sign(path, rec.current_a, rec.voltage_v)
    return rec


def _parse_rows(text: str, header_line: int, usecols: list[int] | None,
                converters: dict | None = None) -> np.ndarray:
    """The data rows as an (n, columns) array (``np.loadtxt``, its C parser); raises ValueError."""
    with warnings.catch_warnings():  # a header without rows is reported by the caller, not as numpy's warning
        warnings.simplefilter("ignore", UserWarning)
        return np.loadtxt(
            io.StringIO(text),
            delimiter=",",
            skiprows=header_line,
            usecols=usecols,
            converters=converters,
            dtype=np.float64,
            ndmin=2,
            comments="#",
            quotechar='"',  # RFC 4180: "0.5" is 0.5
        )


def _temperature_or_nan(value: str) -> float:
    return float(value) if value.strip() else math.nan


def _fill_missing_temperature(path: Path, text: str, header_line: int, data: np.ndarray) -> np.ndarray:
    """Read an empty or ``nan`` temperature (column 3 of ``data``) as not logged there: linearly interpolated in
    time between the logged ones, held beyond the first and the last, with a warning; a column without any
    value is dropped (the recording has no temperature).  A sensor that drops out for a few rows refused the
    whole file ("empty value in column 'temperature_c'")."""
    missing = np.isnan(data[:, 3])
    if not missing.any():
        return data
    n, row = int(np.count_nonzero(missing)), int(np.argmax(missing))
    lineno = int(_data_line_numbers(text, header_line)[row])
    if missing.all():
        warnings.warn(f"{path}: its temperature_c column holds no value: read without a temperature",
                      UserWarning, stacklevel=3)
        return data[:, :3]
    t = data[:, 0]
    if not np.all(np.isfinite(t)) or np.any(np.diff(t[~missing]) < 0):
        t = np.arange(len(data), dtype=float)  # a bad time axis, named by the checks that follow: by row here
    data = data.copy()
    data[missing, 3] = np.interp(t[missing], t[~missing], data[~missing, 3])
    warnings.warn(f"{path}: {n} of {len(data)} temperature_c values are empty or nan (the first on line {lineno}): "
                  "read between the logged ones", UserWarning, stacklevel=3)
    return data


#: logging periods a logger uses, s: a median step at one of these is read as seconds
LOGGING_STEPS_S = (0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.25, 0.5, 1.0, 2.0, 5.0, 10.0, 15.0, 20.0, 30.0,
                   60.0, 120.0, 300.0, 600.0)


def _round_step(step_s: float) -> float | None:
    """The logging period within 1 % of ``step_s`` (None: none is)."""
    return next((r for r in LOGGING_STEPS_S if abs(step_s - r) <= 0.01 * r), None)


def _warn_if_time_is_not_in_seconds(path: Path, native_dt: float) -> None:
    """Warn when the median time step is no logging period in seconds but one in minutes or hours: a 1 s drive
    whose time_s is in minutes steps by 0.01667, read as a 60 Hz log of a 3 min drive; every command ran on it
    (diagnose 'none', fit a 517 mV simulation RMSE) without naming the time axis."""
    if not native_dt > 0 or _round_step(native_dt) is not None:
        return
    found = [(unit, per, step) for unit, per in (("minutes", 60.0), ("hours", 3600.0))
             if (step := _round_step(native_dt * per)) is not None]  # 0.01667: 1 s / 60 or 60 s / 3600
    if found:
        steps = " or ".join(f"{step:g} s / {per:g}" for _, per, step in found)
        units = " or ".join(unit for unit, _, _ in found)
        warnings.warn(f"{path}: time_s steps by {native_dt:.4g} (its median), {steps}: is time_s in {units}? it is "
                      "read in seconds; convert it", UserWarning, stacklevel=3)


def _check_resampled_size(path: Path, text: str, header_line: int, time_s: np.ndarray, resample_s: float) -> None:
    """Refuse a time base that resamples to more than ``RESAMPLED_SAMPLES_MAX`` bins, naming its longest gap."""
    bins = math.floor(time_s[-1] / resample_s) - math.floor(time_s[0] / resample_s) + 1
    if bins <= RESAMPLED_SAMPLES_MAX:
        return
    k = int(np.argmax(np.diff(time_s))) + 1
    lineno = int(_data_line_numbers(text, header_line)[k])
    raise DataError(
        f"{path}: its time base spans {time_s[-1] - time_s[0]:.4g} s, {bins:,} samples at {resample_s:g} s (at most "
        f"{RESAMPLED_SAMPLES_MAX:,}); its longest logging gap ends at line {lineno} ({time_s[k - 1]:.6g} -> "
        f"{time_s[k]:.6g} s): is time_s in seconds? split the recording at the gap")


def check_charge_span(rec: CellRecording, capacity_ah: float, what: str = "capacity") -> None:
    """Refuse a recording whose charge does not fit one cell of ``capacity_ah``.

    The coulomb count ``Q(t) = integral i dt`` of one cell spans at most its capacity
    (SOC stays in [0, 1]): ``max Q - min Q > CHARGE_SPAN_MAX * capacity_ah`` raises
    :class:`DataError` naming the file, the span and ``what`` stated the capacity.
    """
    if len(rec) < 2:
        return
    span = float(np.ptp(soc_from_current(rec.current_a, rec.dt_s, capacity_ah, 1.0)))
    if span > CHARGE_SPAN_MAX and rec.filled.any():
        # the resampled grid holds the current across a logging gap ("Resampling", 4.): when that charge
        # alone breaks the bound, the gap is named, not the units (a 2 h gap under 5 A: 10 Ah of it)
        unlogged = np.where(rec.filled, 0.0, rec.current_a)
        if float(np.ptp(soc_from_current(unlogged, rec.dt_s, capacity_ah, 1.0))) <= CHARGE_SPAN_MAX:
            edges = np.flatnonzero(np.diff(np.r_[0, rec.filled.astype(np.int8), 0]))
            starts, ends = edges[::2], edges[1::2]
            j = int(np.argmax(ends - starts))
            held_ah = float(np.sum(np.abs(rec.current_a[rec.filled]))) * rec.dt_s / 3600.0
            raise DataError(
                f"{rec.source}: its coulomb count spans {span * capacity_ah:.4g} Ah, {span:.1f} times {what} = "
                f"{capacity_ah:g} Ah, {held_ah:.4g} Ah of it the current held across its logging gaps (the longest "
                f"{(ends[j] - starts[j]) * rec.dt_s:.0f} s from t = {rec.time_s[starts[j]]:.0f} s, under "
                f"{abs(float(rec.current_a[starts[j]])):.3g} A): the file does not say what flowed there; cut it "
                "at the gap")
    if span > CHARGE_SPAN_MAX:
        raise DataError(
            f"{rec.source}: its coulomb count spans {span * capacity_ah:.4g} Ah, {span:.1f} times {what} = "
            f"{capacity_ah:g} Ah: one cell cannot move more than its capacity (is current_a in mA, time_s not in "
            f"seconds, or {what} not this cell's?)")


def _check_current_sign(path: Path, current_a: np.ndarray, voltage_v: np.ndarray) -> None:
    """Refuse a discharge-positive current (module docstring, "Sign of the current")."""
    di, dv = np.diff(current_a), np.diff(voltage_v)
    moved = di != 0
    if np.count_nonzero(moved) < SIGN_MIN_STEPS or not np.any(dv != 0):
        return
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = float(np.corrcoef(di, dv)[0, 1])
    if math.isfinite(corr) and corr < SIGN_CORRELATION_MIN:
        raise DataError(
            f"{path}: current_a looks discharge-positive: the voltage falls when the current rises "
            f"(correlation of their steps {corr:+.2f}); this tool takes current positive = charge: negate the column"
        )


def _resample_bins(
    t: np.ndarray, y: np.ndarray, ts: float, interp_gaps: tuple[bool, ...]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Time-average ``y`` (n, m) over bins ``[j ts, (j+1) ts)``; see the module docstring.

    ``t`` must be strictly increasing.  Columns with ``interp_gaps[c]`` true get
    their empty bins linearly interpolated; the others keep the zero-order-hold
    average.  Returns (bin start times, bin values, per bin: True if it held no sample).
    """
    j0 = int(math.floor(t[0] / ts))
    j1 = int(math.floor(t[-1] / ts))
    nb = j1 - j0 + 1
    starts = (j0 + np.arange(nb)) * ts
    # Y(t): exact integral of the zero-order-hold signal at the sample times
    cum = np.zeros_like(y)
    np.cumsum(y[:-1] * np.diff(t)[:, None], axis=0, out=cum[1:])
    a = np.clip(starts, t[0], t[-1])
    b = np.clip(starts + ts, t[0], t[-1])
    width = b - a
    out = np.empty((nb, y.shape[1]))
    for c in range(y.shape[1]):
        ya = np.interp(a, t, cum[:, c])
        yb = np.interp(b, t, cum[:, c])
        with np.errstate(invalid="ignore", divide="ignore"):
            out[:, c] = (yb - ya) / width
    # a bin with zero covered width holds only the final sample (on its start)
    zero = width <= 0
    if zero.any():
        out[zero] = y[-1]
    # bins without any sample inside: fill by linear interpolation between occupied bins
    idx = np.floor(t / ts).astype(np.int64) - j0
    np.clip(idx, 0, nb - 1, out=idx)
    occupied = np.bincount(idx, minlength=nb) > 0
    if not occupied.all():
        occ = np.flatnonzero(occupied)
        emp = np.flatnonzero(~occupied)
        for c in range(y.shape[1]):
            if interp_gaps[c]:
                out[emp, c] = np.interp(emp, occ, out[occ, c])
    return starts, out, ~occupied


# ---------------------------------------------------------------------------
# saving


def save_recording(rec: CellRecording, path: str | os.PathLike) -> Path:
    """Write ``rec`` in the shared-data CSV layout (gzip when ``path`` ends in ``.gz``).

    Precision: time 1e-6 s, current 1e-5 A, voltage 1e-5 V, temperature 1e-3 degC.
    The gzip header carries no timestamp, so equal recordings give equal bytes.
    Returns the path written.
    """
    path = Path(path)
    cols = [rec.time_s, rec.current_a, rec.voltage_v]
    fmt = ["%.6f", "%.5f", "%.5f"]
    header = list(REQUIRED_COLUMNS)
    if rec.temperature_c is not None:
        cols.append(rec.temperature_c)
        fmt.append("%.3f")
        header.append("temperature_c")
    buf = io.StringIO()
    np.savetxt(buf, np.column_stack(cols), fmt=fmt, delimiter=",",
               header=",".join(header), comments="")
    payload = buf.getvalue().encode("utf-8")
    path.parent.mkdir(parents=True, exist_ok=True)
    if path.name.endswith(".gz"):
        with open(path, "wb") as raw, gzip.GzipFile(
            filename="", mode="wb", fileobj=raw, mtime=0
        ) as fh:
            fh.write(payload)
    else:
        path.write_bytes(payload)
    return path


# ---------------------------------------------------------------------------
# locating the shared data set


def shared_data_dir() -> Path | None:
    """Directory of the full measured data set, or ``None`` when it is not available.

    1. ``$BMS_SHARED_DATA`` when set: that directory if it exists, else ``None``
       (set it to an empty string to disable the data set explicitly).
    2. Otherwise ``<project root>/../shared/data`` if it exists, where the
       project root is the parent of the ``bms_estimator`` package directory.
    """
    env = os.environ.get("BMS_SHARED_DATA")
    if env is not None:
        if not env.strip():
            return None
        p = Path(env).expanduser()
        return p if p.is_dir() else None
    project_root = Path(__file__).resolve().parent.parent
    p = project_root.parent / "shared" / "data"
    return p if p.is_dir() else None
