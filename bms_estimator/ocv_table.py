"""OCV table files: the edge between ``soc,ocv_v[,hysteresis_v][,temperature_c][,capacity_ah]`` CSV files and
the core's :class:`~bms_estimator.core.ocv.OcvCurve` / :class:`~bms_estimator.core.ocv_surface.OcvSurface`.

The core parses and formats the text (``OcvCurve.from_csv_text`` / ``to_csv_text``, its checks and
warnings) and combines the tables (``OcvSurface.from_tables``); reading and writing the files is done
here, so the core takes no path.  Every error names the file.
"""

from __future__ import annotations

import gzip
import os
import zlib
from collections.abc import Sequence
from pathlib import Path

from .core.ocv import OcvCurve
from .core.ocv_surface import REFERENCE_TEMPERATURE_C, OcvSurface
from .data import read_file_bytes

__all__ = ["read_ocv_table", "read_ocv_tables", "write_ocv_table"]

PathLike = str | os.PathLike


def read_ocv_table(path: PathLike) -> OcvCurve:
    """The OCV table in the file ``path`` (``OcvCurve.from_csv_text``: its columns and checks); a name ending
    in ``.gz`` is read gzip-compressed, as the recordings are.

    Raises:
        ValueError: naming the file: not UTF-8 text, not gzip data, or what the table's checks found.
        OSError: the file cannot be read (missing, a directory, no permission).
    """
    path = Path(path)
    try:
        raw = read_file_bytes(path)
    except (gzip.BadGzipFile, EOFError, zlib.error) as exc:  # (not OSError's "cannot be read": its content)
        raise ValueError(f"{path}: not a gzip file, or a truncated one ({exc})") from None
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:  # (a binary file's error named no file)
        raise ValueError(f"{path}: not UTF-8 text ({exc.reason} at byte {exc.start})") from None
    return OcvCurve.from_csv_text(text, str(path))


def read_ocv_tables(paths: Sequence[PathLike] | PathLike, temperatures_c: Sequence[float] | None = None, *,
                    default_temperature_c: float = REFERENCE_TEMPERATURE_C) -> OcvSurface:
    """One table per file, each at its ``temperature_c`` column, as one surface (``OcvSurface.from_tables``).

    ``temperatures_c`` (one per file) overrides the files' columns.
    """
    if isinstance(paths, (str, os.PathLike)):
        paths = [paths]
    paths = [Path(p) for p in paths]  # (none: OcvSurface.from_tables says so)
    return OcvSurface.from_tables([read_ocv_table(p) for p in paths], [str(p) for p in paths], temperatures_c,
                                  default_temperature_c=default_temperature_c)


def write_ocv_table(curve: OcvCurve, path: PathLike) -> Path:
    """Write ``curve`` to ``path`` (``OcvCurve.to_csv_text``), its folder made; returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(curve.to_csv_text(), encoding="utf-8")
    return path
