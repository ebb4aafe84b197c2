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

What this takes of uvicorn beyond its public `Server` and `Config` (the protocol's internals,
the signal handler) is in app/doors/uvicorn.py, and nowhere else.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import json
import logging
from typing import Any

import uvicorn

from app.doors import uvicorn as uvicorn_door

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
        coro = svc.emergency_hold() if hold else svc.stop_all(SHUTDOWN_REASON)
        futures.append(asyncio.run_coroutine_threadsafe(coro, loop))
    return futures


class ArmServer(uvicorn_door.SignalServer):
    """uvicorn.Server whose signal handling stops the arms first (see the module doc)."""

    def __init__(self, config: uvicorn.Config, app: Any) -> None:
        super().__init__(config)
        self.arm_app = app

    def first_signal(self, sig: int) -> None:
        log.warning("signal %d: stopping every arm, then shutting down (a second signal "
                    "holds the arms and exits at once)", sig)
        stop_arms(self.arm_app, hold=False)

    def shutting_down(self) -> None:
        cameras = getattr(self.arm_app.state, "cameras", None)
        if cameras is not None:
            cameras.end_streams()

    def again(self, sig: int) -> None:
        log.warning("signal %d again: holding every arm and exiting now", sig)
        futures = stop_arms(self.arm_app, hold=True)
        # Wait for the hold where the arms run on the control thread (without one they run on
        # this thread's loop, which cannot answer while we wait: the hold is only queued).
        if getattr(self.arm_app.state, "control", None) is not None:
            with contextlib.suppress(Exception):
                concurrent.futures.wait(futures, HOLD_WAIT_S)


class ArmHttpToolsProtocol(uvicorn_door.LimitedHttpToolsProtocol):
    """uvicorn's httptools protocol (a C parser: the `GET /state` of 50 keep-alive clients
    cost the server about half as much per request as through h11's pure-Python one), with
    uvicorn's connection limit answered by the API's JSON 503 `busy` with a Retry-After, and
    a bound on the request head (`max_head`, 400): the mechanics are in
    app/doors/uvicorn.py."""

    async def refuse_busy(self, send: Any, limit: int) -> None:
        await send_busy(send, limit)


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
