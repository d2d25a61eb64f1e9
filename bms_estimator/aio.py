"""asyncio waits that never lose a cancellation.

On Python 3.11 ``asyncio.wait_for`` can swallow the cancellation of the task that calls it:
a ``cancel()`` that arrives in the same loop iteration as the awaited thing completes is
dropped, and ``wait_for`` returns the result as if nothing had happened (CPython gh-86296,
gh-107547; 3.12 fixed it by rewriting ``wait_for`` on ``asyncio.timeout``).  The task's
cancel request stays counted (``Task.cancelling()``) but no ``CancelledError`` is raised, so a
loop that waits again blocks for good: the service's MQTT publisher, cancelled right after
it connected, hung within 30 such cancels in each of 5 runs on this 2-core machine under load
(at the 1st to 18th), and a stop that awaits such a task waits for ever (before the final
state is saved).

:func:`wait_for` is ``asyncio.wait_for`` done the 3.12 way, on ``asyncio.timeout``, which
delivers every cancellation.  Waits inside libraries (aiomqtt's publish and disconnect use
``asyncio.wait_for``) can still swallow one: a loop calls :func:`raise_if_cancelling` before
it blocks again.
"""

from __future__ import annotations

import asyncio
import threading
from collections.abc import Awaitable, Callable
from typing import TypeVar

__all__ = ["cancelling", "in_thread", "raise_if_cancelling", "wait_for"]

T = TypeVar("T")


async def wait_for(aw: Awaitable[T], timeout: float | None) -> T:
    """Await ``aw``, raising ``TimeoutError`` after ``timeout`` seconds (None: no limit); a
    cancellation of the caller is always raised, whenever it arrives."""
    async with asyncio.timeout(timeout):
        return await aw


def cancelling() -> bool:
    """True while the current task has a cancellation request pending or swallowed."""
    task = asyncio.current_task()
    return task is not None and task.cancelling() > 0


def raise_if_cancelling() -> None:
    """Raise the ``CancelledError`` that a wait inside a library may have swallowed."""
    if cancelling():
        raise asyncio.CancelledError


async def in_thread(fn: Callable[[], T], *, name: str, discard: Callable[[T], None] | None = None) -> T:
    """``fn()`` in a daemon thread of its own, awaited: a call that blocks (a CAN adapter's open, a file
    on a hung mount) holds neither the event loop nor a cancellation, which ends the wait at once.
    A result that arrives after it is handed to ``discard`` (a bus to shut down); a call that never
    returns is left in its thread, which, unlike ``asyncio.to_thread``'s executor (joined by
    ``asyncio.run``), never holds up the exit."""
    loop = asyncio.get_running_loop()
    done: asyncio.Future[T] = loop.create_future()

    def dispose(value: object) -> None:  # a result nobody awaits any more (best effort)
        if discard is not None:
            try:
                discard(value)  # type: ignore[arg-type]
            except Exception:  # noqa: BLE001, S110
                pass

    def deliver(ok: bool, value: object) -> None:
        if done.cancelled():
            if ok:
                dispose(value)
        elif ok:
            done.set_result(value)  # type: ignore[arg-type]
        else:
            done.set_exception(value)  # type: ignore[arg-type]

    def work() -> None:
        try:
            ok, value = True, fn()
        except BaseException as exc:  # noqa: BLE001 - handed to the awaiting task
            ok, value = False, exc
        try:
            loop.call_soon_threadsafe(deliver, ok, value)
        except RuntimeError:  # the loop is gone
            if ok:
                dispose(value)

    threading.Thread(target=work, name=name, daemon=True).start()
    return await done
