"""Preloaded into ``batch``'s local Dask workers (``distributed.worker.preload``): Ctrl-C is the batch's, not theirs.

Ctrl-C signals the terminal's whole process group, the local worker processes with it: each died of
it printing KeyboardInterrupt tracebacks (asyncio's, multiprocessing's, its nanny's) while ``batch``
stopped and closed the cluster. A worker ignores SIGINT from its start (:func:`dask_setup`, run by
Dask in the worker's main thread); ``batch`` alone stops (exit 130) and closes the cluster, which
ends the workers. Their own ``distributed`` log lines are not the user's either (closed while busy,
they logged each failed heartbeat to the scheduler with its traceback): a task that fails comes
back to ``batch`` through its future and is reported there.
"""

from __future__ import annotations

import logging
import signal


def dask_setup(worker) -> None:  # noqa: ARG001 - Dask's preload hook
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    logging.getLogger("distributed").setLevel(logging.CRITICAL)
