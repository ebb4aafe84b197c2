"""Build every route before the first request needs it: one request nobody sees, at start-up.

FastAPI builds an included router's routes (each one's dependencies, its request and response
models as pydantic adapters) on the first request that reaches the router (FastAPI 0.165: some
80 ms of Python on the test machine for the arms' routers). That first request was a user's:
the first emergency stop pressed on a server took 40-90 ms instead of 5, and `bench/lab.py`'s
estop p99 was made of the first press on each arm. One request for a path no route has, sent
to the router below every middleware (nothing audits, gates or logs it), walks every router
and builds them all while the server starts."""

from __future__ import annotations

from typing import Any

from starlette.types import ASGIApp, Message

#: A path under the API prefix that no route has: matching it walks every router.
NO_ROUTE = "/__warm_routes__"


async def warm_routes(router: ASGIApp, prefix: str) -> int:
    """Send one `GET {prefix}{NO_ROUTE}` to `router` (the app's router, below the middleware):
    its answer's status (404)."""
    path = prefix + NO_ROUTE
    scope: dict[str, Any] = {
        "type": "http", "asgi": {"version": "3.0"}, "http_version": "1.1", "method": "GET",
        "scheme": "http", "path": path, "raw_path": path.encode(), "query_string": b"",
        "root_path": "", "headers": [(b"host", b"localhost")], "client": None,
        "server": None}
    status = 0

    async def receive() -> Message:
        return {"type": "http.request", "body": b"", "more_body": False}

    async def send(message: Message) -> None:
        nonlocal status
        if message["type"] == "http.response.start":
            status = int(message["status"])

    await router(scope, receive, send)
    return status
