"""The front's connections to a worker (app/lab/upstream.py, issue 27): a kept-alive connection
the worker closed is never used for a request, and an estop press is sent again on a new
connection when the one it went out on turns out broken (a release is not).

The worker here is a small HTTP/1.1 server on a Unix socket that closes connections the way
uvicorn does (idle ones after its keep-alive timeout, and, for the broken case, one that it
drops as a request comes in), so that each case happens when the test says and not by chance.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
from collections.abc import AsyncIterator
from pathlib import Path

import pytest
from _wait import wait_for

from app.lab.front import _press
from app.lab.upstream import IDLE_MAX_S, Upstream, UpstreamError


class Worker:
    """Answers each request `{"n": <requests so far>}`; `close_idle`: closes a connection
    right after answering on it (a keep-alive timeout run out at once); `drop_second`: drops a
    connection, unanswered, when a second request comes on it."""

    def __init__(self, close_idle: bool = False, drop_second: bool = False) -> None:
        self.close_idle = close_idle
        self.drop_second = drop_second
        self.requests: list[tuple[str, str]] = []
        self.connections = 0

    async def serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.connections += 1
        served = 0
        try:
            while True:
                head = await reader.readuntil(b"\r\n\r\n")
                lines = head.decode("latin-1").split("\r\n")
                method, target, _ = lines[0].split(" ", 2)
                length = next((int(line.split(":", 1)[1]) for line in lines[1:]
                               if line.lower().startswith("content-length:")), 0)
                await reader.readexactly(length)
                if self.drop_second and served == 1:
                    return  # dropped with the request unanswered
                served += 1
                self.requests.append((method, target))
                body = json.dumps({"n": len(self.requests)}).encode()
                writer.write(b"HTTP/1.1 200 OK\r\ncontent-type: application/json\r\n"
                             b"content-length: " + str(len(body)).encode() + b"\r\n\r\n" + body)
                await writer.drain()
                if self.close_idle:
                    return
        except (asyncio.IncompleteReadError, ConnectionError):
            pass
        finally:
            writer.close()


@contextlib.asynccontextmanager
async def serving(tmp_path: Path, worker: Worker) -> AsyncIterator[Upstream]:
    uds = tmp_path / "worker.sock"
    server = await asyncio.start_unix_server(worker.serve, str(uds))
    up = Upstream(uds, keepalive=4)
    try:
        yield up
    finally:
        await up.aclose()
        server.close()
        await server.wait_closed()


async def answer(up: Upstream, method: str, target: str, retry: bool | None = None) -> int:
    r = await up.request(method, target, [(b"host", b"localhost")], retry=retry)
    n: int = json.loads(await r.read())["n"]
    assert r.status_code == 200
    return n


async def test_a_connection_the_worker_closed_while_idle_is_not_used_again(
        tmp_path: Path) -> None:
    worker = Worker(close_idle=True)
    async with serving(tmp_path, worker) as up:
        assert await answer(up, "GET", "/api/v1/health") == 1
        # the connection is back in the pool, and the worker has closed it (its keep-alive)
        await wait_for(lambda: up._idle and up._idle[-1][0][0].at_eof(),
                       what="the worker's end of the idle connection")
        # a press is no GET: on that connection it would fail (503 through the front)
        assert await answer(up, "POST", "/api/v1/arms/a/estop", retry=False) == 2
        assert worker.requests[-1] == ("POST", "/api/v1/arms/a/estop")
        assert worker.connections == 2


async def test_a_connection_idle_as_long_as_the_workers_keepalive_is_not_taken(
        tmp_path: Path) -> None:
    worker = Worker()
    async with serving(tmp_path, worker) as up:
        assert await answer(up, "GET", "/api/v1/health") == 1
        (conn, since), = up._idle
        up._idle[0] = (conn, since - IDLE_MAX_S)  # as if it had waited IDLE_MAX_S
        assert await answer(up, "POST", "/api/v1/arms/a/estop", retry=False) == 2
        assert worker.connections == 2 and conn[1].is_closing()


async def test_a_press_goes_again_on_a_new_connection_when_its_own_breaks(
        tmp_path: Path) -> None:
    worker = Worker(drop_second=True)
    async with serving(tmp_path, worker) as up:
        assert await answer(up, "GET", "/api/v1/health") == 1
        # the pooled connection is dropped as the press comes: sent again, answered once
        assert await answer(up, "POST", "/api/v1/arms/a/estop", retry=True) == 2
        assert worker.requests == [("GET", "/api/v1/health"), ("POST", "/api/v1/arms/a/estop")]
        # a release is not sent twice: the caller hears of the failure
        with pytest.raises(UpstreamError):
            await up.request("DELETE", "/api/v1/arms/a/estop", [(b"host", b"localhost")])
        assert worker.requests[-1] == ("POST", "/api/v1/arms/a/estop")


@pytest.mark.parametrize(("method", "path", "again"), [
    ("POST", "/api/v1/arms/left/estop", True),
    ("DELETE", "/api/v1/arms/left/estop", False),  # a second release could undo a press
    ("POST", "/api/v1/arms/left/stop", False),
    ("POST", "/api/v1/arms/left/move/joints", False),
    ("POST", "/api/v1/teleop/estop", False),
])
def test_only_an_estop_press_is_one_the_front_may_send_twice(method: str, path: str,
                                                              again: bool) -> None:
    assert _press({"type": "http", "method": method, "path": path}) is again


def test_a_kept_press_is_one_per_arm_and_token_bounded_and_forgotten_after_a_while(
        tmp_path: Path) -> None:
    """`Worker.keep_press` (app/lab/supervisor.py): the same press twice is kept once; another
    arm's or another token's is kept beside it; MAX_KEPT_PRESSES at most; one older than
    KEEP_PRESS_S is dropped."""
    from app.lab import supervisor

    w = supervisor.Worker(1, ("a", "b"), tmp_path / "w.sock",
                          Upstream(tmp_path / "w.sock", 1))
    a, b = "/api/v1/arms/a/estop", "/api/v1/arms/b/estop"
    tok = [(b"host", b"lab"), (b"authorization", b"Bearer t1")]
    other = [(b"host", b"lab"), (b"authorization", b"Bearer t2")]
    assert w.keep_press(a, tok) and w.keep_press(a, tok)
    assert [p.target for p in w.kept] == [a]
    assert w.keep_press(b, tok) and w.keep_press(a, other) and w.keep_press(a, [])
    assert [(p.target, dict(p.headers).get(b"authorization")) for p in w.kept] == [
        (a, b"Bearer t1"), (b, b"Bearer t1"), (a, b"Bearer t2"), (a, None)]
    for k in range(supervisor.MAX_KEPT_PRESSES - 4):
        assert w.keep_press(a, [(b"authorization", f"Bearer x{k}".encode())])
    assert not w.keep_press(b, other)  # full
    assert len(w.kept) == supervisor.MAX_KEPT_PRESSES
    later = w.kept[-1].at + supervisor.KEEP_PRESS_S + 1
    assert w.keep_press(b, other, now=later)  # the old ones forgotten
    assert [(p.target, p.headers) for p in w.kept] == [(b, other)]
