"""A loopback TCP server for the link tests: a stand-in board or echo on 127.0.0.1."""

from __future__ import annotations

import asyncio
import contextlib
import threading
from collections.abc import AsyncIterator, Awaitable, Callable, Coroutine
from typing import Any, TypeVar

from app.arms.dynamixel.practice import raise_priority

T = TypeVar("T")
Handler = Callable[[asyncio.StreamReader, asyncio.StreamWriter], Awaitable[None]]


@contextlib.asynccontextmanager
async def serving(handle: Handler) -> AsyncIterator[int]:
    """`handle` for each connection to a new loopback listener: its port; closed after."""
    server = await asyncio.start_server(handle, "127.0.0.1", 0)
    try:
        yield server.sockets[0].getsockname()[1]
    finally:
        server.close()
        await server.wait_closed()


class LoopThread:
    """An asyncio loop on a thread of its own: a simulated device served from it answers
    while the test's loop is held up, as a separate board would (`run` a coroutine there).
    The thread runs at the practice bus's NICENESS where the system allows it (root, as in
    CI; else as the test's): the board answers from a processor of its own. At the test's
    niceness, beside stress-ng and three other test processes, a bus served from it was silent
    through a scan's 0.3 s at each rate (`make test-loaded`)."""

    def __init__(self) -> None:
        self.loop = asyncio.new_event_loop()
        self.thread = threading.Thread(target=self._run, name="device-loop", daemon=True)
        self.thread.start()

    def _run(self) -> None:
        raise_priority()
        self.loop.run_forever()

    def run(self, coro: Coroutine[Any, Any, T]) -> T:
        return asyncio.run_coroutine_threadsafe(coro, self.loop).result(timeout=10)

    def stop(self) -> None:
        self.loop.call_soon_threadsafe(self.loop.stop)
        self.thread.join(timeout=5)
        assert not self.thread.is_alive(), "the device loop's thread outlived the test"
        self.loop.close()
