"""The MJPEG stream of one camera: one producer for every client (`multipart/x-mixed-replace`).

The producer runs on the HTTP loop while anyone watches: on each new frame (handed over from
the camera's thread with `call_soon_threadsafe`) it gets the frame's JPEG (encoded once, in a
worker thread) and puts the same part into every client's slot. A slot holds one part: a client
that has not taken the last one yet loses it for the newer (a slow client drops frames; nothing
queues without bound).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import AsyncIterator, Callable
from concurrent.futures import Executor

from app.cameras.camera import Camera, Frame
from app.runtime.tasks import cancel_and_wait

__all__ = ["BOUNDARY", "MjpegFeed"]

log = logging.getLogger(__name__)

BOUNDARY = "frame"
#: The producer asks an on-demand camera for frames this often while anyone watches, s.
DEMAND_EVERY_S = 1.0


def part(seq: int, jpeg: bytes) -> bytes:
    head = (f"--{BOUNDARY}\r\nContent-Type: image/jpeg\r\nContent-Length: {len(jpeg)}\r\n"
            f"X-Frame-Seq: {seq}\r\n\r\n")
    return head.encode("ascii") + jpeg + b"\r\n"


class MjpegFeed:
    """One camera's shared producer and its clients' one-part slots."""

    def __init__(self, camera: Camera, pool: Executor, loop: asyncio.AbstractEventLoop) -> None:
        self.camera = camera
        self._pool = pool
        self._loop = loop
        self._slots: set[asyncio.Queue[bytes]] = set()
        self._new = asyncio.Event()
        self._task: asyncio.Task[None] | None = None
        self._unlisten: Callable[[], None] | None = None
        self._last: tuple[int, bytes] | None = None
        self._ending = False
        #: Parts produced (each encoded once) and parts a slow client never took.
        self.produced = 0
        self.dropped = 0

    @property
    def clients(self) -> int:
        return len(self._slots)

    def _on_frame(self, _: Frame) -> None:  # the camera's thread
        self._loop.call_soon_threadsafe(self._new.set)

    async def frames(self) -> AsyncIterator[bytes]:
        """A client's parts, from now on, until it goes away or the camera goes down (the
        response ends; asked again, the route answers 503 `camera_down` with the reason)."""
        slot: asyncio.Queue[bytes] = asyncio.Queue(maxsize=1)
        if self._last is not None:  # the newest part at once, not at the next frame
            slot.put_nowait(self._last[1])
        self._slots.add(slot)
        if self._task is None or self._task.done():
            self._unlisten = self.camera.add_listener(self._on_frame)
            self._task = asyncio.create_task(self._run(), name=f"mjpeg:{self.camera.name}")
        self._new.set()  # the latest frame at once
        try:
            while not self._ending:
                try:
                    data = await asyncio.wait_for(slot.get(), DEMAND_EVERY_S)
                except TimeoutError:
                    if not self.camera.up:
                        return
                    continue
                if not data:  # end_streams: the server is shutting down
                    return
                yield data
        finally:
            self._slots.discard(slot)
            if not self._slots:
                await self.close()

    def end_streams(self) -> None:
        """End every client's response now and refuse none later (the server is shutting
        down: uvicorn waits for open responses before it stops, and a stream never ends by
        itself). On the event loop."""
        self._ending = True
        for slot in self._slots:
            if slot.full():
                slot.get_nowait()
            slot.put_nowait(b"")

    async def close(self) -> None:
        if self._unlisten is not None:
            self._unlisten()
            self._unlisten = None
        task, self._task = self._task, None
        if task is not None and task is not asyncio.current_task():
            await cancel_and_wait(task)

    async def _run(self) -> None:
        last = self._last[0] if self._last is not None else -1
        while self._slots:
            self.camera.demand()
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._new.wait(), DEMAND_EVERY_S)
            self._new.clear()
            got = await self._loop.run_in_executor(self._pool, self.camera.jpeg)
            if got is None or got[0] == last:
                continue
            last = got[0]
            data = part(*got)
            self._last = (last, data)
            self.produced += 1
            for slot in self._slots:
                if slot.full():
                    slot.get_nowait()
                    self.dropped += 1
                slot.put_nowait(data)
