"""Limits on what one client can make the server do (issue 11, item 2), over a real uvicorn
server on loopback with the same HTTP options as `armserver serve` (`app.cli.http_limits`):
a request head over `max_header_bytes` is refused without parsing the rest, connections over
`max_connections` get the API's JSON 503 `busy` with a Retry-After, and telemetry subscribers
over the per-arm or total limit are closed with 1013 and a JSON reason whose code is `busy`."""

from __future__ import annotations

import asyncio
import contextlib
import json
import socket

import pytest
from _wait import wait_until
from conftest import make_settings, serve_live
from websockets.asyncio.client import connect
from websockets.exceptions import ConnectionClosed

from tests._http import HTTP

WS = "/api/v1/arms/{arm}/telemetry"


def _raw_request(port: int, head: bytes, chunk: int = 1 << 20) -> bytes:
    """Send `head` (possibly huge) on a raw socket; whatever the server answers."""
    with socket.create_connection(("127.0.0.1", port), timeout=10) as sock:
        with contextlib.suppress(OSError):  # the server may close before all is sent
            for i in range(0, len(head), chunk):
                sock.sendall(head[i:i + chunk])
        out = b""
        with contextlib.suppress(OSError):
            while True:
                data = sock.recv(65536)
                if not data:
                    break
                out += data
        return out


def test_a_huge_header_is_refused_after_max_header_bytes() -> None:
    with serve_live(make_settings(max_header_bytes=16 * 1024)) as live:
        port = int(live.url.rsplit(":", 1)[1])
        head = (b"GET /api/v1/health HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Big: "
                + b"a" * (8 << 20) + b"\r\n\r\n")
        answer = _raw_request(port, head)
        assert answer.startswith(b"HTTP/1.1 400"), answer[:200]
        # A head under the limit is served as usual.
        ok = _raw_request(port, b"GET /api/v1/health HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Small: "
                          + b"a" * 8000 + b"\r\nConnection: close\r\n\r\n")
        assert ok.startswith(b"HTTP/1.1 200"), ok[:200]


def test_the_head_limit_counts_heads_not_bodies_nor_earlier_requests() -> None:
    """The bound is on each request head: a body sent in the same write as its head, and many
    keep-alive requests on one connection, are not counted against it."""
    with serve_live(make_settings(max_header_bytes=4 * 1024)) as live:
        port = int(live.url.rsplit(":", 1)[1])
        body = b'{"positions": [0.0, 0.0, 0.0]' + b" " * 20000 + b"}"  # 20 KB, valid JSON
        post = (b"POST /api/v1/arms/rbe3001/kinematics/forward HTTP/1.1\r\nHost: 127.0.0.1\r\n"
                b"Content-Type: application/json\r\nContent-Length: "
                + str(len(body)).encode() + b"\r\nConnection: close\r\n\r\n" + body)
        answer = _raw_request(port, post)
        assert answer.startswith(b"HTTP/1.1 200"), answer[:300]
        assert b'"tip"' in answer
        get = (b"GET /api/v1/health HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Pad: " + b"a" * 1000
               + b"\r\n\r\n")
        answers = _raw_request(port, get * 20 + b"GET /api/v1/health HTTP/1.1\r\n"
                               b"Host: 127.0.0.1\r\nConnection: close\r\n\r\n")
        assert answers.count(b"HTTP/1.1 200") == 21 and b"HTTP/1.1 400" not in answers


def test_connections_over_the_limit_get_503() -> None:
    with serve_live(make_settings(max_connections=8)) as live:
        port = int(live.url.rsplit(":", 1)[1])
        idle = [socket.create_connection(("127.0.0.1", port)) for _ in range(8)]
        try:
            wait_until(lambda: len(live.server.server_state.connections) >= 8,
                       what="the server holding the 8 idle connections")
            r = HTTP.get(live.url + "/api/v1/health", timeout=10)
            assert r.status_code == 503
            # the API's error body, not uvicorn's plain text, and when to come back
            assert r.headers["content-type"] == "application/json"
            assert r.json()["code"] == "busy" and "max_connections" in r.json()["detail"]
            assert set(r.json()) == {"detail", "code"}
            assert r.headers["retry-after"] == "1"
        finally:
            for s in idle:
                s.close()
        # the server notices the closed sockets
        wait_until(lambda: HTTP.get(live.url + "/api/v1/health", timeout=10).status_code == 200,
                   what="the server taking requests again", every=0.05)
        assert HTTP.get(live.url + "/api/v1/health", timeout=10).status_code == 200


async def _refused(url: str) -> tuple[int, dict[str, str]]:
    async with connect(url) as ws:
        with pytest.raises(ConnectionClosed) as exc:
            while True:
                await ws.recv()
    assert exc.value.rcvd is not None
    return exc.value.rcvd.code, json.loads(exc.value.rcvd.reason)


def test_subscribers_over_the_per_arm_and_total_limits_are_refused_busy() -> None:
    settings = make_settings(max_subscribers_per_arm=2, max_subscribers=3)

    async def run(base: str) -> None:
        rb, an = base + WS.format(arm="rbe3001"), base + WS.format(arm="angler")
        async with connect(rb) as a, connect(rb) as b:
            await a.recv()
            await b.recv()
            code, reason = await _refused(rb)
            assert code == 1013 and reason["code"] == "busy" and "rbe3001" in reason["detail"]
            async with connect(an) as c:
                await c.recv()
                code, reason = await _refused(an)
                assert code == 1013 and reason["code"] == "busy"
                assert "in all" in reason["detail"]
        # Closed subscribers free their places.
        async with connect(rb) as a:
            assert json.loads(await a.recv())["type"] == "telemetry"

    with serve_live(settings) as live:
        asyncio.run(run(live.ws_url))


def test_the_default_limits_let_a_lab_of_dashboards_watch_one_arm() -> None:
    """Issue 12: defaults must let a lab run its dashboards (the old 100 per arm, 200 in all
    refused the 101st). 300 clients on one arm with the default settings each get telemetry;
    the per-arm limit stays above what a lab needs and below the connection limit."""
    settings = make_settings()
    assert settings.max_subscribers_per_arm >= 1000
    assert settings.max_connections > settings.max_subscribers >= settings.max_subscribers_per_arm
    n = 300

    async def run(base: str) -> None:
        url = base + WS.format(arm="rbe3001") + "?rate=2"
        clients = await asyncio.gather(*[connect(url, open_timeout=60) for _ in range(n)])
        try:
            first = await asyncio.wait_for(asyncio.gather(*[c.recv() for c in clients]), 60)
            kinds = [json.loads(m)["type"] for m in first]
            assert kinds == ["telemetry"] * n
        finally:
            await asyncio.gather(*[c.close() for c in clients], return_exceptions=True)

    with serve_live(settings) as live:
        asyncio.run(run(live.ws_url))
