"""bms_estimator.aio: waits that never lose the caller's cancellation (CPython gh-86296 on 3.11)."""

from __future__ import annotations

import asyncio

import pytest

from bms_estimator import aio


async def _finished_task() -> asyncio.Task:
    task = asyncio.create_task(asyncio.sleep(0))
    await task
    return task


def test_a_cancel_arriving_as_the_awaited_thing_is_done_is_raised():
    """The race of gh-107547, made deterministic: the awaited task is already done when the
    caller is cancelled.  Python 3.11's asyncio.wait_for returns its result and drops the
    cancellation; aio.wait_for raises it."""

    async def caller(wait) -> str:
        done = await _finished_task()
        asyncio.current_task().cancel()
        await wait(done, 10.0)
        return "went on as if not cancelled"

    async def run(wait):
        task = asyncio.create_task(caller(wait))
        try:
            return await task
        except asyncio.CancelledError:
            return "cancelled"

    assert asyncio.run(run(aio.wait_for)) == "cancelled"


def test_raise_if_cancelling_raises_what_a_library_wait_swallowed():
    async def caller() -> str:
        done = await _finished_task()
        asyncio.current_task().cancel()
        try:
            await asyncio.wait_for(done, 10.0)  # swallows it on 3.11, raises it from 3.12 on
        except asyncio.CancelledError:
            return "raised by the library"
        assert aio.cancelling()
        aio.raise_if_cancelling()
        return "went on as if not cancelled"

    async def run():
        try:
            return await asyncio.create_task(caller())
        except asyncio.CancelledError:
            return "cancelled"

    assert asyncio.run(run()) in ("cancelled", "raised by the library")


def test_wait_for_returns_the_result_and_times_out():
    async def slow() -> int:
        await asyncio.sleep(10)
        return 1

    async def quick() -> int:
        await asyncio.sleep(0)
        return 2

    async def run():
        assert await aio.wait_for(quick(), 1.0) == 2
        assert await aio.wait_for(quick(), None) == 2
        with pytest.raises(TimeoutError):
            await aio.wait_for(slow(), 0.01)
        assert not aio.cancelling()  # a timeout leaves no cancel request behind

    asyncio.run(run())


def test_in_thread_returns_raises_and_a_cancel_does_not_wait_for_a_blocked_call():
    import threading

    release = threading.Event()
    discarded: list[str] = []

    def blocked() -> str:
        release.wait(10)
        return "late"

    async def main():
        assert await aio.in_thread(lambda: 42, name="t") == 42
        with pytest.raises(ValueError, match="bad"):
            await aio.in_thread(lambda: (_ for _ in ()).throw(ValueError("bad")), name="t")
        task = asyncio.create_task(aio.in_thread(blocked, name="t", discard=discarded.append))
        await asyncio.sleep(0.01)
        task.cancel()
        with pytest.raises(asyncio.CancelledError):
            await task
        returned_before = bool(discarded)
        release.set()
        while not discarded:
            await asyncio.sleep(0.005)
        return returned_before

    assert asyncio.run(main()) is False  # the cancel ended the wait while the call still blocked
    assert discarded == ["late"]  # and its late result went to discard
