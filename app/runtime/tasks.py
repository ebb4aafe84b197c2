"""Small asyncio helpers shared by the long-lived tasks (link owner, motion executor, lease
watcher)."""

from __future__ import annotations

import asyncio
import concurrent.futures
import logging
from collections.abc import Callable
from typing import Any

log = logging.getLogger(__name__)

#: How long `cancel_and_wait` waits for a cancelled task before cancelling it again, s.
CANCEL_AGAIN_S = 0.1


async def cancel_and_wait(task: asyncio.Task[Any] | None) -> None:
    """Cancel `task` and wait until it has finished; None and finished tasks are fine. A task
    that ends with an error other than its cancellation raises it here.

    The task is cancelled again until it ends: on Python 3.11 a cancellation that arrives as an
    `asyncio.wait_for` inside the task completes is lost (CPython gh-86296, fixed in 3.12), and
    the task goes on as if nothing happened; awaiting it once then waited for ever (a server
    shutdown that hung with its arm's motion executor still looping)."""
    if task is None:
        return
    while not task.done():
        task.cancel()
        await asyncio.wait({task}, timeout=CANCEL_AGAIN_S)  # never raises the task's outcome
    exc = None if task.cancelled() else task.exception()
    if exc is not None:
        raise exc


def retrieve(fut: asyncio.Future[Any] | concurrent.futures.Future[Any]) -> None:
    """A done callback for a future whose outcome nobody may read (a caller that gave up, a
    hold whose presses were told, a call started with `start_now`): mark its error read, or
    asyncio logs "exception never retrieved"; the error is logged at debug."""
    if not fut.cancelled() and fut.exception() is not None:
        log.debug("a call nobody waited for failed: %r", fut.exception())


def resolve(fut: asyncio.Future[None] | None) -> None:
    """Wake a waiter: set `fut`'s result unless it is done already (a timer or a callback
    from another thread may come after the waiter gave up)."""
    if fut is not None and not fut.done():
        fut.set_result(None)


def running_loop() -> asyncio.AbstractEventLoop | None:
    """The event loop running on this thread, or None."""
    try:
        return asyncio.get_running_loop()
    except RuntimeError:
        return None


def soon_on(loop: asyncio.AbstractEventLoop, fn: Callable[..., Any], *args: Any) -> None:
    """`fn(*args)` on `loop`: at once when this thread runs it, else queued with
    `call_soon_threadsafe` (RuntimeError when `loop` is closed)."""
    if running_loop() is loop:
        fn(*args)
    else:
        loop.call_soon_threadsafe(fn, *args)
