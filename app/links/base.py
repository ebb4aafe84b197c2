"""The link interface: one byte transport to one arm.

A link moves bytes and nothing else: it never parses. The driver task that owns it is the
only caller (ARCHITECTURE rule 2). HID links are packetised (each read returns one report);
serial links are streams (a read returns whatever bytes have arrived).
"""

from __future__ import annotations

import abc
import enum
import time
from typing import NamedTuple

#: Bytes a stream link reads at once: several Dynamixel status packets, far above one reply
#: or HID report.
READ_CHUNK = 4096


class LinkState(enum.StrEnum):
    CONNECTING = "connecting"
    UP = "up"
    DOWN = "down"


class LinkError(Exception):
    """The transport failed (cannot open, lost, closed). The link is DOWN afterwards."""


class Reply(NamedTuple):
    """What `Link.transact` read after writing its request (a named tuple: one is made for
    every poll, on the poll thread's hot path, app/links/poller.py)."""

    #: The bytes that arrived (b"": none yet). Fewer than asked for: the reply was not
    #: complete by `deadline`; the caller may read on (`read`) for the rest or a late reply.
    data: bytes
    #: `time.monotonic()` (asyncio's `loop.time()`) by which the reply was due.
    deadline: float
    #: `time.time()` when the reply was complete, where the link read it on a thread of its
    #: own ahead of the caller (a scheduled poll's, app/links/threaded.py: when it was read, or
    #: over a socket the kernel's time of its arrival, app/links/_restpoll.c); else None.
    at: float | None = None


class Link(abc.ABC):
    """One transport. `open` may be called again after a failure to reconnect."""

    kind: str = "link"
    #: True where each `read` returns exactly one device packet (HID reports).
    packetized: bool = False

    def __init__(self, address: str = "") -> None:
        self.address = address
        self.state = LinkState.DOWN
        self.last_error: str | None = None
        #: What identifies the device on the other end, once open (an HID serial number, a
        #: simulator's), or None where the link cannot tell (a serial port's): the stored
        #: calibration is kept under it (app/calibration).
        self.identity: str | None = None
        #: `time.monotonic()` once `transact` had written its last request (None: none yet):
        #: the device has it by then, whatever the request waited for before (a link's
        #: thread pausing its schedule); the owner task's poll after a write is timed from
        #: it (`poll_delay_s`).
        self.written_at: float | None = None

    @abc.abstractmethod
    async def open(self) -> None:
        """Open the transport; raise LinkError with a reason a person can act on."""

    @abc.abstractmethod
    async def write(self, data: bytes) -> None:
        """Send bytes (a whole packet for packetised links); raise LinkError if lost."""

    @abc.abstractmethod
    async def read(self, timeout: float) -> bytes:
        """Bytes received (one packet if packetised), or b"" after `timeout` seconds of
        silence; raise LinkError if the link is lost."""

    async def transact(self, packet: bytes, reply_size: int, timeout: float) -> Reply:
        """Write `packet` and read its reply: at most `timeout` s for `reply_size` bytes (a
        stream link may return more, a packetised link one packet). This base writes and
        returns no bytes (`Reply(b"", deadline)`): the caller reads the reply with `read`, as
        the asyncio links are read. A link with a thread of its own (app/links/threaded.py)
        does both in one blocking call on that thread."""
        deadline = time.monotonic() + timeout
        await self.write(packet)
        self.written_at = time.monotonic()
        return Reply(b"", deadline)

    @abc.abstractmethod
    async def close(self) -> None:
        """Release the transport. Safe to call twice."""

    def _down(self, reason: str) -> LinkError:
        self.state = LinkState.DOWN
        self.last_error = reason
        return LinkError(reason)
