"""app/runtime/tasks.py: `cancel_and_wait` ends a task even when the task loses a cancellation
(Python
3.11's `asyncio.wait_for` swallows one that arrives as its inner future completes, CPython
gh-86296; a shutdown of the fuzzed server hung on a motion executor that went on looping)."""

from __future__ import annotations

import asyncio

import pytest

from app.runtime.tasks import cancel_and_wait


async def test_a_task_that_loses_the_first_cancellation_still_ends() -> None:
    lost = 0

    async def stubborn() -> None:
        nonlocal lost
        while True:
            try:
                await asyncio.sleep(1.0)
            except asyncio.CancelledError:
                if lost == 0:  # what wait_for does on 3.11 when its future completed too
                    lost += 1
                    continue
                raise

    task = asyncio.create_task(stubborn())
    await asyncio.sleep(0)
    closer = asyncio.create_task(cancel_and_wait(task))
    await asyncio.wait({closer}, timeout=5.0)  # (a timeout that cancelled it would end it)
    assert closer.done(), "cancel_and_wait waits for ever on a task that lost a cancellation"
    assert task.cancelled() and lost == 1
    closer.result()


async def test_an_error_the_task_ended_with_is_raised_and_none_and_done_tasks_are_fine() -> None:
    async def broken() -> None:
        raise ValueError("boom")

    task = asyncio.create_task(broken())
    await asyncio.sleep(0)
    with pytest.raises(ValueError, match="boom"):
        await cancel_and_wait(task)
    await cancel_and_wait(None)
    done = asyncio.create_task(asyncio.sleep(0))
    await done
    await cancel_and_wait(done)
    assert done.done() and not done.cancelled()
