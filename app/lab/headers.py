"""What the front passes to a worker of a request's headers (app/lab/front.py, ws_relay.py) and
the one header it adds: the client's address, which a worker behind a Unix socket cannot see
(app/lab/worker.py `FrontClient` reads it back)."""

from __future__ import annotations

from starlette.types import Scope

#: The header in which the front names the client's address (host:port); the front drops any
#: a client sends, and only the front can reach a worker's socket (the lab's 0700 folder).
CLIENT_HEADER = b"x-armserver-lab-client"
#: Request headers the front does not pass on: hop by hop, the length (recomputed: the front
#: has read the body) and Expect (the front answered the 100-continue itself).
HOP = frozenset({b"connection", b"keep-alive", b"transfer-encoding", b"te", b"trailer",
                 b"upgrade", b"proxy-authorization", b"proxy-connection", b"content-length",
                 b"expect"})


def forwarded_headers(scope: Scope) -> list[tuple[bytes, bytes]]:
    """The request's headers for the worker: hop-by-hop ones dropped, the client's address
    (host:port) in CLIENT_HEADER (one a client sent is dropped)."""
    headers = [(k, v) for k, v in scope["headers"] if k not in HOP and k != CLIENT_HEADER]
    client = scope.get("client")
    if client:
        headers.append((CLIENT_HEADER, f"{client[0]}:{client[1]}".encode("latin-1")))
    return headers


def credentials(headers: list[tuple[bytes, bytes]]) -> bytes | None:
    """The `Authorization` value among forwarded `headers` (None: none)."""
    return next((v for k, v in headers if k == b"authorization"), None)
