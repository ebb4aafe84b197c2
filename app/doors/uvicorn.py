"""uvicorn's internals: the only module that touches them.

Checked with uvicorn 0.54.0 (pyproject.toml: `>=0.50,<0.55`). `check()` runs when this module is
imported (by `app.web.serving` and `app.web.ws_fanout`) and names any internal a uvicorn
version lacks, instead of letting the server lose a figure or a limit silently.

- The telemetry fan-out writes frames of its own to the transport under uvicorn's
  websockets-sansio protocol (`websocket_protocol`, `ws_transport`, `ws_closed`): one task
  and one built frame for every client of an arm at a rate. The lab front's WebSocket relay
  (app/lab/ws_relay.py) writes a worker's frames there the same way, as they come. uvicorn
  has no public way to write a pre-built frame, and a `send_text` per client per message
  cost more than a core at 1,000 clients and 30 msg/s (`make bench-peers`: 29.6 % of a core
  with this door).
- `LimitedHttpToolsProtocol`: uvicorn's httptools protocol (a C parser: the REST figure of
  `make bench-peers`, about twice h11's) with what uvicorn's options do not give with it: a
  bound on the request head (httptools has none; h11's `h11_max_incomplete_event_size` is
  h11's only) and the API's JSON 503 `busy` over `limit_concurrency` (uvicorn answers its own
  plain-text one, inline).
- `SignalServer`: a hook on each exit signal before uvicorn's own handling (the arms stop
  before the connections close; a second signal forces the exit).
"""

from __future__ import annotations

import asyncio
import inspect
import socket
from collections.abc import Iterable
from types import FrameType
from typing import Any

import uvicorn
from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol
from uvicorn.protocols.websockets import auto as ws_auto
from uvicorn.protocols.websockets.websockets_sansio_impl import WebSocketsSansIOProtocol

from app.doors import require, uses

CHECKED = "0.54.0"

# ------------------------------------------------------------------ WebSocket: direct writes


def websocket_protocol(owners: Iterable[object]) -> WebSocketsSansIOProtocol | None:
    """uvicorn's websockets-sansio protocol among `owners` (the objects whose bound methods lie
    under an ASGI `send`: `app.doors.starlette.send_owners`), if frames built elsewhere may be
    written to its transport: the handshake is complete and no extension was negotiated
    (permessage-deflate frames need the library). None otherwise: another protocol (wsproto,
    the legacy websockets one), another server (the test client), compression.

    Internals: the ASGI send uvicorn hands the app is the protocol's bound method `send`; the
    protocol's `conn`, `transport`, `handshake_complete` and `response` (the handshake's answer,
    whose `Sec-WebSocket-Extensions` header says what was negotiated)."""
    for owner in owners:
        if hasattr(owner, "conn") and hasattr(owner, "transport"):
            break
    else:
        return None
    if not isinstance(owner, WebSocketsSansIOProtocol) or owner.transport is None:
        return None
    if not owner.handshake_complete:
        return None  # not accepted yet
    response = getattr(owner, "response", None)
    if response is None or "Sec-WebSocket-Extensions" in response.headers:
        return None  # compression negotiated: frames need the library
    return owner


def ws_transport(proto: WebSocketsSansIOProtocol) -> asyncio.Transport:
    """The transport under `proto` (internal: the protocol's `transport`)."""
    return proto.transport


def ws_closed(proto: WebSocketsSansIOProtocol) -> bool:
    """Whether `proto` has sent a close frame or lost its connection (internals:
    `close_sent`, `disconnected`): no frame of ours may follow."""
    return proto.close_sent or proto.disconnected


# ------------------------------------------------------------------ HTTP: limits


class LimitedHttpToolsProtocol(HttpToolsProtocol):
    """uvicorn's httptools protocol with two changes; `refuse_busy` (a subclass's) answers.

    A request over `limit_concurrency` (connections open, or requests running, across the
    server) is handed to `refuse_busy`: uvicorn checks the limit inline and answers with its
    own plain-text app; here the limit is taken off uvicorn and checked as the request's app
    starts (its task is then one of `tasks`, hence `>`), before anything of the app runs.

    A request whose head (request line and headers) exceeds `max_head` bytes is refused with
    400 and the connection closed, after at most one more read: httptools has no such bound
    (a 64 MiB header would otherwise be gathered whole, 3.8 s of parsing before any check).
    Bytes are counted from the end of one request's head to the end of the next; the read
    that completes a head may carry body bytes too, and is not refused for them.

    Internals: the constructor's signature; the attributes `limit_concurrency`, `app`,
    `connections`, `tasks`, `logger`, `transport`; the parser callbacks `on_headers_complete`
    (where uvicorn reads `limit_concurrency` and starts `app`) and `on_message_complete`;
    `send_400_response`."""

    def __init__(self, config: uvicorn.Config, server_state: Any, app_state: dict[str, Any],
                 _loop: asyncio.AbstractEventLoop | None = None, *,
                 max_head: int = 32 * 1024) -> None:
        super().__init__(config, server_state, app_state, _loop)
        self.max_connections, self.limit_concurrency = self.limit_concurrency, None
        self._inner_app = self.app
        self.app = self._admit
        self.max_head = max_head
        self._head_bytes = 0
        self._in_body = False

    async def refuse_busy(self, send: Any, limit: int) -> None:
        """Answer a request over `max_connections` (ASGI `send`)."""
        raise NotImplementedError

    async def _admit(self, scope: Any, receive: Any, send: Any) -> None:
        limit = self.max_connections
        if limit is not None and (len(self.connections) >= limit or len(self.tasks) > limit):
            self.logger.warning("over max_connections (%d): 503 busy", limit)
            await self.refuse_busy(send, limit)
            return
        await self._inner_app(scope, receive, send)

    def data_received(self, data: bytes) -> None:
        if not self._in_body:
            self._head_bytes += len(data)
        super().data_received(data)
        over = not self._in_body and self._head_bytes > self.max_head
        if over and not self.transport.is_closing():
            self.logger.warning("request head over %d bytes: 400", self.max_head)
            self.send_400_response("Request head too large.")

    def on_headers_complete(self) -> None:
        self._in_body, self._head_bytes = True, 0
        super().on_headers_complete()

    def on_message_complete(self) -> None:
        self._in_body = False
        super().on_message_complete()


# ------------------------------------------------------------------ signals


class SignalServer(uvicorn.Server):
    """uvicorn.Server that calls `first_signal` before uvicorn starts its graceful shutdown,
    and on a signal during it `again` and then a forced exit (uvicorn forces only on a second
    SIGINT, and stops waiting for connections and tasks once `force_exit` is set).

    Internals: `handle_exit(sig, frame)` as the signal handler, `should_exit`, `force_exit`;
    `shutdown(sockets)`, awaited on the server's loop before it waits for connections."""

    def first_signal(self, sig: int) -> None:
        """The first SIGTERM or SIGINT, before uvicorn's graceful shutdown starts."""

    def again(self, sig: int) -> None:
        """A signal during the graceful shutdown, before the forced exit."""

    def shutting_down(self) -> None:
        """uvicorn's shutdown starts (a signal or `should_exit`), before it waits for the open
        connections: end what never ends by itself (a streamed response)."""

    async def shutdown(self, sockets: list[socket.socket] | None = None) -> None:
        self.shutting_down()
        await super().shutdown(sockets)

    def handle_exit(self, sig: int, frame: FrameType | None) -> None:
        if not self.should_exit:
            self.first_signal(sig)
            super().handle_exit(sig, frame)
            return
        self.again(sig)
        super().handle_exit(sig, frame)  # (uvicorn records the signal, re-raised at the end)
        self.force_exit = True


# ------------------------------------------------------------------ the check


def _init_params(cls: type) -> list[str]:
    return list(inspect.signature(cls).parameters)


def check() -> None:
    """Raise app.doors.DoorError naming each internal above the installed uvicorn lacks."""
    ws, http, server = WebSocketsSansIOProtocol, HttpToolsProtocol, uvicorn.Server
    fanout = ("the telemetry fan-out cannot write its frames: every WebSocket client needs a "
              "sender task of its own (1,000 clients at 30 msg/s: more than a core)")
    require("app.doors.uvicorn", "uvicorn", CHECKED, [
        ("websockets-sansio as the default WebSocket protocol (protocols.websockets.auto)",
         lambda: ws_auto.AutoWebSocketsProtocol is ws, fanout),
        ("WebSocketsSansIOProtocol.send, the ASGI send run_asgi hands the app",
         lambda: callable(ws.send) and uses(ws.run_asgi, "app", "send"), fanout),
        ("WebSocketsSansIOProtocol.conn, .transport, .handshake_complete, .close_sent, "
         ".disconnected", lambda: uses(ws.__init__, "conn", "transport", "handshake_complete",
                                       "close_sent", "disconnected"), fanout),
        ("WebSocketsSansIOProtocol.response (the handshake's answer, set by handle_connect)",
         lambda: uses(ws.handle_connect, "response"),
         "a negotiated extension cannot be seen: " + fanout),
        ("HttpToolsProtocol(config, server_state, app_state, _loop)",
         lambda: _init_params(http)[:4] == ["config", "server_state", "app_state", "_loop"],
         "the server cannot start (the `http` protocol cannot be built)"),
        ("HttpToolsProtocol.app, .limit_concurrency, .connections, .tasks, .logger, .transport",
         lambda: uses(http.__init__, "app", "limit_concurrency", "connections", "tasks",
                      "logger", "transport"),
         "no JSON 503 `busy` over max_connections (uvicorn's plain-text one, or none)"),
        ("HttpToolsProtocol.on_headers_complete reading .limit_concurrency and starting .app",
         lambda: uses(http.on_headers_complete, "limit_concurrency", "app"),
         "max_connections is not enforced, or not by the API's 503 `busy`"),
        ("HttpToolsProtocol.data_received, .on_message_complete, .send_400_response",
         lambda: all(callable(getattr(http, n, None))
                     for n in ("data_received", "on_message_complete", "send_400_response")),
         "no bound on a request's head (a 64 MiB header parsed whole: 3.8 s)"),
        ("Server.shutdown(sockets), run on the server's loop before it waits for connections",
         lambda: (inspect.iscoroutinefunction(server.shutdown)
                  and list(inspect.signature(server.shutdown).parameters) == ["self", "sockets"]),
         "a streamed response (a camera's MJPEG) holds a shutdown for its whole graceful "
         "timeout"),
        ("Server.handle_exit(sig, frame), .should_exit, .force_exit",
         lambda: (list(inspect.signature(server.handle_exit).parameters) == ["self", "sig",
                                                                             "frame"]
                  and uses(server.__init__, "should_exit", "force_exit")),
         "a shutdown signal no longer stops the arms first, or a second one does not force "
         "the exit"),
    ])


check()
