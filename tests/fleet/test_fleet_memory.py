"""fleet/memory.py: batch workers keep freed memory for the next array (fewer page faults; values unaffected)."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from bms_estimator.fleet.memory import MALLOC_ENV

_PROBE = """
import os, sys
import numpy as np
from bms_estimator.fleet.memory import keep_freed_memory
if sys.argv[1] == "keep":
    assert keep_freed_memory()
def resident_mb():
    with open("/proc/self/statm") as fh:
        return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20
a = np.empty(96 * 2**20, dtype=np.uint8)  # 96 MB: above glibc's largest mmap threshold
a.fill(1)
held = resident_mb()
del a
print(held - resident_mb())
"""


def _released_mb(mode: str) -> float:
    """MB of resident memory a process gives back to the OS when it frees a 96 MB array."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("MALLOC_")}
    out = subprocess.run([sys.executable, "-c", _PROBE, mode], capture_output=True, text=True, env=env, check=True)
    return float(out.stdout.split()[-1])


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt and /proc (Linux)")
def test_keep_freed_memory_keeps_a_freed_array_for_the_next_one():
    """By default a freed 96 MB array goes back to the OS (the next one is faulted in and zeroed again, page
    by page); with the setting it stays in the process's heap for the next allocation."""
    assert _released_mb("default") > 90
    assert _released_mb("keep") < 1


def test_batch_local_cluster_starts_its_workers_with_the_malloc_environment():
    """batch's own LocalCluster: every worker process has MALLOC_ENV (Dask's 64 kB trim threshold replaced)."""
    from bms_estimator.fleet.batch import _client

    client, cluster = _client(None, 1)
    try:
        seen = client.run(lambda: {k: os.environ.get(k) for k in MALLOC_ENV})
    finally:
        client.close()
        cluster.close()
    assert list(seen.values()) == [MALLOC_ENV]
