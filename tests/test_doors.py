"""The doors (app/doors/): the only modules that touch a library's internals, one per library.

For each: its `check()` passes on the installed version, and with one of the internals it relies
on taken away (monkeypatched) it fails with a message naming that internal, the library and its
installed version, and the version the door was checked with. And the doors do their job: a
WebSocket route under Starlette, served by uvicorn, reaches uvicorn's protocol (and does not
once compression is negotiated)."""

from __future__ import annotations

import json
import socket
from collections.abc import Callable, Iterator
from typing import Any

import aiomqtt
import paho.mqtt.client as mqtt
import pytest
import serial_asyncio
import uvicorn
from conftest import uvicorn_thread
from starlette.applications import Starlette
from starlette.middleware import Middleware
from starlette.routing import WebSocketRoute
from starlette.websockets import WebSocket
from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol
from uvicorn.protocols.websockets import auto as ws_auto
from uvicorn.protocols.websockets.websockets_sansio_impl import WebSocketsSansIOProtocol
from websockets.asyncio.client import connect

from app.doors import DoorError, installed
from app.doors import aiomqtt as aiomqtt_door
from app.doors import paho as paho_door
from app.doors import serial_asyncio as serial_door
from app.doors import starlette as starlette_door
from app.doors import uvicorn as uvicorn_door
from app.web.ws_fanout import RawSocket

DOORS: dict[str, tuple[Callable[[], None], str, str]] = {
    # door: (check, distribution, version checked)
    "uvicorn": (uvicorn_door.check, "uvicorn", uvicorn_door.CHECKED),
    "starlette": (starlette_door.check, "starlette", starlette_door.CHECKED),
    "serial_asyncio": (serial_door.check, "pyserial-asyncio", serial_door.CHECKED),
    "paho": (paho_door.check, "paho-mqtt", paho_door.CHECKED),
    "aiomqtt": (aiomqtt_door.check, "aiomqtt", aiomqtt_door.CHECKED),
}


@pytest.mark.parametrize("door", sorted(DOORS))
def test_each_door_passes_its_check_on_the_installed_version(door: str) -> None:
    check, _dist, _checked = DOORS[door]
    check()  # (a DoorError here names what the installed version lacks)


def _no_init(self: Any, *args: Any, **kwargs: Any) -> None:
    """An __init__ that sets nothing: every attribute a door expects it to set is gone."""


def _plain_send(self: Any, *args: Any, **kwargs: Any) -> None:
    """A method that touches no attribute."""


def _without(monkeypatch: pytest.MonkeyPatch, door: str) -> list[str]:
    """Take one internal of each kind away from the library behind `door`; what the door's
    message must name."""
    if door == "uvicorn":
        monkeypatch.delattr(HttpToolsProtocol, "send_400_response")
        monkeypatch.setattr(WebSocketsSansIOProtocol, "__init__", _no_init)
        monkeypatch.setattr(ws_auto, "AutoWebSocketsProtocol", None)
        return ["HttpToolsProtocol.data_received, .on_message_complete, .send_400_response",
                "WebSocketsSansIOProtocol.conn", "websockets-sansio as the default"]
    if door == "starlette":
        def init(self: WebSocket, scope: Any, receive: Any, send: Any) -> None:
            self.scope, self.receive_fn, self.send_fn = scope, receive, send  # not `_send`
        monkeypatch.setattr(WebSocket, "__init__", init)
        return ["WebSocket._send"]
    if door == "serial_asyncio":
        monkeypatch.delattr(serial_asyncio.SerialTransport, "_read_ready")
        return ["SerialTransport._read_ready"]
    if door == "paho":
        monkeypatch.setattr(mqtt.Client, "_call_socket_register_write", _plain_send)
        return ["Client._registered_write"]
    if door == "aiomqtt":
        monkeypatch.setattr(aiomqtt.Client, "__init__", _no_init)
        return ["Client._client", "Client._disconnected"]
    raise AssertionError(door)


@pytest.mark.parametrize("door", sorted(DOORS))
def test_each_door_names_a_missing_internal_and_the_library_version(
        door: str, monkeypatch: pytest.MonkeyPatch) -> None:
    check, dist, checked = DOORS[door]
    names = _without(monkeypatch, door)
    with pytest.raises(DoorError) as info:
        check()
    msg = str(info.value)
    assert f"{dist} {installed(dist)} lacks internals that app.doors.{door}" in msg, msg
    assert f"checked with {dist} {checked}" in msg, msg
    for name in names:
        assert name in msg, f"{name!r} not named in: {msg}"


def test_the_starlette_door_sees_a_wrapper_that_drops_the_send_below_it(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """A Starlette whose ExceptionMiddleware hid the `send` below it (not in its closure)."""
    import starlette.middleware.exceptions as exceptions

    class Hiding:
        def __init__(self, app: Any, *args: Any, **kwargs: Any) -> None:
            self.app = app

        async def __call__(self, scope: Any, receive: Any, send: Any) -> None:
            await self.app(scope, receive, _hidden(send))

    monkeypatch.setattr(starlette_door, "ExceptionMiddleware", Hiding)
    assert exceptions.ExceptionMiddleware is not Hiding
    with pytest.raises(DoorError, match="ExceptionMiddleware's send wrapper"):
        starlette_door.check()


def _hidden(send: Any) -> Any:
    box = {"send": send}  # the send held in a dict, out of the wrapper's closure cells

    async def sender(message: Any) -> None:
        await box["send"](message)
    return sender


# ------------------------------------------------------------------ the doors at work


class _Wrapping:
    """A pure ASGI middleware that wraps `send` in a closure, as app.web.middleware's do."""

    def __init__(self, app: Any) -> None:
        self.app = app

    async def __call__(self, scope: Any, receive: Any, send: Any) -> None:
        async def _send(message: Any) -> None:
            await send(message)
        await self.app(scope, receive, _send)


async def _endpoint(ws: WebSocket) -> None:
    await ws.accept()
    raw = RawSocket.open(ws)
    await ws.send_text(json.dumps({"raw": raw is not None,
                                   "closed": None if raw is None else raw.closed}))
    await ws.close()


@pytest.fixture
def uvicorn_on_loopback() -> Iterator[str]:
    """A Starlette app (a wrapping middleware, Starlette's own stack) under uvicorn with its
    default WebSocket protocol and permessage-deflate on; its ws:// URL."""
    app = Starlette(routes=[WebSocketRoute("/ws", _endpoint)], middleware=[Middleware(_Wrapping)])
    sock = socket.socket()
    sock.bind(("127.0.0.1", 0))
    server = uvicorn.Server(uvicorn.Config(app, log_level="warning", lifespan="off"))
    with uvicorn_thread(server, "doors-uvicorn", sockets=[sock]):
        yield f"ws://127.0.0.1:{sock.getsockname()[1]}/ws"
    sock.close()


@pytest.mark.parametrize("compression", [None, "deflate"])
async def test_a_route_reaches_uvicorns_protocol_unless_compression_was_negotiated(
        uvicorn_on_loopback: str, compression: str | None) -> None:
    async with connect(uvicorn_on_loopback, compression=compression) as ws:
        got = json.loads(await ws.recv())
    if compression is None:
        assert got == {"raw": True, "closed": False}, (
            "the doors did not reach uvicorn's websockets-sansio protocol under Starlette: "
            f"uvicorn {installed('uvicorn')}, starlette {installed('starlette')}")
    else:
        assert got == {"raw": False, "closed": None}, "compression negotiated, yet a raw socket"
