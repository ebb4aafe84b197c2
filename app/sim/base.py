"""The contract of a simulated device: bytes in, bytes out, time explicit (sans-IO).

A simulated device is driven by whoever carries its bytes: the in-process `SimLink`
(app/links/sim.py), or `app/sim/servers.py` over a pseudo-terminal or a TCP socket. It never
knows which, and the server never knows it is talking to one.
"""

from __future__ import annotations

from typing import Protocol


class SimDevice(Protocol):
    #: True where the device speaks in whole packets (HID reports), False for byte streams.
    packetized: bool

    def receive(self, data: bytes, now: float) -> list[tuple[float, bytes]]:
        """Take bytes written by the host at monotonic time `now` (s). Return the replies it
        causes, each as (delay after `now` in s, bytes). Physics is advanced to `now` first."""
        ...

    def advance(self, now: float) -> None:
        """Advance the simulated physics to monotonic time `now` (s)."""
        ...
