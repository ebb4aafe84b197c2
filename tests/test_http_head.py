"""HEAD is answered as GET would be, without the body (RFC 9110 9.1 and 9.3.2; before, every
GET route answered it 405): `HeadAsGet` (app/web/middleware.py), over real uvicorn. Through a
lab's front: tests/test_lab_workers.py."""

from __future__ import annotations

import socket
import time

import httpx
from conftest import LiveServer

API = "/api/v1"
#: Answers whose bodies do not change from one request to the next.
STEADY = ("/", "/openapi.json", f"{API}/arms", f"{API}/cameras", f"{API}/arms/nobody/state")


def test_head_has_gets_status_and_headers_and_no_body(live_server: LiveServer) -> None:
    with httpx.Client(base_url=live_server.url) as c:
        for path in STEADY:
            got, head = c.get(path), c.head(path)
            assert head.status_code == got.status_code, path
            assert head.content == b"", path
            assert head.headers["content-type"] == got.headers["content-type"], path
            assert int(head.headers["content-length"]) == len(got.content), path
        # the state's fast path, and an arm's detail: GET's kind of answer, no body
        for path in (f"{API}/arms/rbe3001/state", f"{API}/arms/rbe3001"):
            head = c.head(path)
            assert head.status_code == 200 and head.content == b"", path
            assert head.headers["content-type"] == "application/json"
            assert int(head.headers["content-length"]) > 0
        # a route with no GET is refused as before, and moves nothing
        press = c.head(f"{API}/arms/rbe3001/estop")
        assert press.status_code == 405 and press.content == b""
        assert c.get(f"{API}/arms/rbe3001/state").json()["estop"] is False


def test_head_of_a_stream_ends_at_its_head_and_the_connection_goes_on(
        live_server: LiveServer) -> None:
    """An MJPEG stream never ends; its HEAD does, and the next request on the same
    connection is answered (the raw bytes: one answer's head, then the next answer)."""
    host, port = live_server.url.removeprefix("http://").split(":")
    camera = httpx.get(f"{live_server.url}{API}/cameras").json()[0]["name"]
    with socket.create_connection((host, int(port)), timeout=10) as sock:
        sock.sendall(f"HEAD {API}/cameras/{camera}/stream HTTP/1.1\r\nHost: {host}:{port}\r\n"
                     f"\r\nGET {API}/health HTTP/1.1\r\nHost: {host}:{port}\r\n\r\n".encode())
        got = b""
        deadline = time.monotonic() + 10
        while b'"status"' not in got and time.monotonic() < deadline:
            chunk = sock.recv(65536)
            if not chunk:
                break
            got += chunk
    first, rest = got.split(b"\r\n\r\n", 1)
    assert first.startswith(b"HTTP/1.1 200"), first
    assert b"content-type: multipart/x-mixed-replace" in first.lower()
    assert rest.startswith(b"HTTP/1.1 200"), rest[:200]  # no frame between the two answers
    assert b'"status"' in rest
