"""The front's WebSocket relay (app/lab/ws_relay.py) between two real uvicorn servers.

A "worker" (uvicorn on a Unix socket, a Starlette app whose sockets each do one thing) and a
"front" (uvicorn on a loopback port, its app the relay to that worker) run on one loop in a
thread of their own, as a lab's processes would; the client is `websockets` on the test's loop.
The worker pings every 50 ms and closes a socket whose pong does not come in 2 s, so a relay
that did not answer its pings would lose a socket kept open longer.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import socket
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest
import uvicorn
from _wait import wait_for
from starlette.applications import Starlette
from starlette.routing import WebSocketRoute
from starlette.websockets import WebSocket, WebSocketDisconnect
from websockets.asyncio.client import connect
from websockets.exceptions import ConnectionClosed, InvalidStatus

from app.lab import ws_relay
from app.lab.supervisor import Worker
from app.web.ws_fanout import RawSocket

#: The worker's keepalive: a ping this often, the socket closed (1011) if no pong in PONG_S
#: (long enough for a loaded machine's stalls; the ping test watches a socket for longer).
PING_S = 0.05
PONG_S = 2.0
FLOOD_MESSAGE = 64 * 1024


@dataclass
class WorkerState:
    """What the worker's sockets saw."""

    received: list[Any] = field(default_factory=list)
    close_codes: list[int] = field(default_factory=list)
    flooded: int = 0


def worker_app(state: WorkerState) -> Starlette:
    async def echo(ws: WebSocket) -> None:
        await ws.accept()
        await ws.send_text("hello")
        await ws.send_bytes(b"\x00\x01\xff")
        await ws.send_text("é" * 40_000)  # (a 16-bit length, and text in more than one read)
        while True:
            message = await ws.receive()
            if message["type"] == "websocket.disconnect":
                state.close_codes.append(message.get("code", 0))
                return
            state.received.append(message.get("text") or message.get("bytes"))
            if message.get("text") is not None:
                await ws.send_text(message["text"])
            else:
                await ws.send_bytes(message["bytes"])

    async def close(ws: WebSocket) -> None:
        await ws.accept()
        await ws.send_text("bye")
        await ws.close(4404, "nope")

    async def refuse(ws: WebSocket) -> None:
        await ws.close(1008)  # before accepting: uvicorn answers the handshake 403

    async def tick(ws: WebSocket) -> None:
        await ws.accept()
        with contextlib.suppress(WebSocketDisconnect, RuntimeError):
            for i in range(1_000_000):
                await ws.send_text(str(i))
                await asyncio.sleep(0.005)

    async def flood(ws: WebSocket) -> None:
        await ws.accept()
        with contextlib.suppress(WebSocketDisconnect, RuntimeError):
            while True:
                await ws.send_bytes(b"x" * FLOOD_MESSAGE)
                state.flooded += 1
                # A turn of the loop between sends: uvicorn's send on a transport that has
                # lost its connection neither raises nor waits until `connection_lost` has run
                # (a callback of a later turn), so a loop of sends that never waited spun here
                # for the rest of the test process at the servers' shutdown, its thread
                # outliving the fixture, and asyncio logged "socket.send() raised exception."
                # at each send into every later test's captured log (session 31).
                await asyncio.sleep(0)

    async def die(ws: WebSocket) -> None:
        await ws.accept()
        await ws.send_text("going")
        raw = RawSocket.open(ws)
        assert raw is not None
        raw.transport.abort()  # gone without a close frame, as a killed process
        with contextlib.suppress(WebSocketDisconnect):
            await ws.receive()

    return Starlette(routes=[WebSocketRoute(f"/{f.__name__}", f)
                             for f in (echo, close, refuse, tick, flood, die)])


@dataclass
class Relay:
    url: str
    state: WorkerState


def _serve(front_deflate: bool, folder: Path, ping: bool = True) -> Iterator[Relay]:
    state = WorkerState()
    uds = folder / "worker.sock"
    worker = Worker(0, ("a",), uds, client=None, ready=True)  # type: ignore[arg-type]
    # a worker whose socket is not there (it died, and its restart has not listened yet)
    gone = Worker(1, ("b",), folder / "gone.sock", client=None, ready=True)  # type: ignore[arg-type]

    async def front(scope: Any, receive: Any, send: Any) -> None:
        assert scope["type"] == "websocket"
        await ws_relay.relay_websocket(scope, receive, send,
                                       gone if scope["path"] == "/gone" else worker)

    sock = socket.socket()
    sock.bind(("127.0.0.1", 0))
    port = sock.getsockname()[1]
    servers = [
        uvicorn.Server(uvicorn.Config(worker_app(state), uds=str(uds), lifespan="off",
                                      log_level="warning",
                                      ws_ping_interval=PING_S if ping else None,
                                      ws_ping_timeout=PONG_S, ws_per_message_deflate=False)),
        uvicorn.Server(uvicorn.Config(front, lifespan="off", log_level="warning",
                                      ws_ping_interval=None,
                                      ws_per_message_deflate=front_deflate))]
    box: dict[str, asyncio.AbstractEventLoop] = {}

    def run() -> None:
        async def main() -> None:
            box["loop"] = asyncio.get_running_loop()
            await asyncio.gather(servers[0].serve(), servers[1].serve(sockets=[sock]))
        asyncio.run(main())

    thread = threading.Thread(target=run, name="relay-servers", daemon=True)
    thread.start()
    deadline = time.monotonic() + 30
    while not all(s.started for s in servers):
        assert thread.is_alive() and time.monotonic() < deadline, "the servers did not start"
        time.sleep(0.01)
    try:
        yield Relay(f"ws://127.0.0.1:{port}", state)
    finally:
        for s in servers:
            s.should_exit = True
        thread.join(30)
        assert not thread.is_alive(), "the servers' thread outlived the test"


@pytest.fixture
def relay(tmp_path: Path) -> Iterator[Relay]:
    yield from _serve(False, tmp_path)


@pytest.fixture
def quiet_relay(tmp_path: Path) -> Iterator[Relay]:
    """No keepalive: a client that does not read does not answer a ping either (through the
    front or not), and the worker would close its socket."""
    yield from _serve(False, tmp_path, ping=False)


@pytest.fixture
def deflate_relay(tmp_path: Path) -> Iterator[Relay]:
    yield from _serve(True, tmp_path)


async def _echo_both_ways(relay: Relay, compression: str | None) -> None:
    async with connect(relay.url + "/echo", compression=compression, max_size=None) as ws:
        assert await ws.recv() == "hello"
        assert await ws.recv() == b"\x00\x01\xff"
        assert await ws.recv() == "é" * 40_000
        await ws.send("ping?")
        assert await ws.recv() == "ping?"
        await ws.send(b"\x07" * 70_000)  # (a 64-bit length)
        assert await ws.recv() == b"\x07" * 70_000
        await ws.close(4000, "done")
    await wait_for(lambda: relay.state.close_codes, what="the worker told of the close")
    assert relay.state.received == ["ping?", b"\x07" * 70_000]
    assert relay.state.close_codes == [4000]  # the client's own code


async def test_messages_cross_both_ways_as_they_were_written(relay: Relay) -> None:
    before = dict(ws_relay.stats)
    await _echo_both_ways(relay, None)
    assert ws_relay.stats["direct"] == before["direct"] + 1  # frames written as they came
    assert ws_relay.stats["messages"] == before["messages"]


async def test_a_client_that_negotiated_compression_gets_whole_messages(
        deflate_relay: Relay) -> None:
    before = dict(ws_relay.stats)
    await _echo_both_ways(deflate_relay, "deflate")
    assert ws_relay.stats["messages"] == before["messages"] + 1
    assert ws_relay.stats["direct"] == before["direct"]


async def test_the_workers_close_code_and_reason_reach_the_client(relay: Relay) -> None:
    async with connect(relay.url + "/close") as ws:
        assert await ws.recv() == "bye"
        with pytest.raises(ConnectionClosed) as closed:
            await ws.recv()
    assert closed.value.rcvd is not None
    assert (closed.value.rcvd.code, closed.value.rcvd.reason) == (4404, "nope")


async def test_a_handshake_the_worker_refuses_is_refused(relay: Relay) -> None:
    with pytest.raises(InvalidStatus) as refused:
        async with connect(relay.url + "/refuse"):
            pass
    assert refused.value.response.status_code == 403


async def test_the_workers_pings_are_answered_by_the_relay(relay: Relay) -> None:
    """Past the worker's pong timeout (some 40 pings) the stream goes on, every message in
    order."""
    async with connect(relay.url + "/tick", ping_interval=None) as ws:
        got = [int(await asyncio.wait_for(ws.recv(), 10))]
        t0 = time.monotonic()
        while time.monotonic() - t0 < PING_S + PONG_S + 0.5:
            got.append(int(await asyncio.wait_for(ws.recv(), 10)))
    assert got == list(range(got[0], got[0] + len(got)))
    assert len(got) > 20


async def test_a_worker_that_cannot_be_reached_is_try_again_later(relay: Relay) -> None:
    async with connect(relay.url + "/gone") as ws:
        with pytest.raises(ConnectionClosed) as closed:
            await asyncio.wait_for(ws.recv(), 10)
    assert closed.value.rcvd is not None
    assert closed.value.rcvd.code == ws_relay.CLOSE_TRY_AGAIN
    assert json.loads(closed.value.rcvd.reason)["code"] == "link_down"


async def test_a_worker_gone_under_the_socket_closes_it_service_restart(relay: Relay) -> None:
    async with connect(relay.url + "/die") as ws:
        assert await ws.recv() == "going"
        with pytest.raises(ConnectionClosed) as closed:
            await asyncio.wait_for(ws.recv(), 10)
    assert closed.value.rcvd is not None and closed.value.rcvd.code == ws_relay.CLOSE_RESTART


async def test_a_client_that_does_not_read_holds_the_worker_back(quiet_relay: Relay) -> None:
    """The worker writes 64 KiB messages as fast as its socket takes them; the client reads
    none for a while. The relay stops reading the worker once the client's transport holds
    SLOW_CLIENT_BYTES, so the worker's writes stall: what it got out is bounded by the
    buffers on the way (the kernel's, a few MB here), not by time; then the client reads
    and the stream goes on."""
    async with connect(quiet_relay.url + "/flood", max_size=None) as ws:
        assert len(await ws.recv()) == FLOOD_MESSAGE
        await asyncio.sleep(0)

        def stalled() -> bool:  # no message out of the worker for 0.3 s
            n = quiet_relay.state.flooded
            time.sleep(0.3)
            return quiet_relay.state.flooded == n

        await wait_for(lambda: asyncio.to_thread(stalled), what="the worker held back")
        held = quiet_relay.state.flooded
        # bounded: the client's queue and socket, the front's transport (SLOW_CLIENT_BYTES
        # and what one read brings), the two sockets' kernel buffers
        assert held * FLOOD_MESSAGE < 64 * 1024 * 1024, held
        for _ in range(held + 10):
            assert len(await asyncio.wait_for(ws.recv(), 10)) == FLOOD_MESSAGE
        assert quiet_relay.state.flooded > held
        # gone without a close (a client holding unread messages waits its close timeout for
        # the server's close frame behind them)
        ws.transport.abort()
