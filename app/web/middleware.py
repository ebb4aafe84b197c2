"""The raw ASGI middlewares of the app (app/web/factory.py installs them): the last resort for bugs
(502 `internal_error`, never a 500), the request body limit (413 `too_large`) and the token
gate (401 `unauthorized` before a body is read). Each answers with `send_error`, the one JSON
error writer (app/web/error_responses.py). And `HeadAsGet`, outermost, here and around a lab's
front (app/lab/serve.py): HEAD answered as GET is, without the body.
"""

from __future__ import annotations

import logging
from typing import Any

from starlette.types import ASGIApp, Message, Receive, Scope, Send

from app import schemas as s
from app.errors import Unauthorized
from app.web.error_responses import send_error
from app.web.security import Access, bearer_token_of

log = logging.getLogger("armserver")

API_PREFIX = s.API_PREFIX


class InternalErrors:
    """Last resort for bugs: log with traceback, count, answer 502 `internal_error` (if the
    response has not started). Fix the cause; tests assert the count stays 0."""

    def __init__(self, app: ASGIApp, app_ref: Any) -> None:
        self.app = app
        self.ref = app_ref

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] not in ("http", "websocket"):
            await self.app(scope, receive, send)
            return
        started = False

        async def _send(message: Message) -> None:
            nonlocal started
            if message["type"] in ("http.response.start", "websocket.accept"):
                started = True
            await send(message)

        try:
            await self.app(scope, receive, _send)
        except Exception:
            self.ref.state.internal_errors += 1
            log.exception("internal error on %s %s", scope.get("method", "WS"), scope.get("path"))
            if scope["type"] == "http" and not started:
                await send_error(send, 502, "internal error (logged); please report it",
                                 "internal_error")


class BodyLimit:
    """413 `too_large` for a request body over `max_bytes`, declared or streamed. The body is
    read here (it is small by definition) and replayed to the app."""

    def __init__(self, app: ASGIApp, max_bytes: int) -> None:
        self.app = app
        self.max_bytes = max_bytes

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        declared = dict(scope.get("headers", ())).get(b"content-length")
        if declared is not None:
            try:
                if int(declared) > self.max_bytes:
                    await self._too_large(send)
                    return
            except ValueError:
                pass
        chunks: list[bytes] = []
        size = 0
        while True:
            message = await receive()
            if message["type"] != "http.request":  # disconnect: let the app see it
                chunks = []
                replay: Message | None = message
                break
            size += len(message.get("body", b""))
            if size > self.max_bytes:
                await self._too_large(send)
                return
            chunks.append(message.get("body", b""))
            if not message.get("more_body", False):
                replay = None
                break
        body = b"".join(chunks)
        sent = False

        async def _receive() -> Message:
            nonlocal sent
            if replay is not None:
                return replay
            if not sent:
                sent = True
                return {"type": "http.request", "body": body, "more_body": False}
            return await receive()

        await self.app(scope, _receive, send)

    async def _too_large(self, send: Send) -> None:
        await send_error(send, 413, f"request body over {self.max_bytes} bytes", "too_large")


class TokenGate:
    """401 `unauthorized` for an API request with no valid token, before the body is read or
    parsed: without it a malformed body would answer 422 to a client that may not even ask.
    Roles (403) stay with the routes' dependencies; health, docs and the dashboard are open;
    WebSockets check their token (header or `?token=`) in their route."""

    def __init__(self, app: ASGIApp, access: Access) -> None:
        self.app = app
        self.access = access

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        path = scope.get("path", "")
        if (scope["type"] != "http" or not self.access.enabled or scope.get("method") == "OPTIONS"
                or not path.startswith(API_PREFIX + "/") or path == API_PREFIX + "/health"):
            await self.app(scope, receive, send)
            return
        header = dict(scope.get("headers", ())).get(b"authorization")
        token = bearer_token_of(header)
        if self.access.role_of(token) is not None:
            await self.app(scope, receive, send)
            return
        # the very answer the routes give (`Access.require` through the ArmError handler):
        # same detail, same serializer, same headers, byte for byte
        exc = Unauthorized("missing bearer token" if not token else "invalid bearer token")
        await send_error(send, exc.status_code, exc.detail, exc.code,
                         {"WWW-Authenticate": "Bearer"})


class HeadAsGet:
    """HEAD answered as GET would be, without the body: "The HEAD method is identical to GET
    except that the server MUST NOT send content in the response", and a general-purpose
    server supports both (RFC 9110 9.1, 9.3.2); FastAPI's GET routes answered HEAD with 405.
    The request goes on as a GET (every gate and limit as for one; the audit log records GET,
    uvicorn's access log HEAD). Its answer ends at its head: the status and headers (the length
    a GET's body would have) are sent with an empty, last body; what the app sends after is
    dropped, and it is told the client has gone, so that a stream (MJPEG) ends there rather
    than feeding a connection no body may be sent on."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or scope["method"] != "HEAD":
            return await self.app(scope, receive, send)
        ended = False

        async def head_only(message: Message) -> None:
            nonlocal ended
            if ended:
                return
            if message["type"] == "http.response.start":
                await send(message)
                await send({"type": "http.response.body", "body": b"", "more_body": False})
                ended = True

        async def gone_once_ended() -> Message:
            if ended:
                return {"type": "http.disconnect"}
            return await receive()

        await self.app({**scope, "method": "GET"}, gone_once_ended, head_only)
