"""The batch worker's allocator: memory a drive frees is kept for the next array, not returned to the OS.

A drive's stages allocate and free arrays of tens to hundreds of MB (the log's bytes, the
offsets of its fields, the decoded events, the samples, the per-cell outputs). glibc serves
every allocation above its mmap threshold (32 MB at most) with a fresh ``mmap`` and unmaps it
on ``free``, and trims the heap's free top (a Dask nanny sets ``MALLOC_TRIM_THRESHOLD_`` to
64 kB for its workers), so each such array is faulted in again, page by page, zeroed by the
kernel. On the 2-core machine of the README that cost about 2 ms per MB: 1 to 3 s of a 4 h
96-cell drive's 7 to 13 s were page faults (``bms-estimator bench`` figures, README "Fleet
re-estimation").

:data:`MALLOC_ENV` turns that off for a process started with it: no ``mmap`` for
allocations (``MALLOC_MMAP_MAX_=0``), one arena (``MALLOC_ARENA_MAX=1``: a Dask worker runs
its tasks in a thread, and a thread's own arena falls back to ``mmap`` for anything over
64 MB), no trimming below 2 GB of free top (``MALLOC_TRIM_THRESHOLD_``). Freed memory stays
in the heap and the next allocation reuses it. Values are not affected (the same arithmetic on
the same numbers); the cost is resident memory that stays at the worker's peak (about 2.2 GB
for 4 stacked drives of 4 h x 96 cells). glibc reads these variables at process start: the
batch's ``LocalCluster`` passes them to its worker processes (Dask's
``distributed.nanny.pre-spawn-environ``); workers of an existing cluster (``--scheduler``)
need them in their environment. :func:`keep_freed_memory` sets the same in a running
process (``mallopt``) for its main thread's allocations, as ``bms-estimator bench`` does to
measure what a worker's task costs.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import sys

__all__ = ["MALLOC_ENV", "keep_freed_memory"]

_TRIM_THRESHOLD = 2**31 - 1  # mallopt takes a C int

#: environment of a batch worker process (glibc reads it at process start)
MALLOC_ENV = {"MALLOC_ARENA_MAX": "1", "MALLOC_MMAP_MAX_": "0", "MALLOC_TRIM_THRESHOLD_": str(_TRIM_THRESHOLD)}

# mallopt parameters (glibc malloc.h)
_M_TRIM_THRESHOLD = -1
_M_MMAP_MAX = -4
_M_ARENA_MAX = -8


def keep_freed_memory() -> bool:
    """:data:`MALLOC_ENV`'s settings in this running process (glibc's ``mallopt``); False where there is no glibc.

    Affects the allocations to come in arenas made from now on and in the main one (a thread
    that already has its own arena keeps it: start worker processes with :data:`MALLOC_ENV`).
    """
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):  # not glibc (musl has no mallopt)
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    return all(mallopt(param, value) == 1 for param, value in (
        (_M_ARENA_MAX, 1), (_M_MMAP_MAX, 0), (_M_TRIM_THRESHOLD, _TRIM_THRESHOLD)))
