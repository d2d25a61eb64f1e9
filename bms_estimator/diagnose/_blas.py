"""Run a block with one BLAS thread (OpenBLAS as bundled with numpy/scipy wheels), restoring afterwards.

The diagnosis does thousands of small products (a dozen rows times 10^4 samples);
OpenBLAS's threads cost more than they bring there: a 4-hour drive cycle took
13.5 s with the default threads and 4.4 s with one on a loaded 2-core machine.
There is no numpy API for this, so the OpenBLAS libraries already loaded in the
process are found in ``/proc/self/maps`` and their ``*set_num_threads*`` entry
points called through ctypes.  Anything unexpected (another BLAS, no /proc, a
missing symbol) makes this a no-op.
"""

from __future__ import annotations

import contextlib
import ctypes
from typing import Iterator

_PREFIXES = ("", "scipy_")
_SUFFIXES = ("", "64_")


def _openblas_handles() -> list[tuple[object, object]]:
    out = []
    try:
        with open("/proc/self/maps", encoding="utf-8", errors="replace") as fh:
            paths = {line.split()[-1] for line in fh if "openblas" in line.lower() and "/" in line}
    except OSError:
        return out
    for path in sorted(paths):
        try:
            lib = ctypes.CDLL(path)
        except OSError:
            continue
        for pre in _PREFIXES:
            for suf in _SUFFIXES:
                get = getattr(lib, f"{pre}openblas_get_num_threads{suf}", None)
                put = getattr(lib, f"{pre}openblas_set_num_threads{suf}", None)
                if get is not None and put is not None:
                    get.restype = ctypes.c_int
                    put.argtypes = [ctypes.c_int]
                    out.append((get, put))
    return out


@contextlib.contextmanager
def single_blas_thread() -> Iterator[None]:
    handles = _openblas_handles()
    saved = []
    for get, put in handles:
        try:
            saved.append((put, int(get())))
            put(1)
        except Exception:  # pragma: no cover - exotic BLAS builds
            continue
    try:
        yield
    finally:
        for put, n in saved:
            try:
                put(n)
            except Exception:  # pragma: no cover
                pass
