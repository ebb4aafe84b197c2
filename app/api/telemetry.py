"""Telemetry WebSocket: `WS /api/v1/arms/{arm}/telemetry?rate=HZ`.

On connect the client gets the latest sample at once; then, every 1/rate s, ONE telemetry
message batching every sample since the last, and events as they come (checked every
`EVENT_SLICE_S`). The hub publishes synchronously into this client's bounded backlog, so the
link task never waits for a socket; only this client's sender awaits its own socket. A client
too slow to keep up loses the oldest samples and is told how many in `dropped`.

Close codes: 4401 bad or missing token, 4404 unknown arm, 1008 a `rate` that is not a number,
1009 a client message over `max_ws_message_bytes`. A client may send `{"rate": HZ}` to change
its rate; anything else it sends is ignored.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import math
from collections import deque

from fastapi import APIRouter, WebSocket, WebSocketDisconnect

from app.auth import bearer_token
from app.service import ArmService
from app.telemetry import Subscription

log = logging.getLogger(__name__)

router = APIRouter(tags=["telemetry"])

MIN_RATE_HZ = 0.1
MAX_RATE_HZ = 1000.0
#: Longest an event waits for the sender to notice it, s (a person does not see 50 ms).
EVENT_SLICE_S = 0.05

CLOSE_UNAUTHORIZED = 4401
CLOSE_UNKNOWN_ARM = 4404
CLOSE_POLICY = 1008
CLOSE_TOO_BIG = 1009
#: Too many subscribers (per arm or in all): try again later, reason `{"code": "busy", ...}`.
CLOSE_BUSY = 1013


class BadRate(ValueError):
    pass


def parse_rate(value: object, default: float) -> float:
    """A rate in Hz clamped to MIN..MAX; `default` for None; BadRate for a non-number."""
    if value is None or value == "":
        rate = default
    else:
        try:
            rate = float(value)  # type: ignore[arg-type]
        except (TypeError, ValueError):
            raise BadRate(f"rate must be a number of Hz, got {value!r}") from None
        if not math.isfinite(rate):
            raise BadRate(f"rate must be finite, got {value!r}")
    return min(MAX_RATE_HZ, max(MIN_RATE_HZ, rate))


@router.websocket("/arms/{arm}/telemetry", name="telemetry")
async def telemetry(ws: WebSocket, arm: str) -> None:
    state = ws.app.state
    token = bearer_token(ws.headers.get("authorization")) or ws.query_params.get("token")
    # Accept first: a close before the handshake reaches the client as a bare HTTP 403, with
    # no code or reason; after it, the client sees why.
    await ws.accept()
    if state.access.role_of(token) is None:
        await ws.close(CLOSE_UNAUTHORIZED, "unauthorized: missing or invalid token")
        return
    svc: ArmService | None = state.services.get(arm)
    if svc is None:
        await ws.close(CLOSE_UNKNOWN_ARM, f"unknown arm {arm[:64]!r}")
        return
    try:
        rate = parse_rate(ws.query_params.get("rate"), svc.profile.link.poll_hz)
    except BadRate as exc:
        await ws.close(CLOSE_POLICY, str(exc))
        return
    busy = subscribers_over_limit(state, svc)
    if busy is not None:
        await ws.close(CLOSE_BUSY, json.dumps({"code": "busy", "detail": busy[:90]},
                                              separators=(",", ":")))
        return
    stream = _Stream(ws, svc, rate, state.settings.max_ws_message_bytes)
    await stream.run()  # subscribes before its first await: the count above stays true


def subscribers_over_limit(state: object, svc: ArmService) -> str | None:
    """Why one more subscriber to `svc` is refused (settings `max_subscribers_per_arm`,
    `max_subscribers`), or None."""
    settings = state.settings  # type: ignore[attr-defined]
    here = svc.hub.subscriber_count
    if here >= settings.max_subscribers_per_arm:
        return f"{svc.name[:32]} has {here} subscribers (limit {settings.max_subscribers_per_arm})"
    total = sum(s.hub.subscriber_count for s in state.services.values())  # type: ignore[attr-defined]
    if total >= settings.max_subscribers:
        return f"{total} subscribers in all (limit {settings.max_subscribers})"
    return None


class _Stream:
    """One client's sender and receiver."""

    def __init__(self, ws: WebSocket, svc: ArmService, rate: float, max_message: int) -> None:
        self.ws = ws
        self.svc = svc
        self.period = 1.0 / rate
        self.max_message = max_message
        self._rate_changed = False

    async def run(self) -> None:
        sub = self.svc.hub.subscribe()
        # Read the latest sample with no await since subscribe(): every later sample reaches
        # the subscription, none is sent twice.
        latest = self.svc.hub.latest_json
        try:
            tasks = {asyncio.create_task(self._send(sub, latest)),
                     asyncio.create_task(self._receive())}
            done, pending = await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
            for t in pending:
                t.cancel()
            for t in pending:
                with contextlib.suppress(asyncio.CancelledError):
                    await t
            for t in done:
                if t.exception() is not None:
                    raise t.exception()  # type: ignore[misc]
        except (WebSocketDisconnect, OSError, RuntimeError):
            pass  # the client went away: nothing to tell it
        finally:
            sub.close()

    async def _send(self, sub: Subscription, latest: str | None) -> None:
        ws = self.ws
        if latest is not None:
            await ws.send_text(sub.telemetry_message([latest], 0))
        loop = asyncio.get_running_loop()
        pending: deque[str] = deque(maxlen=self.svc.hub.backlog)
        dropped = 0
        next_batch = loop.time() + self.period
        while True:
            now = loop.time()
            wake = min(next_batch, now + EVENT_SLICE_S)
            if wake > now:
                await asyncio.sleep(wake - now)
            if self._rate_changed:
                self._rate_changed = False
                next_batch = min(next_batch, loop.time() + self.period)
            samples, events, lost = sub.take()
            dropped += lost + max(0, len(pending) + len(samples) - (pending.maxlen or 0))
            pending.extend(samples)
            for event in events:
                await ws.send_text(event)
            now = loop.time()
            if now >= next_batch:
                if pending or dropped:
                    await ws.send_text(sub.telemetry_message(list(pending), dropped))
                    pending.clear()
                    dropped = 0
                next_batch += self.period
                if next_batch < loop.time():  # fell behind (slow socket): do not burst
                    next_batch = loop.time() + self.period

    async def _receive(self) -> None:
        while True:
            msg = await self.ws.receive()
            if msg["type"] == "websocket.disconnect":
                return
            data = msg.get("text")
            size = len(data.encode()) if data is not None else len(msg.get("bytes") or b"")
            if size > self.max_message:
                await self.ws.close(CLOSE_TOO_BIG, f"message over {self.max_message} bytes")
                return
            if data is None:
                continue
            try:
                body = json.loads(data)
                if isinstance(body, dict) and "rate" in body:
                    self.period = 1.0 / parse_rate(body["rate"], 1.0 / self.period)
                    self._rate_changed = True
            except (ValueError, BadRate):
                continue  # the contract lets the server ignore what clients send
