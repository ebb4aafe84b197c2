"""An in-process link to a simulated device, with fault injection.

The device (app/sim/) sees the same bytes a real link would carry; this link only adds
time: each reply is delivered at `write time + device delay + latency`, in order. Faults
(app.config.FaultConfig) can be changed while running: drop or corrupt a fraction of
replies (seeded RNG, so a run repeats), add latency, and cut the link `disconnect_after_s`
after each open for `reconnect_after_s` seconds, as an unplugged cable would.
"""

from __future__ import annotations

import asyncio
from collections import deque

from app.config import FaultConfig
from app.links.base import Link, LinkError, LinkState
from app.runtime.tasks import resolve
from app.sim.base import SimDevice
from app.sim.faults import ReplyFaults

DISCONNECTED = "simulated disconnect"


class SimLink(Link):
    """Carries bytes to and from a SimDevice on the running event loop's clock."""

    kind = "sim"

    def __init__(
        self,
        device: SimDevice,
        faults: FaultConfig | None = None,
        address: str = "sim:rbe3001",
        seed: int | None = 0,
        serial_number: str | None = None,
    ) -> None:
        """`serial_number`: the simulated device's, its identity once open (the profile's
        `link.serial_number`, as an HID device reports its own)."""
        super().__init__(address)
        self.device = device
        self.serial_number = serial_number
        self.packetized = device.packetized
        self._reply_faults = ReplyFaults(faults, seed)
        self._replies: deque[tuple[float, bytes]] = deque()  # (delivery time, bytes), in order
        self._waiter: asyncio.Future[None] | None = None  # a read waiting for bytes
        self._down_at: float | None = None  # loop time of the next scheduled disconnect
        self._up_at = float("-inf")  # loop time the "cable" is back after a disconnect

    # --- faults ------------------------------------------------------------------------

    @property
    def faults(self) -> FaultConfig:
        return self._reply_faults.faults

    def set_faults(self, faults: FaultConfig) -> None:
        """Replace the fault settings; a disconnect timer restarts from now."""
        self._reply_faults.faults = faults
        if self.state is LinkState.UP:
            self._schedule_disconnect(self._now())

    def disconnect(self) -> None:
        """Cut the link now (call from the event loop); it can be reopened after
        `faults.reconnect_after_s`. A pending read raises LinkError at once."""
        now = self._now()
        if self.state is LinkState.UP:
            self._down_at = now
            self._check()
        else:
            self._up_at = max(self._up_at, now + self.faults.reconnect_after_s)
        self._wake()

    # --- Link --------------------------------------------------------------------------

    async def open(self) -> None:
        now = self._now()
        if now < self._up_at:
            raise self._down(f"{DISCONNECTED}: back in {self._up_at - now:.3f} s")
        self.state = LinkState.UP
        self.last_error = None
        self.identity = f"sim-serial:{self.serial_number}" if self.serial_number else None
        self._replies.clear()
        self._schedule_disconnect(now)

    async def write(self, data: bytes) -> None:
        self._require()
        now = self._now()
        last = self._replies[-1][0] if self._replies else now
        for delay, reply in self.device.receive(bytes(data), now):
            out = self._reply_faults.apply(reply)
            if out is None:
                continue
            last = max(last, now + delay + self.faults.latency_s)  # never reorder
            self._replies.append((last, out))
        self._wake()

    async def read(self, timeout: float) -> bytes:
        """The due reply bytes, waiting on one timer the loop keeps until the next delivery,
        the deadline or a disconnect, whichever is first (no task per read)."""
        self._require()
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout
        while True:
            self._require()
            now = loop.time()
            if self._replies and self._replies[0][0] <= now:
                return self._take(now)
            if now >= deadline:
                return b""
            wake = deadline
            if self._replies:
                wake = min(wake, self._replies[0][0])
            if self._down_at is not None:
                wake = min(wake, self._down_at)
            fut = loop.create_future()
            self._waiter = fut
            timer = loop.call_at(wake, resolve, fut)
            try:
                await fut
            finally:
                self._waiter = None
                timer.cancel()

    async def close(self) -> None:
        self.state = LinkState.DOWN
        self._replies.clear()
        self._down_at = None
        self._wake()

    # --- internals ---------------------------------------------------------------------

    def _take(self, now: float) -> bytes:
        """One packet if packetised; else every due chunk of the stream, joined."""
        if self.packetized:
            return self._replies.popleft()[1]
        chunks = []
        while self._replies and self._replies[0][0] <= now:
            chunks.append(self._replies.popleft()[1])
        return b"".join(chunks)

    def _wake(self) -> None:
        fut = self._waiter
        if fut is not None and not fut.done():
            fut.set_result(None)

    def _schedule_disconnect(self, now: float) -> None:
        after = self.faults.disconnect_after_s
        self._down_at = None if after is None else now + after

    def _check(self) -> None:
        """Apply a due disconnect: state DOWN and the link unusable for a while."""
        if self.state is LinkState.UP and self._down_at is not None:
            if self._now() >= self._down_at:
                self._up_at = self._down_at + self.faults.reconnect_after_s
                self._down_at = None
                self._replies.clear()
                self._down(DISCONNECTED)

    def _require(self) -> None:
        self._check()
        if self.state is not LinkState.UP:
            raise LinkError(self.last_error or f"sim link {self.address} is not open")

    @staticmethod
    def _now() -> float:
        return asyncio.get_running_loop().time()

