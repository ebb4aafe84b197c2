"""`armserver serve`'s uvicorn server, with a shutdown that leaves every arm still.

- First SIGTERM or SIGINT: every arm stops the way `POST /stop` does (its motion decelerates
  within the limits and the arm holds; a `wait: true` move answers `stopped`, "server shutting
  down"), no new motion is accepted (503 `shutting_down`), then uvicorn closes: connections get
  `shutdown_timeout_s` to finish, then the arms' links close.
- Second signal: the arms are told to hold where they were last commanded (bounded wait of
  `HOLD_WAIT_S`) and the process stops at once.

`ArmHttpToolsProtocol` is uvicorn's httptools protocol whose refusal over `max_connections`
(uvicorn's `limit_concurrency`) is the API's error body, 503 `{"detail", "code": "busy"}` with
a Retry-After, instead of uvicorn's plain-text "Service Unavailable", and which bounds the
request head (`max_header_bytes`).
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import json
import logging
from types import FrameType
from typing import Any

import uvicorn
from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol

log = logging.getLogger("armserver")

#: How long the second signal waits for the hold to be sent, s.
HOLD_WAIT_S = 1.0
SHUTDOWN_REASON = "server shutting down"
#: Retry-After of the 503 for a request over `max_connections`, s.
BUSY_RETRY_AFTER_S = 1


def stop_arms(app: Any, hold: bool) -> list[concurrent.futures.Future[Any]]:
    """From any thread (a signal handler included): refuse new motion on every arm and stop
    (decelerate, then hold) or, with `hold`, hold at once. The futures of those calls."""
    futures = []
    for svc in getattr(app.state, "services", {}).values():
        svc.closing = True
        loop = svc.home_loop
        if loop is None or loop.is_closed():
            continue
        coro = svc.motion.emergency_stop() if hold else _stop_for_shutdown(svc)
        futures.append(asyncio.run_coroutine_threadsafe(coro, loop))
    return futures


async def _stop_for_shutdown(svc: Any) -> list[str]:
    """`POST /stop`, with the reason the running motion ends with saying why (on the arm's
    loop)."""
    cur = svc.motion.current
    if cur is not None and cur.status == "running" and cur.reason is None:
        cur.reason = SHUTDOWN_REASON
    return list(await svc.motion.stop_all(reason=SHUTDOWN_REASON))


class ArmServer(uvicorn.Server):
    """uvicorn.Server whose signal handling stops the arms first (see the module doc)."""

    def __init__(self, config: uvicorn.Config, app: Any) -> None:
        super().__init__(config)
        self.arm_app = app

    def handle_exit(self, sig: int, frame: FrameType | None) -> None:
        if not self.should_exit:
            log.warning("signal %d: stopping every arm, then shutting down (a second signal "
                        "holds the arms and exits at once)", sig)
            stop_arms(self.arm_app, hold=False)
            super().handle_exit(sig, frame)
            return
        log.warning("signal %d again: holding every arm and exiting now", sig)
        futures = stop_arms(self.arm_app, hold=True)
        # Wait for the hold where the arms run on the control thread (without one they run on
        # this thread's loop, which cannot answer while we wait: the hold is only queued).
        if getattr(self.arm_app.state, "control", None) is not None:
            with contextlib.suppress(Exception):
                concurrent.futures.wait(futures, HOLD_WAIT_S)
        self._captured_signals.append(sig)
        self.force_exit = True


class ArmHttpToolsProtocol(HttpToolsProtocol):
    """uvicorn's httptools protocol (a C parser: the `GET /state` of 50 keep-alive clients
    cost the server about half as much per request as through h11's pure-Python one) with two
    changes.

    A request over `limit_concurrency` (connections open, or requests running, across the
    server) gets the API's JSON 503 `busy` with a Retry-After: uvicorn checks the limit inline
    and answers with its own plain-text app; here the limit is taken off uvicorn and checked
    as the request's app starts (its task is then one of `tasks`, hence `>`), before anything
    of ours runs.

    A request whose head (request line and headers) exceeds `max_head` bytes is refused with
    400 and the connection closed, after at most one more read: httptools has no such bound
    (a 64 MiB header would otherwise be gathered whole, 3.8 s of parsing before any check).
    Bytes are counted from the end of one request's head to the end of the next; the read
    that completes a head may carry body bytes too, and is not refused for them."""

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

    async def _admit(self, scope: Any, receive: Any, send: Any) -> None:
        limit = self.max_connections
        if limit is not None and (len(self.connections) >= limit or len(self.tasks) > limit):
            self.logger.warning("over max_connections (%d): 503 busy", limit)
            await send_busy(send, limit)
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


async def send_busy(send: Any, limit: int) -> None:
    """The 503 `busy` answer for a request over `max_connections` (ASGI)."""
    body = json.dumps({"detail": f"the server has {limit} connections open, its limit "
                                 "(max_connections): retry later", "code": "busy"}).encode()
    await send({"type": "http.response.start", "status": 503,
                "headers": [(b"content-type", b"application/json"),
                            (b"content-length", str(len(body)).encode()),
                            (b"retry-after", str(BUSY_RETRY_AFTER_S).encode()),
                            (b"connection", b"close")]})
    await send({"type": "http.response.body", "body": body, "more_body": False})
