"""Telemetry WebSocket: `WS /api/v1/arms/{arm}/telemetry?rate=HZ`.

On connect the client gets the latest sample at once; then, every 1/rate s, ONE telemetry
message batching every sample since the last, and events as they come (checked every
`EVENT_SLICE_S`). The hub publishes synchronously into this client's bounded backlog, so the
link task never waits for a socket; only this client's sender awaits its own socket. A client
too slow to keep up loses the oldest samples and is told how many in `dropped`.

Close codes: 4401 bad or missing token, 4404 unknown arm, 1008 a `rate` that is not a finite
number (in the query or a message) or a malformed message, 1003 a binary message, 1009 a client
message over `max_ws_message_bytes`. A client may send `{"rate": HZ}` (a JSON object) to change
its rate; a well-formed JSON object without `rate` is ignored. Everything a client sends is
parsed within bounds (`parse_message`): the message's size, its JSON nesting, and numbers a
float can hold, so that nothing it sends raises out of the socket; a close reason is cut to the
protocol's 123 bytes.
"""

from __future__ import annotations

import asyncio
import json
import logging
import math
import sys

from fastapi import APIRouter, WebSocket, WebSocketDisconnect

from app.runtime.tasks import cancel_and_wait
from app.service import ArmService
from app.telemetry.hub import Subscription
from app.web.security import bearer_token
from app.web.ws_fanout import Broadcasts, Member, RawSocket

log = logging.getLogger(__name__)

router = APIRouter(tags=["telemetry"])

MIN_RATE_HZ = 0.1
MAX_RATE_HZ = 1000.0
#: Longest an event waits for the sender to notice it, s (a person does not see 50 ms).
EVENT_SLICE_S = 0.05
#: Clients at this period or shorter (100 Hz and up) get each batch as soon as it is due and
#: a sample is there; slower ones batch on a shared clock and share messages.
PROMPT_PERIOD_S = 0.01

CLOSE_UNSUPPORTED = 1003
CLOSE_UNAUTHORIZED = 4401
CLOSE_UNKNOWN_ARM = 4404
CLOSE_POLICY = 1008
CLOSE_TOO_BIG = 1009
#: Too many subscribers (per arm or in all): try again later, reason `{"code": "busy", ...}`.
CLOSE_BUSY = 1013


#: Deepest JSON nesting a client message may have (`{"rate": HZ}` has 1). Deeper ones are
#: refused before they are parsed (the parser recurses: a 4 KiB `[[[...]]]` hits Python's limit).
MAX_MESSAGE_DEPTH = 8
#: Longest close reason, bytes (RFC 6455 5.5: a control frame's 125, less the 2-byte code);
#: a longer one makes the server's protocol library raise and drop the socket with no code.
MAX_REASON_BYTES = 123
#: Most digits of an integer a float can hold (1.8e308).
FLOAT_DIGITS = 309
#: Longest shown excerpt of a client's value in a close reason, characters.
SHOWN_CHARS = 24


class BadMessage(ValueError):
    """A client's message (or query) the socket refuses; the text is the close reason."""


class BadRate(BadMessage):
    pass


def _shown(value: object) -> str:
    """A short excerpt of a client's value for a close reason (never a 400-digit number)."""
    if isinstance(value, int) and not isinstance(value, bool) and value.bit_length() > 64:
        return f"an integer of about {int(value.bit_length() * 0.30103) + 1} digits"
    text = repr(value) if isinstance(value, (str, int, float)) else type(value).__name__
    return text if len(text) <= SHOWN_CHARS else text[:SHOWN_CHARS - 3] + "..."


def close_reason(text: str) -> str:
    """`text` cut to the MAX_REASON_BYTES a close frame may carry (whole UTF-8 characters)."""
    return text.encode()[:MAX_REASON_BYTES].decode(errors="ignore")


def parse_rate(value: object, default: float) -> float:
    """A rate in Hz clamped to MIN..MAX; `default` for None; BadRate for anything that is not a
    finite number (a bool, a number a float cannot hold, NaN, infinity)."""
    if value is None or value == "":
        return min(MAX_RATE_HZ, max(MIN_RATE_HZ, default))
    if isinstance(value, bool) or not isinstance(value, (int, float, str)):
        raise BadRate(f"rate must be a number of Hz, got {_shown(value)}")
    try:
        rate = float(value)
    except OverflowError:  # an int beyond a float's range (float() of a str gives inf instead)
        raise BadRate(f"rate out of range: {_shown(value)}") from None
    except ValueError:
        raise BadRate(f"rate must be a number of Hz, got {_shown(value)}") from None
    if not math.isfinite(rate):
        raise BadRate(f"rate must be finite, got {_shown(value)}")
    return min(MAX_RATE_HZ, max(MIN_RATE_HZ, rate))


def _too_deep(text: str) -> bool:
    """Whether `text`'s brackets (outside strings) nest deeper than MAX_MESSAGE_DEPTH."""
    if text.count("[") + text.count("{") <= MAX_MESSAGE_DEPTH:
        return False
    depth = 0
    in_string = escaped = False
    for ch in text:
        if in_string:
            if escaped:
                escaped = False
            elif ch == "\\":
                escaped = True
            elif ch == '"':
                in_string = False
        elif ch == '"':
            in_string = True
        elif ch in "[{":
            depth += 1
            if depth > MAX_MESSAGE_DEPTH:
                return True
        elif ch in "]}":
            depth -= 1
    return False


def _no_constant(name: str) -> float:
    raise BadMessage(f"{name} is not a number (JSON has no NaN or Infinity)")


def _json_float(text: str) -> float:
    value = float(text)
    if not math.isfinite(value):  # 1e400: beyond a float
        raise BadMessage(f"number out of range: {_shown(text)}")
    return value


def _json_int(text: str) -> int:
    digits = len(text.lstrip("-"))
    if digits > FLOAT_DIGITS:  # 1 followed by 400 zeros: no float holds it (not even parsed)
        raise BadMessage(f"number out of range: an integer of {digits} digits")
    value = int(text)
    if abs(value) > sys.float_info.max:
        raise BadMessage(f"number out of range: an integer of {digits} digits")
    return value


def parse_message(text: str, current: float) -> float | None:
    """The rate a client's text message asks for (clamped as in the query), or None for a
    well-formed JSON object that asks for nothing this server knows. BadMessage (the close
    reason) for anything else: not JSON, not an object, nested deeper than MAX_MESSAGE_DEPTH,
    NaN or Infinity, a number (anywhere in it) that no float holds, or a `rate` that is not a
    finite number."""
    if _too_deep(text):
        raise BadMessage(f"message nested deeper than {MAX_MESSAGE_DEPTH} levels")
    try:
        body = json.loads(text, parse_constant=_no_constant, parse_float=_json_float,
                          parse_int=_json_int)
    except BadMessage:
        raise
    except RecursionError:  # not reached after _too_deep; kept so no parse can escape
        raise BadMessage(f"message nested deeper than {MAX_MESSAGE_DEPTH} levels") from None
    except ValueError:
        raise BadMessage('message is not JSON: send {"rate": HZ}') from None
    if not isinstance(body, dict):
        raise BadMessage('message must be a JSON object: send {"rate": HZ}')
    if "rate" not in body:
        return None
    return parse_rate(body["rate"], current)


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
        await ws.close(CLOSE_UNKNOWN_ARM, close_reason(f"unknown arm {arm[:64]!r}"))
        return
    try:
        rate = parse_rate(ws.query_params.get("rate"), svc.profile.link.poll_hz)
    except BadRate as exc:
        await ws.close(CLOSE_POLICY, close_reason(str(exc)))
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
    settings = state.settings  # type: ignore[attr-defined]  # app.state: untyped
    here = svc.subscriber_count
    if here >= settings.max_subscribers_per_arm:
        return f"{svc.name[:32]} has {here} subscribers (limit {settings.max_subscribers_per_arm})"
    services = state.services  # type: ignore[attr-defined]  # app.state: untyped
    total = sum(s.hub.subscriber_count for s in services.values())
    if total >= settings.max_subscribers:
        return f"{total} subscribers in all (limit {settings.max_subscribers})"
    return None


def _broadcasts(state: object) -> Broadcasts:
    """The app's telemetry broadcasts (app/web/ws_fanout.py), made on first use."""
    found: Broadcasts | None = getattr(state, "ws_broadcasts", None)
    if found is None:
        found = Broadcasts()
        state.ws_broadcasts = found  # type: ignore[attr-defined]
    return found


class _Stream:
    """One client's sender and receiver."""

    def __init__(self, ws: WebSocket, svc: ArmService, rate: float, max_message: int) -> None:
        self.ws = ws
        self.svc = svc
        self.period = 1.0 / rate
        self.max_message = max_message
        self._rate_changed = False
        self._changed = asyncio.Event()  # set with _rate_changed: a broadcast member leaves

    async def run(self) -> None:
        # The subscription carries the latest sample as of subscribing (`initial`); every later
        # sample is in the hub's log from the subscription's cursor on: none lost, none twice.
        sub = self.svc.subscribe()
        try:
            tasks = {asyncio.create_task(self._send(sub)),
                     asyncio.create_task(self._receive())}
            done, pending = await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
            for t in pending:
                t.cancel()
            for t in pending:
                await cancel_and_wait(t)
            for t in done:
                if t.exception() is not None:
                    raise t.exception()  # type: ignore[misc]  # checked not None above
        except (WebSocketDisconnect, OSError, RuntimeError):
            pass  # the client went away: nothing to tell it
        finally:
            sub.close()

    async def _send(self, sub: Subscription) -> None:
        ws = self.ws
        if sub.initial is not None:
            await ws.send_text(sub.telemetry_message([sub.initial], 0))
        raw = RawSocket.open(ws)
        while True:
            self._rate_changed = False
            if self.period <= PROMPT_PERIOD_S:
                await self._send_prompt(sub)
            elif raw is not None:  # one task and one frame per batch for every such client
                self._changed = asyncio.Event()
                await _broadcasts(ws.app.state).serve(self.period, Member(sub, raw),
                                                      self._changed)
            else:
                await self._send_ticked(sub)

    async def _send_ticked(self, sub: Subscription) -> None:
        """Batches on ticks of a clock shared by every client at the same rate (multiples of
        the period in loop time), each holding the samples published before its tick: clients
        at one rate take the same samples and share one built message (`take_message`).
        Returns when the rate changes."""
        ws = self.ws
        loop = asyncio.get_running_loop()
        tick = math.floor(loop.time() / self.period) + 1
        while not self._rate_changed:
            next_batch = tick * self.period
            now = loop.time()
            wake = min(next_batch, now + EVENT_SLICE_S)
            if wake > now:
                await asyncio.sleep(wake - now)
            for event in sub.take_events():
                await ws.send_text(event)
            now = loop.time()
            if now >= next_batch:
                msg = sub.take_message(until=next_batch)
                if msg is not None:
                    await ws.send_text(msg)
                tick += 1
                if tick * self.period < loop.time():  # fell behind (slow socket): do not burst
                    tick = math.floor(loop.time() / self.period) + 1

    async def _send_prompt(self, sub: Subscription) -> None:
        """For a rate near the device's own (period up to PROMPT_PERIOD_S): a sample that
        arrives when the last message is a period old goes out at once, not at the next tick,
        so a command's effect (a pass-through write's) reaches the client one device round
        trip after it, an estop's at once. Still one message a period on average. A rate at
        or above the arm's poll rate asks for no fewer messages than samples: each sample goes
        out as it is published, the extra one a command asks for (an estop's, a pass-through
        write's) included, instead of waiting out the period of the scheduled one before it.
        Returns when the rate changes."""
        ws = self.ws
        loop = asyncio.get_running_loop()
        next_send = loop.time()
        every = self.period * self.svc.profile.link.poll_hz <= 1.0 + 1e-9  # (set per rate)
        while not self._rate_changed:
            await sub.wait(EVENT_SLICE_S)
            for event in sub.take_events():
                await ws.send_text(event)
            now = loop.time()
            if now < next_send and not every:
                await asyncio.sleep(next_send - now)
                now = loop.time()
            msg = sub.take_message()
            if msg is not None:
                await ws.send_text(msg)
                next_send = max(next_send + self.period, now)

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
                await self.ws.close(CLOSE_UNSUPPORTED, close_reason(json.dumps(
                    {"code": "invalid_request",
                     "detail": 'binary message: send JSON text, {"rate": HZ}'},
                    separators=(",", ":"))))
                return
            try:
                rate = parse_message(data, 1.0 / self.period)
            except BadMessage as exc:
                log.debug("%s: telemetry client refused: %s", self.svc.name, exc)
                await self.ws.close(CLOSE_POLICY, close_reason(str(exc)))
                return
            if rate is not None:
                self.period = 1.0 / rate
                self._rate_changed = True
                self._changed.set()
