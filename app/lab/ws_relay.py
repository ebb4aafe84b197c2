"""The front's WebSocket relay: the client's socket joined to one on the arm's worker.

The worker does everything a single server does with the socket (token, Host and Origin,
rate, limits, close codes 4401/4404/1008/1009/1013); the relay opens the worker's socket first
with the client's headers and query, accepts the client's once the worker accepted, and then
carries messages both ways and the close code back. Slowness passes through: while the client
does not read, the relay does not read the worker, whose bounded per-subscriber backlog then
drops and counts (`dropped`), as for a direct client. A worker that dies under the socket
closes the client's with 1012 (service restart): reconnect, its arm is back in seconds.

How a message crosses (issue 27). The worker's side is websockets' sans-I/O client
(`websockets.client.ClientProtocol`) over the worker's Unix socket, driven by `WorkerSocket`,
an asyncio protocol: each frame the worker sends is parsed once, in the callback that read it.
Where the client's socket is uvicorn's websockets-sansio protocol with no extension negotiated
(the telemetry fan-out's condition: app/web/ws_fanout.py `RawSocket`, through the door of
app/doors/uvicorn.py), the frame is written to the client's transport as it came (a server's
frames are unmasked both sides of the front): no task, no message assembled, no text decoded
and encoded again. With 200 dashboards at 30 Hz through the front (`bench/lab.py
--relay-clients 200 --relay-rate 30`) the front spent 41-45 µs of CPU a relayed message when
it went through the asyncio client's messages and the ASGI `send`, 27-31 of them in user
space; it spends 32-33, 15-16 of them in user space: the rest is the kernel's (the two
sockets). Where the client negotiated compression, messages are assembled and go through the
ASGI `send` (uvicorn compresses them), one task for the socket. The worker's keepalive pings
are answered here (the client never sees them); the client's are answered by the front's
uvicorn.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import json
import logging
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any, cast

from starlette.types import Receive, Scope, Send
from websockets.client import ClientProtocol
from websockets.exceptions import InvalidHandshake, InvalidState, InvalidStatus
from websockets.frames import EXTERNAL_CLOSE_CODES, CloseCode, Frame, Opcode
from websockets.http11 import Response
from websockets.uri import parse_uri

from app.doors import uvicorn as uvicorn_door
from app.lab.headers import forwarded_headers
from app.web.ws_fanout import SLOW_CLIENT_BYTES, RawSocket

if TYPE_CHECKING:
    from app.lab.supervisor import Worker

log = logging.getLogger("armserver.lab")

#: Client handshake headers the relay does not copy (the worker's handshake makes its own).
SKIP = frozenset({b"host", b"connection", b"upgrade", b"sec-websocket-key",
                  b"sec-websocket-version", b"sec-websocket-extensions",
                  b"sec-websocket-protocol", b"content-length"})
#: How long the worker's handshake may take, s.
OPEN_TIMEOUT_S = 5.0
#: Close codes: the worker is down or went away (RFC 6455 / IANA: 1013 try again later,
#: 1012 service restart).
CLOSE_TRY_AGAIN = 1013
CLOSE_RESTART = 1012
#: While the client's transport holds more than SLOW_CLIENT_BYTES the worker is not read; it
#: is read again once the transport holds less than this, looked at every DRAIN_CHECK_S.
RESUME_BYTES = SLOW_CLIENT_BYTES // 2
DRAIN_CHECK_S = 0.01
#: Messages assembled for the ASGI `send` (compression) that may wait before the worker is
#: no longer read.
MAX_QUEUED = 16
#: How long a worker's close waits for the messages still queued to reach the client, s.
FINISH_TIMEOUT_S = 5.0
#: What the relay did with each socket it joined: frames written as they came (`direct`), or
#: messages through the ASGI send (`messages`: the client negotiated compression, or the
#: server is not uvicorn's websockets-sansio).
stats = {"direct": 0, "messages": 0}

_DATA = (Opcode.TEXT, Opcode.BINARY, Opcode.CONT)


class WorkerSocket(asyncio.Protocol):
    """The relay's WebSocket to a worker: websockets' sans-I/O client on a Unix socket.
    `opened` resolves with the handshake; `ended` with the close code and reason the worker
    sent, or None if its connection went without one (the worker died). Frames of messages go
    to the sink `attach`ed (those that came with the handshake wait for it)."""

    def __init__(self, uri: str, headers: list[tuple[str, str]]) -> None:
        self.conn = ClientProtocol(parse_uri(uri), max_size=None)
        self._request = self.conn.connect()
        for name, value in headers:
            self._request.headers[name] = value
        loop = asyncio.get_running_loop()
        self.opened: asyncio.Future[None] = loop.create_future()
        self.ended: asyncio.Future[tuple[int, str] | None] = loop.create_future()
        self.transport: asyncio.Transport | None = None
        self._sink: Callable[[Frame], None] | None = None
        self._early: list[Frame] = []
        self._paused = False

    @classmethod
    async def open(cls, uds: Path, uri: str, headers: list[tuple[str, str]],
                   timeout: float) -> WorkerSocket:
        """Connect and shake hands; raises InvalidStatus (the worker refused), another
        InvalidHandshake, OSError or TimeoutError."""
        sock = cls(uri, headers)
        loop = asyncio.get_running_loop()
        try:
            async with asyncio.timeout(timeout):
                await loop.create_unix_connection(lambda: sock, str(uds))
                await sock.opened
        except BaseException:
            if not sock.opened.done():  # (no one left to read how it ends)
                sock.opened.cancel()
            sock.abort()
            raise
        return sock

    def attach(self, sink: Callable[[Frame], None]) -> None:
        self._sink = sink
        early, self._early = self._early, []
        for frame in early:
            sink(frame)

    def send(self, message: str | bytes) -> None:
        if isinstance(message, str):
            self.conn.send_text(message.encode())
        else:
            self.conn.send_binary(message)
        self._flush()

    def close(self, code: int = CloseCode.NORMAL_CLOSURE, reason: str = "") -> None:
        """Send a close frame (if the socket is open) and close the connection after it."""
        with contextlib.suppress(InvalidState):
            self.conn.send_close(code, reason)
            self._flush()
        if self.transport is not None:
            self.transport.close()

    def abort(self) -> None:
        if self.transport is not None:
            self.transport.abort()

    def pause(self) -> None:
        if not self._paused and self.transport is not None:
            self._paused = True
            self.transport.pause_reading()

    def resume(self) -> None:
        if self._paused and self.transport is not None and not self.transport.is_closing():
            self._paused = False
            self.transport.resume_reading()

    # ------------------------------------------------------------ asyncio.Protocol

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = cast(asyncio.Transport, transport)  # (uvloop's is not a subclass)
        self.conn.send_request(self._request)
        self._flush()

    def data_received(self, data: bytes) -> None:
        self.conn.receive_data(data)
        self._take()

    def eof_received(self) -> None:
        self.conn.receive_eof()
        self._take()

    def connection_lost(self, exc: Exception | None) -> None:
        if not self.opened.done():
            self.opened.set_exception(ConnectionError("the worker closed the connection"))
        if not self.ended.done():
            self.ended.set_result(None)

    def _take(self) -> None:
        """Write what the client protocol has to send (a pong, a close's echo), then hand on
        what came."""
        self._flush()
        for event in self.conn.events_received():
            if isinstance(event, Response):
                if not self.opened.done():
                    exc = self.conn.handshake_exc
                    if exc is None:
                        self.opened.set_result(None)
                    else:
                        self.opened.set_exception(exc)
            elif isinstance(event, Frame) and event.opcode in _DATA:
                if self._sink is None:
                    self._early.append(event)
                else:
                    self._sink(event)
            # a ping: its pong is already written; a pong: none asked; a close: below
        close = self.conn.close_rcvd
        if close is not None and not self.ended.done():
            code = int(close.code)
            self.ended.set_result((CloseCode.NORMAL_CLOSURE if code == CloseCode.NO_STATUS_RCVD
                                   else code, close.reason))

    def _flush(self) -> None:
        if self.transport is None or self.transport.is_closing():
            return
        for data in self.conn.data_to_send():
            if data:
                self.transport.write(data)
            elif self.transport.can_write_eof():  # (websockets' SEND_EOF)
                self.transport.write_eof()


class _Direct:
    """A sink that writes each frame to the client's transport as it came; while the client
    reads too slowly the worker is not read."""

    def __init__(self, raw: RawSocket, upstream: WorkerSocket) -> None:
        self.raw = raw
        self.upstream = upstream
        self._watch: asyncio.TimerHandle | None = None

    def __call__(self, frame: Frame) -> None:
        self.raw.write(frame.serialize(mask=False))
        if self._watch is None and self.raw.slow:
            self.upstream.pause()
            self._watch = asyncio.get_running_loop().call_later(DRAIN_CHECK_S, self._drained)

    def _drained(self) -> None:
        if self.raw.closed:
            self._watch = None
            return
        if self.raw.transport.get_write_buffer_size() > RESUME_BYTES:
            self._watch = asyncio.get_running_loop().call_later(DRAIN_CHECK_S, self._drained)
            return
        self._watch = None
        self.upstream.resume()

    async def finish(self) -> None:
        if self._watch is not None:
            self._watch.cancel()


class _Messages:
    """A sink that assembles messages and sends them through the ASGI `send`, on a task of
    its own; more than MAX_QUEUED waiting and the worker is not read."""

    def __init__(self, send: Send, upstream: WorkerSocket) -> None:
        self.send = send
        self.upstream = upstream
        self.queue: collections.deque[dict[str, Any]] = collections.deque()
        self._parts: list[bytes] = []
        self._text = False
        self._ready = asyncio.Event()
        self._empty = asyncio.Event()
        self._empty.set()
        self._task = asyncio.create_task(self._run())

    def __call__(self, frame: Frame) -> None:
        if frame.opcode is not Opcode.CONT:
            self._parts, self._text = [], frame.opcode is Opcode.TEXT
        self._parts.append(bytes(frame.data))
        if not frame.fin:
            return
        data = b"".join(self._parts)
        self._parts = []
        self.queue.append({"type": "websocket.send", "text": data.decode()} if self._text
                          else {"type": "websocket.send", "bytes": data})
        self._ready.set()
        self._empty.clear()
        if len(self.queue) > MAX_QUEUED:
            self.upstream.pause()

    async def _run(self) -> None:
        while True:
            await self._ready.wait()
            self._ready.clear()
            while self.queue:
                await self.send(self.queue.popleft())
            self._empty.set()
            self.upstream.resume()

    async def finish(self) -> None:
        """The queued messages sent (bounded; not if sending failed), then the task ended."""
        empty = asyncio.ensure_future(self._empty.wait())
        await asyncio.wait([empty, self._task], timeout=FINISH_TIMEOUT_S,
                           return_when=asyncio.FIRST_COMPLETED)
        empty.cancel()
        self._task.cancel()
        with contextlib.suppress(asyncio.CancelledError, Exception):
            await self._task


async def _refuse(send: Send, code: int, detail: str) -> None:
    await send({"type": "websocket.accept"})
    await send({"type": "websocket.close", "code": code,
                "reason": json.dumps({"code": "link_down", "detail": detail})})


async def relay_websocket(scope: Scope, receive: Receive, send: Send,
                          worker: Worker | None) -> None:
    if (await receive())["type"] != "websocket.connect":
        return
    if worker is None or not worker.ready:
        await _refuse(send, CLOSE_TRY_AGAIN, "its worker is restarting: retry shortly")
        return
    host = dict(scope["headers"]).get(b"host", b"armserver").decode("latin-1")
    uri = f"ws://{host}{scope.get('raw_path', scope['path'].encode()).decode('latin-1')}"
    if scope.get("query_string"):
        uri += "?" + scope["query_string"].decode("latin-1")
    headers = [(k.decode("latin-1"), v.decode("latin-1")) for k, v in forwarded_headers(scope)
               if k not in SKIP]
    try:
        upstream = await WorkerSocket.open(worker.uds, uri, headers, OPEN_TIMEOUT_S)
    except InvalidStatus as exc:  # the worker refused the handshake (its Host/Origin guard)
        log.info("worker %d refused a WebSocket: %s", worker.index, exc.response.status_code)
        await send({"type": "websocket.close", "code": 1008})
        return
    except (OSError, InvalidHandshake, TimeoutError):
        await _refuse(send, CLOSE_TRY_AGAIN, "its worker is restarting")
        return
    try:
        await send({"type": "websocket.accept"})
        proto = uvicorn_door.websocket_protocol([getattr(send, "__self__", None)])
        sink = _Direct(RawSocket(proto), upstream) if proto is not None else _Messages(send,
                                                                                    upstream)
        stats["direct" if proto is not None else "messages"] += 1
        upstream.attach(sink)
        up = asyncio.create_task(_to_worker(upstream, receive))
        try:
            worker_end: asyncio.Future[Any] = upstream.ended
            await asyncio.wait([worker_end, up], return_when=asyncio.FIRST_COMPLETED)
        finally:
            up.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await up
        await sink.finish()
        if upstream.ended.done():  # the worker closed, or died under the socket
            ended = upstream.ended.result()
            code, reason = ended or (CLOSE_RESTART, "its worker restarted: reconnect")
            with contextlib.suppress(Exception):
                await send({"type": "websocket.close", "code": code, "reason": reason})
    finally:
        upstream.close()


async def _to_worker(upstream: WorkerSocket, receive: Receive) -> None:
    """The client's messages to the worker, until the client goes (its close passed on)."""
    while True:
        message = await receive()
        if message["type"] == "websocket.disconnect":
            code = message.get("code", CloseCode.NORMAL_CLOSURE)
            # a code an endpoint may send (websockets' own rule, `Close.check`): not 1005,
            # 1006, 1015, which only say what happened
            upstream.close(code if code in EXTERNAL_CLOSE_CODES or 3000 <= code < 5000
                           else CloseCode.NORMAL_CLOSURE)
            return
        if message.get("text") is not None:
            upstream.send(message["text"])
        elif message.get("bytes") is not None:
            upstream.send(message["bytes"])
