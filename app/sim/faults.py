"""Per-reply faults of a simulated link: drop, corrupt (one byte changed), latency.

One implementation for every way a simulator is reached: the in-process SimLink and the
pseudo-terminal and TCP servers of app/sim/servers.py. Seeded, so a run can be repeated.
"""

from __future__ import annotations

import random

from app.config import FaultConfig


class ReplyFaults:
    def __init__(self, faults: FaultConfig | None = None, seed: int | None = 0) -> None:
        self.faults = faults or FaultConfig()
        self._rng = random.Random(seed)
        self.dropped = 0
        self.corrupted = 0

    @property
    def latency_s(self) -> float:
        return self.faults.latency_s

    def apply(self, reply: bytes) -> bytes | None:
        """The reply as the host will see it, or None where it is lost."""
        if self._rng.random() < self.faults.drop:
            self.dropped += 1
            return None
        if reply and self._rng.random() < self.faults.corrupt:
            self.corrupted += 1
            out = bytearray(reply)
            out[self._rng.randrange(len(out))] ^= self._rng.randrange(1, 256)
            return bytes(out)
        return reply
