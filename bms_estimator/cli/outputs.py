"""The output options of the commands, checked before a command reads or computes anything.

Every command that writes files calls :func:`check_outputs` first, with its inputs and its outputs.
Each is refused as a usage error (exit 2) naming the option and the path:

* an output that is the same file as an input (``ocv c20.csv -o c20.csv`` overwrote the measured
  test), or as another output;
* a file output whose directory does not exist (``fit --json nodir/x.json`` made ``nodir``: a typo
  made directories anywhere, ``/nonexistdir`` at the filesystem root), or one that is a directory;
* a folder output (``compare --plots DIR``) that exists and is not a directory, or whose parent does
  not exist: the command makes the folder itself, not the path to it;
* a figure whose suffix matplotlib cannot write (:func:`figure_output`), said after the whole fit;
* an output the command could not write where it is given (a read-only file or directory, one without write
  permission, a directory of ``/proc``): ``fit --json /proc/x.json`` failed only after the whole run, exit 3
  ("No such file or directory", no option named), and the result was lost.

``-`` (standard output, where an option takes it) and an option not given (``None``) are not checked.
"""

from __future__ import annotations

import os
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Sequence

from ..errors import UsageError

__all__ = ["Output", "file_output", "folder_output", "figure_output", "check_outputs"]

#: an input: (the option or argument that names it, the path or paths it gives, None if not given)
Input = tuple[str, Path | str | Sequence[Path | str] | None]


@dataclass(frozen=True)
class Output:
    """An output option's ``path`` (``None``: not given), whether it is a ``folder`` the command makes,
    and ``writes``: every file the command writes for it (the path itself for a file output, possibly
    more beside it; for a folder, the files inside it)."""

    option: str
    path: Path | None
    folder: bool = False
    writes: tuple[Path, ...] = ()


def _given(path: Path | str | None, stdout: bool) -> Path | None:
    if path is None or (stdout and str(path) == "-"):
        return None
    return Path(path)


def file_output(option: str, path: Path | str | None, *beside: str, stdout: bool = False) -> Output:
    """A file ``option`` writes at ``path`` (``stdout``: ``-`` is standard output), and the files named
    ``beside`` it (a name, or ``{stem}`` / ``{name}`` patterns of the path's stem / name)."""
    p = _given(path, stdout)
    if p is None:
        return Output(option, None)
    also = tuple(p.with_name(b.format(stem=p.stem, name=p.name)) for b in beside)
    return Output(option, p, writes=(p, *also))


def folder_output(option: str, path: Path | str | None, *names: str) -> Output:
    """A folder ``option`` makes at ``path`` (the folder itself; its parent must exist), writing the
    files ``names`` inside it."""
    p = _given(path, False)
    return Output(option, p, folder=True, writes=tuple(p / n for n in names) if p is not None else ())


def figure_output(option: str, path: Path | str | None, *beside: str) -> Output:
    """:func:`file_output` for a figure: its suffix must be a format matplotlib writes (no suffix:
    matplotlib's default, PNG, whose suffix it appends)."""
    p = _given(path, False)
    if p is None:
        return Output(option, None)
    fmt = p.suffix[1:].lower()
    if fmt:
        from matplotlib.backend_bases import FigureCanvasBase

        formats = FigureCanvasBase.get_supported_filetypes()
        if fmt not in formats:
            raise UsageError(f"{option} {p}: matplotlib cannot write a '.{fmt}' figure; give a file ending in "
                             f"{', '.join('.' + f for f in sorted(formats))}")
    else:
        p = p.with_name(p.name + ".png")  # what matplotlib writes
    return file_output(option, p, *beside)


def _same_file(a: Path, b: Path) -> bool:
    """Whether ``a`` and ``b`` are one file (the same inode, through links and relative paths too)."""
    try:
        return os.path.samefile(a, b)
    except OSError:  # one of them does not exist (yet): the same path, resolved
        return a.resolve() == b.resolve()


def _input_paths(inputs: Iterable[Input]) -> list[tuple[str, Path]]:
    out = []
    for name, given in inputs:
        if given is None:
            continue
        for p in [given] if isinstance(given, (str, os.PathLike)) else given:
            if p is not None and str(p) != "-":
                out.append((name, Path(p)))
    return out


def _check_place(o: Output) -> None:
    """The output's own path: a file output's directory exists and the path is not a directory; a folder
    output's parent exists and the path is not a file."""
    path = o.path
    if o.folder and path.exists() and not path.is_dir():
        raise UsageError(f"{o.option} {path}: exists and is not a directory; give a folder (it is made if missing)")
    if not o.folder and path.is_dir():
        raise UsageError(f"{o.option} {path}: is a directory; give a file name")
    missing = _missing_dir(path.parent)
    if missing is not None:
        what = "is a file, not a directory" if missing.exists() else "does not exist"
        raise UsageError(f"{o.option} {path}: the directory {missing} {what}; give a path in an existing "
                         "directory, or create it first")
    _check_writable(o)


def _check_writable(o: Output) -> None:
    """The output can be written: an existing file is writable, and the directory it is made in (a file's, a
    missing folder's parent, an existing folder itself) takes a new file, tried with a temporary file that is
    removed at once (``os.access`` says yes to root on a read-only mount or in ``/proc``)."""
    path = o.path
    if not o.folder and path.exists() and not os.access(path, os.W_OK):
        raise UsageError(f"{o.option} {path}: the file is not writable; give a path you can write to")
    where = path if o.folder and path.is_dir() else path.parent
    try:
        with tempfile.TemporaryFile(dir=where):
            pass
    except OSError as exc:
        raise UsageError(f"{o.option} {path}: cannot write in the directory {where} ({exc.strerror or exc}); "
                         "give a path in a directory you can write to") from None


def _missing_dir(where: Path) -> Path | None:
    """The first directory on the way to ``where`` that is not there (or not a directory); None: all are."""
    if where.is_dir():
        return None
    missing = where
    for parent in where.parents:
        if parent.is_dir():
            break
        missing = parent
    return missing


def check_outputs(inputs: Iterable[Input], outputs: Iterable[Output]) -> None:
    """Refuse (:class:`~bms_estimator.errors.UsageError`, exit 2) an output in a missing directory, of the
    wrong kind, or the same file as an input or as another output (module docstring)."""
    ins = _input_paths(inputs)
    given = [o for o in outputs if o.path is not None]
    written: list[tuple[str, Path]] = []
    for o in given:
        _check_place(o)
        for w in o.writes:
            said = f"{o.option} {o.path}" + (f" (it writes {w})" if w != o.path else "")
            for name, p in ins:
                if _same_file(w, p):
                    raise UsageError(f"{said} is the input {name} {p}: writing it would overwrite the input; "
                                     "give another path")
            for name, p in written:
                if _same_file(w, p):
                    raise UsageError(f"{said} is also written by {name}: one would overwrite the other; "
                                     "give another path")
            written.append((o.option, w))
