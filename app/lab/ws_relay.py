"""The front's WebSocket relay: the client's socket joined to one on the arm's worker.

The worker does everything a single server does with the socket (token, Host and Origin,
rate, limits, close codes 4401/4404/1008/1009/1013); the relay opens the worker's socket first
with the client's headers and query, accepts the client's once the worker accepted, and then
copies messages both ways and the close code back. Slowness passes through: while the client
does not read, the relay does not read the worker, whose bounded per-subscriber backlog then
drops and counts (`dropped`), as for a direct client. A worker that dies under the socket
closes the client's with 1012 (service restart): reconnect, its arm is back in seconds.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
from typing import TYPE_CHECKING

from starlette.types import Receive, Scope, Send
from websockets.asyncio.client import ClientConnection, unix_connect
from websockets.exceptions import ConnectionClosed, InvalidHandshake, InvalidStatus

from app.lab.headers import forwarded_headers

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


async def relay_websocket(scope: Scope, receive: Receive, send: Send,
                          worker: Worker | None) -> None:
    if (await receive())["type"] != "websocket.connect":
        return
    if worker is None or not worker.ready:
        await send({"type": "websocket.accept"})
        await send({"type": "websocket.close", "code": CLOSE_TRY_AGAIN,
                    "reason": json.dumps({"code": "link_down", "detail": "its worker is "
                                          "restarting: retry shortly"})})
        return
    host = dict(scope["headers"]).get(b"host", b"armserver").decode("latin-1")
    uri = f"ws://{host}{scope.get('raw_path', scope['path'].encode()).decode('latin-1')}"
    if scope.get("query_string"):
        uri += "?" + scope["query_string"].decode("latin-1")
    headers = [(k.decode("latin-1"), v.decode("latin-1")) for k, v in forwarded_headers(scope)
               if k not in SKIP]
    try:
        upstream = await unix_connect(str(worker.uds), uri, additional_headers=headers,
                                      user_agent_header=None, compression=None, max_size=None,
                                      ping_interval=None, open_timeout=OPEN_TIMEOUT_S)
    except InvalidStatus as exc:  # the worker refused the handshake (its Host/Origin guard)
        log.info("worker %d refused a WebSocket: %s", worker.index, exc.response.status_code)
        await send({"type": "websocket.close", "code": 1008})
        return
    except (OSError, InvalidHandshake, TimeoutError):
        await send({"type": "websocket.accept"})
        await send({"type": "websocket.close", "code": CLOSE_TRY_AGAIN,
                    "reason": '{"code":"link_down","detail":"its worker is restarting"}'})
        return
    await send({"type": "websocket.accept"})
    async with upstream:
        down = asyncio.create_task(_to_client(upstream, send))
        up = asyncio.create_task(_to_worker(upstream, receive))
        await asyncio.wait([down, up], return_when=asyncio.FIRST_COMPLETED)
        for t in (down, up):
            t.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await t


async def _to_client(upstream: ClientConnection, send: Send) -> None:
    try:
        async for message in upstream:
            if isinstance(message, str):
                await send({"type": "websocket.send", "text": message})
            else:
                await send({"type": "websocket.send", "bytes": message})
    except ConnectionClosed:
        pass
    rcvd = upstream.close_code
    if rcvd is None or rcvd == 1006:  # no close frame: the worker died under the socket
        code, reason = CLOSE_RESTART, "its worker restarted: reconnect"
    else:
        code, reason = rcvd, upstream.close_reason or ""
    with contextlib.suppress(Exception):
        await send({"type": "websocket.close", "code": code, "reason": reason})


async def _to_worker(upstream: ClientConnection, receive: Receive) -> None:
    while True:
        message = await receive()
        if message["type"] == "websocket.disconnect":
            await upstream.close()
            return
        if message.get("text") is not None:
            await upstream.send(message["text"])
        elif message.get("bytes") is not None:
            await upstream.send(message["bytes"])
