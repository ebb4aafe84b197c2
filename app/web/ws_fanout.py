"""Telemetry fan-out to many WebSocket clients: one task per (arm, rate), pre-built frames.

At 1,000 clients and 30 messages a second, a sender task per client (a timer, a wake-up, a
`send_text` through Starlette and the WebSocket library per message) costs more than a core
(py-spy: half of it in `send_text`). Here the clients of one arm at one rate are members of a
`Broadcast`: ONE task wakes on the rate's shared clock, takes every member's batch under one
hub lock (members at the same cursor share one built message, `TelemetryHub.messages`), frames
each distinct message once (RFC 6455 text frame, server frames are unmasked) and writes the
frame bytes to each member's transport. The contract is the per-client sender's: every sample
once, in order (`seq` gap-free), batched per period, events as they come (checked every
`EVENT_SLICE_S`), and a client too slow to keep up is skipped while its transport holds more
than `SLOW_CLIENT_BYTES`: its backlog in the hub is bounded, and its next message says in
`dropped` how many samples it lost.

The direct write is used only where it is sound: uvicorn's websockets-sansio protocol (the
default) with no extension negotiated (`ws_compression` off: permessage-deflate frames need
the library). Anything else (the test client, compression on) gets the per-client sender.
Reaching that protocol from a route's WebSocket takes Starlette's and uvicorn's internals:
they are behind app/doors/starlette.py and app/doors/uvicorn.py, and nowhere else.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
from typing import Any

from app.doors import starlette as starlette_door
from app.doors import uvicorn as uvicorn_door
from app.telemetry.hub import Subscription, TelemetryHub

#: Longest an event waits for the broadcast to notice it, s.
EVENT_SLICE_S = 0.05
#: A broadcast writes its members in slices of this many, SLICE_GAP_S apart, over SPREAD of
#: the period at most (see _run).
SLICE = 100
SLICE_GAP_S = 0.003
SPREAD = 0.8
#: A member whose transport holds more than this is skipped (it reads too slowly); its
#: samples wait in the hub's bounded log, and it is told what it lost when it catches up.
SLOW_CLIENT_BYTES = 64 * 1024


def text_frame(payload: bytes) -> bytes:
    """One unfragmented, unmasked text frame (RFC 6455 section 5.2) carrying `payload`."""
    n = len(payload)
    if n < 126:
        head = bytes((0x81, n))
    elif n < 1 << 16:
        head = b"\x81\x7e" + n.to_bytes(2, "big")
    else:
        head = b"\x81\x7f" + n.to_bytes(8, "big")
    return head + payload


class RawSocket:
    """The transport under an accepted uvicorn (websockets-sansio) WebSocket, for frames the
    server builds itself; `open()` is None where a direct write is not sound. What it needs of
    Starlette and uvicorn is behind their doors (app/doors/)."""

    def __init__(self, proto: Any) -> None:
        self._proto = proto
        self.transport: asyncio.WriteTransport = uvicorn_door.ws_transport(proto)

    @classmethod
    def open(cls, ws: Any) -> RawSocket | None:
        proto = uvicorn_door.websocket_protocol(starlette_door.send_owners(ws))
        return None if proto is None else cls(proto)

    @property
    def closed(self) -> bool:
        return uvicorn_door.ws_closed(self._proto) or self.transport.is_closing()

    @property
    def slow(self) -> bool:
        return self.transport.get_write_buffer_size() > SLOW_CLIENT_BYTES

    def write(self, frame: bytes) -> None:
        if not self.closed:
            self.transport.write(frame)


class Member:
    """One client in a broadcast: its subscription and its socket."""

    __slots__ = ("sub", "raw")

    def __init__(self, sub: Subscription, raw: RawSocket) -> None:
        self.sub = sub
        self.raw = raw


class Broadcast:
    """The clients of one hub at one rate, served by one task on the HTTP loop."""

    def __init__(self, hub: TelemetryHub, period: float) -> None:
        self.hub = hub
        self.period = period
        self.members: dict[Subscription, Member] = {}
        self._task: asyncio.Task[None] | None = None

    def add(self, member: Member) -> None:
        self.members[member.sub] = member
        if self._task is None or self._task.done():
            self._task = asyncio.get_running_loop().create_task(
                self._run(), name=f"telemetry:{self.hub.arm}@{1 / self.period:g}Hz")

    def remove(self, sub: Subscription) -> None:
        self.members.pop(sub, None)

    async def _run(self) -> None:
        loop = asyncio.get_running_loop()
        period = self.period
        tick = math.floor(loop.time() / period) + 1
        while self.members:
            next_batch = tick * period
            now = loop.time()
            wake = min(next_batch, now + EVENT_SLICE_S)
            if wake > now:
                await asyncio.sleep(wake - now)
            members = list(self.members.values())
            for m in members:
                if m.sub.has_events:
                    for event in m.sub.take_events():
                        m.raw.write(text_frame(event.encode()))
            if loop.time() < next_batch:
                continue
            # The members go out in slices of SLICE members, a slice every SLICE_GAP_S from
            # the tick (over SPREAD of the period at most): one burst of 1,000 frames reached
            # a reader holding many of these sockets (a lab machine with many dashboards, the
            # benchmark's client) faster than it could take them, and where each client fell
            # in its reads moved from tick to tick (gaps of 41 ms where the period is 33). A
            # member keeps its place, so its messages stay a period apart.
            gap = min(SLICE_GAP_S, SPREAD * period / max(1, math.ceil(len(members) / SLICE)))
            frames: dict[int, tuple[str, bytes]] = {}
            for k in range(0, len(members), SLICE):
                if k:
                    wait = next_batch + gap * (k // SLICE) - loop.time()
                    if wait > 0:
                        await asyncio.sleep(wait)
                self._write_slice(members[k:k + SLICE], next_batch, frames)
            tick += 1
            if tick * period < loop.time():  # fell behind (a stalled loop): do not burst
                tick = math.floor(loop.time() / period) + 1


    def _write_slice(self, members: list[Member], until: float,
                     frames: dict[int, tuple[str, bytes]]) -> None:
        """Each live member's batch of the samples published before `until`, one built
        frame per distinct message (`frames`, by message id, holding the message so that the
        id stays its own; shared by a tick's slices); the least Python per member (30,000
        writes a second at 1,000 clients)."""
        subs, transports = [], []
        for m in members:
            raw = m.raw
            if not raw.slow and not raw.closed:
                subs.append(m.sub)
                transports.append(raw.transport)
        last: str | None = None
        frame = b""
        for transport, msg in zip(transports, self.hub.messages(subs, until), strict=True):
            if msg is None:
                continue
            if msg is not last:  # (members at one cursor share one message object)
                found = frames.get(id(msg))
                if found is None:
                    found = frames[id(msg)] = (msg, text_frame(msg.encode()))
                last, frame = msg, found[1]
            transport.write(frame)


class Broadcasts:
    """Every broadcast of one app, by (hub, period); held in `app.state`."""

    def __init__(self) -> None:
        self._groups: dict[tuple[int, float], Broadcast] = {}

    async def serve(self, period: float, member: Member, until: asyncio.Event) -> None:
        """Serve `member` in the broadcast for (its subscription's hub, period) until `until`
        is set."""
        hub = member.sub.hub
        key = (id(hub), period)
        group = self._groups.get(key)
        if group is None or group.hub is not hub:
            group = self._groups[key] = Broadcast(hub, period)
        group.add(member)
        try:
            await until.wait()
        finally:
            group.remove(member.sub)
            if not group.members:
                with contextlib.suppress(KeyError):
                    if self._groups[key] is group:
                        del self._groups[key]
