"""The front's HTTP/1.1 client to one worker's Unix socket: kept-alive connections, nothing else.

A general client (httpx) spent about 1 ms of Python on each request here, against 0.16 ms for
the exchange itself on the development machine; the front makes one such request for every
request it serves, so it speaks the little HTTP/1.1 it needs itself: a request line, the
headers as the client sent them, a Content-Length body; an answer framed by Content-Length,
chunked, or to the end of the connection. Only the worker (our own server, uvicorn) is at the
other end, and only the front can reach its socket.

A connection the worker closed while it waited in the pool (uvicorn closes one idle for
`timeout_keep_alive`, 5 s; the worker restarted) is not used again: one whose end has come is
dropped as it is taken, and one idle for IDLE_MAX_S is not kept waiting for that end to come.
The supervisor's health probes share the pool with the requests, so a second connection is
opened whenever the two overlap, and then waits, mostly idle, under the one in use: an estop
press through the front that took it after the worker's close answered 503 `link_down`
(bench/lab.py, issue 27). A connection that breaks all the same (closed as the request went)
fails the request before any byte of an answer: a request the caller says may be sent twice
(`retry`: a GET or HEAD by default) is then tried once more on a new connection; any other is
the caller's failure (it may have reached the old worker).
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections import deque
from collections.abc import AsyncIterator
from pathlib import Path

#: Longest answer head accepted, bytes (the worker's are a few hundred).
HEAD_LIMIT = 64 * 1024
#: Read size of a relayed body, bytes.
READ_CHUNK = 64 * 1024
#: Methods tried again on a new connection when a kept-alive one turns out broken.
RETRYABLE = frozenset({"GET", "HEAD"})
#: Longest a connection waits in the pool, s: under the worker's `timeout_keep_alive` (uvicorn's
#: 5 s), so that a request never goes out on one the worker is closing.
IDLE_MAX_S = 4.0


class UpstreamError(OSError):
    """The worker could not be reached, or broke its answer off."""


Conn = tuple[asyncio.StreamReader, asyncio.StreamWriter]


class UpstreamResponse:
    """An answer's status and headers; its body read whole (`read`) or relayed (`chunks`)."""

    def __init__(self, upstream: Upstream, conn: Conn, status: int,
                 headers: list[tuple[bytes, bytes]], method: str) -> None:
        self._upstream = upstream
        self._conn: Conn | None = conn
        self.status_code = status
        self.headers = headers
        lower = {k: v for k, v in headers}
        self._chunked = b"chunked" in lower.get(b"transfer-encoding", b"").lower()
        length = lower.get(b"content-length")
        self._length = int(length) if length is not None and not self._chunked else None
        self._reuse = lower.get(b"connection", b"").lower() != b"close"
        if method == "HEAD" or status in (204, 304) or 100 <= status < 200:
            self._length, self._chunked = 0, False

    @property
    def length(self) -> int | None:
        """The body's length in bytes where the answer's head says it (Content-Length, not
        chunked), else None (a stream: to be relayed as it comes)."""
        return self._length

    async def chunks(self) -> AsyncIterator[bytes]:
        """The body as it comes (de-chunked); the connection back to the pool at its end."""
        if self._conn is None:
            return
        reader = self._conn[0]
        try:
            if self._chunked:
                while True:
                    line = await reader.readuntil(b"\r\n")
                    size = int(line.split(b";", 1)[0].strip(), 16)
                    if size == 0:
                        while await reader.readuntil(b"\r\n") != b"\r\n":  # trailers
                            pass
                        break
                    data = await reader.readexactly(size)
                    await reader.readexactly(2)
                    yield data
            elif self._length is not None:
                left = self._length
                while left > 0:
                    data = await reader.readexactly(min(left, READ_CHUNK))
                    left -= len(data)
                    yield data
            else:  # to the end of the connection
                self._reuse = False
                while data := await reader.read(READ_CHUNK):
                    yield data
        except (asyncio.IncompleteReadError, asyncio.LimitOverrunError, ValueError) as exc:
            self._reuse = False
            raise UpstreamError(f"a broken answer from the worker: {exc!r}") from None
        except BaseException:
            self._reuse = False
            raise
        finally:
            if self._conn is not None:
                conn, self._conn = self._conn, None
                self._upstream._release(conn, self._reuse)

    async def read(self) -> bytes:
        return b"".join([c async for c in self.chunks()])

    async def aclose(self) -> None:
        """Drop the connection if the body was not read to its end."""
        if self._conn is not None:
            conn, self._conn = self._conn, None
            self._upstream._release(conn, False)


class Upstream:
    """Kept-alive connections to one Unix socket (at most `keepalive` idle)."""

    def __init__(self, uds: Path, keepalive: int) -> None:
        self.uds = uds
        self.keepalive = keepalive
        #: Idle connections, each with the time it came back (`time.monotonic()`).
        self._idle: deque[tuple[Conn, float]] = deque()

    async def request(self, method: str, target: str, headers: list[tuple[bytes, bytes]],
                      body: bytes = b"", timeout: float | None = None,
                      retry: bool | None = None) -> UpstreamResponse:
        """Send one request and read the answer's head (within `timeout` s); the body is
        the caller's to read or relay. `headers` go as given (no Content-Length: it is
        computed; add Host yourself). `retry`: the request may go twice (default: a GET or
        HEAD), so a kept-alive connection that turns out broken is no failure."""
        head = [f"{method} {target} HTTP/1.1\r\n".encode("latin-1")]
        head += [k + b": " + v + b"\r\n" for k, v in headers]
        if body or method not in RETRYABLE:
            head.append(b"content-length: " + str(len(body)).encode() + b"\r\n")
        data = b"".join(head) + b"\r\n" + body
        again = method in RETRYABLE if retry is None else retry
        for attempt in (0, 1):
            taken = self._take()
            reused = taken is not None
            conn = taken if taken is not None else await self._open()
            try:
                async with asyncio.timeout(timeout):
                    conn[1].write(data)
                    raw = await conn[0].readuntil(b"\r\n\r\n")
            except (OSError, asyncio.IncompleteReadError, asyncio.LimitOverrunError) as exc:
                self._release(conn, False)
                if reused and attempt == 0 and again:
                    continue
                raise UpstreamError(f"worker socket {self.uds.name}: {exc!r}") from None
            except BaseException:
                self._release(conn, False)
                raise
            lines = raw[:-4].split(b"\r\n")
            try:
                status = int(lines[0].split(b" ", 2)[1])
            except (IndexError, ValueError):
                self._release(conn, False)
                raise UpstreamError(f"a malformed status line: {lines[0][:80]!r}") from None
            fields = []
            for line in lines[1:]:
                name, _, value = line.partition(b":")
                fields.append((name.strip().lower(), value.strip()))
            return UpstreamResponse(self, conn, status, fields, method)
        raise AssertionError("unreachable")

    async def _open(self) -> Conn:
        try:
            return await asyncio.open_unix_connection(str(self.uds), limit=HEAD_LIMIT)
        except OSError as exc:
            raise UpstreamError(f"worker socket {self.uds.name}: {exc!r}") from None

    def _take(self) -> Conn | None:
        """The idle connection that came back last, if one is left that the worker has not
        closed (nor may be closing: idle for IDLE_MAX_S); those it passes are closed."""
        now = time.monotonic()
        # (they came back in order: those idle too long are at the left, the rest are not)
        while self._idle and now - self._idle[0][1] >= IDLE_MAX_S:
            self._idle.popleft()[0][1].close()
        while self._idle:
            conn, _ = self._idle.pop()
            if conn[0].at_eof() or conn[1].is_closing():
                conn[1].close()
                continue
            return conn
        return None

    def _release(self, conn: Conn, reuse: bool) -> None:
        if reuse and len(self._idle) < self.keepalive and not conn[1].is_closing():
            self._idle.append((conn, time.monotonic()))
        else:
            conn[1].close()

    def reset(self) -> None:
        """Close every idle connection (the worker restarted: they lead nowhere)."""
        while self._idle:
            self._idle.pop()[0][1].close()

    async def aclose(self) -> None:
        self.reset()
        with contextlib.suppress(Exception):
            await asyncio.sleep(0)
