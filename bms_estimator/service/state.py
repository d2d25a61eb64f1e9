"""Estimator state that survives restarts: an atomically written ``.npz``.

File layout (``np.savez``, no pickled objects): one entry per state key plus
the reserved entries ``__format__`` (``"bms-estimator-state"``),
``__version__``, ``__pack_id__``, ``__n_cells__``, ``__saved_at__`` (wall
time, seconds since the epoch) and ``__meta__`` (a JSON object string).

:func:`save_state` writes a temp file in the same directory, flushes and
fsyncs it, renames it over the target and fsyncs the directory, so a crash at
any point leaves either the old or the new file, never a torn one.

:func:`load_state` never raises: it returns ``None`` with a logged reason when
the file is missing, stale, foreign (other format/version/pack/cell count) or
corrupt. Anything that exists but is not used is renamed aside
(``<name>.corrupt-<UTC timestamp>``, ``.foreign-…``, ``.stale-…``) so no data
is lost and the next save starts fresh; at most ``KEEP_ASIDE`` such files
are kept per kind.
"""

from __future__ import annotations

import contextlib
import glob
import json
import math
import os
import re
import tempfile
import time
import zipfile
import zlib
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np
import structlog

from ..jsonsafe import to_jsonable

__all__ = [
    "FORMAT_TAG",
    "FORMAT_VERSION",
    "StateDict",
    "estimator_state",
    "load_state",
    "resume_sox",
    "save_state",
]

log = structlog.get_logger("bms.state")

FORMAT_TAG = "bms-estimator-state"
FORMAT_VERSION = 1
MAX_FILE_BYTES = 64 * 1024 * 1024
KEEP_ASIDE = 5

_RESERVED = ("__format__", "__version__", "__pack_id__", "__n_cells__", "__saved_at__", "__meta__")
_KEY_RE = re.compile(r"^[A-Za-z][A-Za-z0-9_.-]{0,127}$")
_ALLOWED_KINDS = set("biufcUS")  # bool, int, uint, float, complex, str, bytes - never object


class StateDict(dict):  # type: ignore[type-arg]
    """The loaded state (``key -> ndarray | float | int | str``) with ``.meta``.

    ``meta`` holds the saved meta dict plus ``pack_id``, ``n_cells``,
    ``saved_at`` (epoch seconds), ``age_s`` and ``format_version``.
    """

    meta: dict[str, Any]


def _to_array(key: str, value: Any) -> np.ndarray:
    if not _KEY_RE.match(key):
        raise ValueError(f"state key {key!r} is not a plain name ([A-Za-z][A-Za-z0-9_.-]*)")
    if isinstance(value, (bool, int, float, str, np.generic, np.ndarray)):
        arr = np.asarray(value)
    else:
        raise TypeError(f"state[{key!r}]: unsupported type {type(value).__name__}")
    if arr.dtype.kind not in _ALLOWED_KINDS:
        raise TypeError(f"state[{key!r}]: dtype {arr.dtype} cannot be stored without pickle")
    return arr


def _fsync_dir(directory: Path) -> None:
    try:
        fd = os.open(directory, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def save_state(
    path: Path | str,
    state: Mapping[str, np.ndarray | float | int | str],
    meta: Mapping[str, Any],
    *,
    saved_at: float | None = None,
) -> Path:
    """Write ``state`` atomically to ``path`` (an ``.npz``); return the path.

    ``meta`` must contain ``pack_id`` (str) and ``n_cells`` (int); the rest
    must be JSON-serialisable. ``saved_at`` (epoch seconds) defaults to now.
    Raises ``ValueError``/``TypeError`` for unstorable input and ``OSError``
    for I/O failures (the temp file is removed; the old file is untouched).
    """
    path = Path(path)
    if "pack_id" not in meta or "n_cells" not in meta:
        raise ValueError("meta must contain 'pack_id' and 'n_cells'")
    pack_id = str(meta["pack_id"])
    n_cells = int(meta["n_cells"])
    extra = {k: v for k, v in meta.items() if k not in ("pack_id", "n_cells")}
    meta_json = json.dumps(to_jsonable(extra), allow_nan=False)
    when = time.time() if saved_at is None else float(saved_at)

    arrays: dict[str, np.ndarray] = {k: _to_array(k, v) for k, v in state.items()}
    arrays.update(
        {
            "__format__": np.asarray(FORMAT_TAG),
            "__version__": np.asarray(FORMAT_VERSION, dtype=np.int64),
            "__pack_id__": np.asarray(pack_id),
            "__n_cells__": np.asarray(n_cells, dtype=np.int64),
            "__saved_at__": np.asarray(when, dtype=np.float64),
            "__meta__": np.asarray(meta_json),
        }
    )

    directory = path.parent
    directory.mkdir(parents=True, exist_ok=True)
    fd, tmp_name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=directory)
    tmp = Path(tmp_name)
    try:
        with os.fdopen(fd, "wb") as fh:
            np.savez(fh, **arrays)  # type: ignore[arg-type]
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise
    _fsync_dir(directory)
    return path


class _Reject(Exception):
    def __init__(self, kind: str, reason: str) -> None:
        super().__init__(reason)
        self.kind = kind
        self.reason = reason


def _scalar(arrays: Mapping[str, np.ndarray], key: str, kinds: str) -> Any:
    arr = arrays.get(key)
    if arr is None:
        raise _Reject("corrupt", f"missing entry {key}")
    if arr.shape != () or arr.dtype.kind not in kinds:
        raise _Reject("corrupt", f"entry {key} has wrong type {arr.dtype}{list(arr.shape)}")
    return arr.item()


def _move_aside(path: Path, kind: str) -> Path | None:
    stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
    target = path.with_name(f"{path.name}.{kind}-{stamp}")
    n = 1
    while target.exists():
        target = path.with_name(f"{path.name}.{kind}-{stamp}-{n}")
        n += 1
    try:
        os.replace(path, target)
    except OSError as exc:
        log.error("cannot move state file aside", path=str(path), error=str(exc))
        return None
    _fsync_dir(path.parent)
    # Bound the number of kept files of this kind (oldest first by name).
    try:
        kept = sorted(p for p in path.parent.glob(f"{path.name}.{kind}-*") if p.is_file())
        for old in kept[:-KEEP_ASIDE]:
            old.unlink()
    except OSError:
        pass
    return target


def remove_stale_temp_files(path: Path | str) -> int:
    """Remove the temp files of saves that never finished (``.<name>.*.tmp`` beside ``path``).

    A process killed during :func:`save_state` leaves its temp file behind, up
    to the full state size each; called at start, before any save of this
    process can be in flight. Returns how many were removed (never raises).
    """
    path = Path(path)
    removed = 0
    try:
        stale = list(path.parent.glob(f".{glob.escape(path.name)}.*.tmp"))
    except OSError:
        return 0
    for tmp in stale:
        try:
            tmp.unlink()
            removed += 1
        except OSError as exc:
            log.warning("cannot remove a stale state temp file", path=str(tmp), error=str(exc))
    if removed:
        log.info("removed temp files of unfinished state saves", directory=str(path.parent), files=removed)
    return removed


def load_state(
    path: Path | str,
    *,
    pack_id: str,
    n_cells: int,
    max_age_s: float | None,
    now: float | None = None,
) -> StateDict | None:
    """Load state saved by :func:`save_state`, or ``None`` (never raises).

    Temp files of unfinished saves are removed first (:func:`remove_stale_temp_files`).
    ``None`` when the file is missing, older than ``max_age_s`` (None = no
    limit) or saved more than ``max_age_s`` in the future, foreign
    (other format, version, ``pack_id`` or ``n_cells``) or corrupt; every
    case but "missing" renames the file aside. ``now`` (epoch seconds)
    is for tests.

    A state saved "in the future" is this host's clock come back behind it: a gateway without a
    real-time clock boots, after a power cut, with the time its fake-hwclock or systemd-timesyncd
    saved last (up to an hour old) until NTP answers. Such a state is used (its ``age_s`` is 0; the
    daemon does not rest it and says so), as far ahead as a past state may be old; further ahead, the
    clock is not to be trusted at all and it is set aside as ``stale``.
    """
    path = Path(path)
    remove_stale_temp_files(path)
    try:
        return _load(path, pack_id=pack_id, n_cells=n_cells, max_age_s=max_age_s, now=now)
    except _Reject as rej:
        aside = _move_aside(path, rej.kind) if path.exists() else None
        log.warning(
            "saved estimator state not used; starting fresh",
            path=str(path),
            kind=rej.kind,
            reason=rej.reason,
            moved_to=str(aside) if aside else None,
        )
        return None
    except Exception as exc:  # noqa: BLE001 - last resort: never raise
        log.error("unexpected error loading state; starting fresh", path=str(path), error=repr(exc))
        return None


def _load(
    path: Path, *, pack_id: str, n_cells: int, max_age_s: float | None, now: float | None
) -> StateDict | None:
    try:
        size = path.stat().st_size
    except FileNotFoundError:
        log.info("no saved estimator state; starting fresh", path=str(path))
        return None
    except OSError as exc:
        log.error("cannot stat state file; starting fresh", path=str(path), error=str(exc))
        return None
    if not path.is_file():
        raise _Reject("corrupt", "not a regular file")
    if size > MAX_FILE_BYTES:
        raise _Reject("corrupt", f"file too large ({size} bytes)")

    try:
        with path.open("rb") as fh:
            magic = fh.read(4)
    except PermissionError as exc:
        log.error("cannot read state file; starting fresh", path=str(path), error=str(exc))
        return None
    if magic != b"PK\x03\x04":
        raise _Reject("corrupt", "not an npz (zip) archive" if magic else "empty file")

    arrays: dict[str, np.ndarray] = {}
    try:
        with np.load(path, allow_pickle=False) as npz:
            if not isinstance(npz, np.lib.npyio.NpzFile):
                raise _Reject("corrupt", "not an npz archive")
            for name in npz.files:
                arrays[name] = npz[name]
    except _Reject:
        raise
    except PermissionError as exc:
        # Not the file's fault: do not move it aside.
        log.error("cannot read state file; starting fresh", path=str(path), error=str(exc))
        return None
    except (ValueError, OSError, EOFError, zipfile.BadZipFile, zlib.error, KeyError, RuntimeError, TypeError) as exc:
        raise _Reject("corrupt", f"unreadable: {type(exc).__name__}: {exc}") from None
    except AttributeError:  # np.load returned a plain array (.npy) - no context manager
        raise _Reject("corrupt", "not an npz archive") from None

    if "__format__" not in arrays:
        raise _Reject("foreign", "no format tag (not a bms-estimator state file)")
    fmt = _scalar(arrays, "__format__", "U")
    if fmt != FORMAT_TAG:
        raise _Reject("foreign", f"format {fmt!r} is not {FORMAT_TAG!r}")
    version = _scalar(arrays, "__version__", "iu")
    if version != FORMAT_VERSION:
        raise _Reject("foreign", f"format version {version} (supported: {FORMAT_VERSION})")
    file_pack = _scalar(arrays, "__pack_id__", "U")
    file_cells = _scalar(arrays, "__n_cells__", "iu")
    saved_at = _scalar(arrays, "__saved_at__", "f")
    meta_json = _scalar(arrays, "__meta__", "U")
    if not math.isfinite(saved_at):
        raise _Reject("corrupt", "saved time is not finite")
    try:
        meta = json.loads(meta_json)
    except ValueError:
        raise _Reject("corrupt", "meta is not valid JSON") from None
    if not isinstance(meta, dict):
        raise _Reject("corrupt", "meta is not a JSON object")
    if file_pack != pack_id:
        raise _Reject("foreign", f"pack_id {file_pack!r} != configured {pack_id!r}")
    if file_cells != n_cells:
        raise _Reject("foreign", f"n_cells {file_cells} != configured {n_cells}")

    wall = time.time() if now is None else now
    age = wall - saved_at
    if max_age_s is not None and age < -max_age_s:
        raise _Reject("stale", f"saved {-age:.0f} s in the future (clock skew beyond max_age_s {max_age_s:.0f})")
    if max_age_s is not None and age > max_age_s:
        raise _Reject("stale", f"saved {age:.0f} s ago (max_age_s {max_age_s:.0f})")

    out = StateDict()
    for key, arr in arrays.items():
        if key in _RESERVED:
            continue
        if key.startswith("__") or arr.dtype.kind not in _ALLOWED_KINDS:
            raise _Reject("corrupt", f"unexpected entry {key!r} ({arr.dtype})")
        out[key] = arr.item() if arr.shape == () else arr
    meta.update(
        pack_id=file_pack,
        n_cells=int(file_cells),
        saved_at=float(saved_at),
        age_s=max(0.0, float(age)),
        format_version=int(version),
    )
    out.meta = meta
    log.info("saved estimator state read", path=str(path), age_s=round(max(0.0, age), 1), keys=len(out))
    return out


#: the prefix of the SOP/SOE/SOH part's keys in a state (the rest is the SOC estimator's)
SOX_PREFIX = "sox."


def estimator_state(est: Any, sox: Any = None) -> dict[str, np.ndarray]:
    """What a state file holds of the estimators: ``est.state_dict()`` and, when given, the SOX part's
    ``state_dict()`` under :data:`SOX_PREFIX`; own copies (a writer may hold them while the estimators go on)."""
    state = {k: np.array(v, copy=True) for k, v in est.state_dict().items()}
    if sox is not None:
        state.update({f"{SOX_PREFIX}{k}": np.array(v, copy=True) for k, v in sox.state_dict().items()})
    return state


def resume_sox(make_sox: Callable[[], Any], saved: Mapping[str, Any]) -> Any:
    """A fresh SOX estimator from ``make_sox()``, resumed from the SOX part of ``saved`` (an
    :func:`estimator_state`); a state without it (older files) or one that does not fit starts it
    afresh (logged), whatever the SOC part does."""
    sox = make_sox()
    part = {k[len(SOX_PREFIX):]: v for k, v in dict(saved).items() if k.startswith(SOX_PREFIX)}
    if part:
        try:
            sox.load_state_dict(part)
        except Exception as exc:  # noqa: BLE001 - ValueError, KeyError, shape errors...
            log.warning("saved SOP/SOE/SOH state not used; starting it fresh", reason=f"{type(exc).__name__}: {exc}")
            sox = make_sox()
    return sox
