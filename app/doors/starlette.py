"""Starlette's internals: the only module that touches them.

Checked with Starlette 1.10.0 (pyproject.toml: `<1.11`). `check()` runs when this module is
imported (by `app.web.ws_fanout`).

The telemetry fan-out needs uvicorn's protocol object under a WebSocket route
(`app.doors.uvicorn`) to write its pre-built frames (1,000 clients at 30 msg/s in 29.6 % of a
core, `make bench-peers`). A Starlette `WebSocket` offers no public way to the ASGI `send` it
was given, and the middlewares between it and the server each wrap `send` in a function of
their own. Without this door every client gets a sender task of its own (more than a core at
that load); nothing else changes.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from typing import Any

from starlette.middleware.exceptions import ExceptionMiddleware
from starlette.websockets import WebSocket

from app.doors import require

CHECKED = "1.10.0"


def send_owners(ws: WebSocket, depth: int = 12) -> Iterator[object]:
    """The objects whose bound methods lie under the ASGI send `ws` was given, nearest first:
    each middleware's wrapper holds the `send` below it in its closure (Starlette's, and
    app.web.middleware's, are written so), or is a bound method whose object has a `send`;
    at the bottom is the server's own send. Walks at most `depth` wrappers.

    Internals: `WebSocket._send`; Starlette's wrappers (ExceptionMiddleware's) holding the
    `send` below them in their closures."""
    seen: set[int] = set()
    todo = [getattr(ws, "_send", None)]
    for _ in range(depth * 4):
        if not todo:
            return
        fn = todo.pop(0)
        if fn is None or id(fn) in seen:
            continue
        seen.add(id(fn))
        owner = getattr(fn, "__self__", None)
        if owner is not None:
            yield owner
        for cell in getattr(fn, "__closure__", None) or ():
            with contextlib.suppress(ValueError):  # an empty cell
                if callable(cell.cell_contents):
                    todo.append(cell.cell_contents)
        if owner is not None:
            todo.append(getattr(owner, "send", None))


def _probe_websocket() -> bool:
    """WebSocket(scope, receive, send) keeps `send` as `_send`."""

    async def receive() -> Any:
        return {}

    async def send(message: Any) -> None:
        return None

    ws = WebSocket({"type": "websocket", "path": "/", "headers": []}, receive, send)
    return getattr(ws, "_send", None) is send


def _probe_wrapper() -> bool:
    """ExceptionMiddleware hands the app below it a `send` whose closure holds its own `send`
    (run to completion without an event loop: nothing in it waits)."""
    got: list[Any] = []

    async def app(scope: Any, receive: Any, send: Any) -> None:
        got.append(send)

    async def receive() -> Any:
        return {}

    async def send(message: Any) -> None:
        return None

    coro = ExceptionMiddleware(app)({"type": "websocket", "path": "/", "headers": []},
                                    receive, send)
    try:
        coro.send(None)
    except StopIteration:
        pass
    else:
        coro.close()
        return False
    cells = (getattr(got[0], "__closure__", None) or ()) if got else ()
    return any(c.cell_contents is send for c in cells)


def check() -> None:
    """Raise app.doors.DoorError naming each internal above the installed Starlette lacks."""
    fanout = ("the telemetry fan-out cannot reach uvicorn's protocol under a WebSocket: every "
              "client gets a sender task of its own (1,000 clients at 30 msg/s: more than a core)")
    require("app.doors.starlette", "starlette", CHECKED, [
        ("WebSocket._send, the ASGI send a WebSocket was built with", _probe_websocket, fanout),
        ("ExceptionMiddleware's send wrapper holding the send below it in its closure",
         _probe_wrapper, fanout),
    ])


check()
