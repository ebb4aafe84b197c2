"""`RemoteLeader.set_torque` (app/teleop/remote.py) against a worker's socket that answers as
given: a real HTTP exchange over a real Unix socket, the request as sent and the error raised
for each answer. A refusal of the error table keeps its code; anything else (a 500, a body
that is no error) is the worker's fault, 502 `device_error`; a silent worker 504; no socket
503. (The whole path, front and workers, is tests/test_lab_across.py.)"""

from __future__ import annotations

import asyncio
from pathlib import Path

import orjson
import pytest

from app.arms.loading import load_profile
from app.errors import ArmError
from app.teleop import remote
from app.teleop.remote import Peer, RemoteLeader


async def _worker(path: Path, answer: bytes | None, seen: list[bytes]) -> asyncio.Server:
    """A one-answer HTTP server on `path`: notes each request's bytes, answers `answer`
    (None: never)."""
    async def serve(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        head = await reader.readuntil(b"\r\n\r\n")
        size = next((int(line.split(b":")[1]) for line in head.split(b"\r\n")
                     if line.lower().startswith(b"content-length:")), 0)
        seen.append(head + await reader.readexactly(size))
        if answer is None:
            await asyncio.sleep(60)
        else:
            writer.write(answer)
            await writer.drain()
        writer.close()
    return await asyncio.start_unix_server(serve, path=str(path))


def _http(status: str, body: bytes, kind: str = "application/json") -> bytes:
    return (f"HTTP/1.1 {status}\r\ncontent-type: {kind}\r\ncontent-length: {len(body)}\r\n"
            "connection: close\r\n\r\n").encode() + body


async def test_the_request_and_each_answer(tmp_path: Path, monkeypatch: pytest.MonkeyPatch
                                           ) -> None:
    peer = Peer(load_profile("angler"), tmp_path / "w.sock")
    leader = RemoteLeader(peer, [("Authorization", "Bearer tok")], "L-1", load_supported=True)
    ok = _http("200 OK", b'{"arm": "angler", "on": false}')
    leased = _http("409 Conflict", orjson.dumps({"detail": "angler is leased",
                                                 "code": "leased"}))
    cases: list[tuple[bytes | None, str | None, int | None]] = [
        (ok, None, None), (leased, "leased", 409),
        (_http("500 Internal Server Error", b"oops", "text/plain"), "device_error", 502),
        (_http("409 Conflict", b'{"detail": "x", "code": "not_a_code"}'), "device_error", 502),
    ]
    for answer, code, status in cases:
        seen: list[bytes] = []
        server = await _worker(peer.uds, answer, seen)
        try:
            if code is None:
                await leader.set_torque(False)
            else:
                with pytest.raises(ArmError) as got:
                    await leader.set_torque(False)
                assert (got.value.code, got.value.status_code) == (code, status)
                assert got.value.detail.startswith("angler's worker: ")
        finally:
            server.close()
            await server.wait_closed()
            peer.uds.unlink(missing_ok=True)
        head, _, body = seen[0].partition(b"\r\n\r\n")
        assert head.startswith(b"PUT /api/v1/arms/angler/torque HTTP/1.1")
        lines = {ln.split(b":")[0].lower(): ln.split(b":", 1)[1].strip()
                 for ln in head.split(b"\r\n")[1:]}
        assert lines[b"authorization"] == b"Bearer tok" and lines[b"x-arm-lease"] == b"L-1"
        assert orjson.loads(body) == {"on": False, "load_supported": True}
    # no worker on the socket: 503 link_down; a worker that never answers: 504
    with pytest.raises(ArmError) as got:
        await leader.set_torque(True)
    assert (got.value.code, got.value.status_code) == ("link_down", 503)
    monkeypatch.setattr(remote, "TORQUE_TIMEOUT_S", 0.2)
    seen = []
    server = await _worker(peer.uds, None, seen)
    try:
        with pytest.raises(ArmError) as got:
            await leader.set_torque(True)
        assert (got.value.code, got.value.status_code) == ("device_timeout", 504)
    finally:
        server.close()
        await server.wait_closed()
