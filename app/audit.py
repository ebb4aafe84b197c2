"""The audit log: every /api/v1 request that may change something (every method but GET, HEAD
and OPTIONS) is recorded with the time, the caller's name and role, the arm, the route, a
summary of the body and the answer's status and code (API.md "Audit log").

One ASGI middleware, outermost, so refusals (401, 403, 409, 413, 422) are recorded as well as
successes. Records go to the store's writer thread without waiting (app/store.py): the event
loop never blocks on the disk, and a record the disk refuses is kept and retried, never lost.

No token is ever recorded: the caller is named (app/auth.py), lease ids in paths become
`{lease}`, and body fields whose name says token, secret, password or lease are blanked.
"""

from __future__ import annotations

import json
import re
import time
from typing import Any

from fastapi import FastAPI
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from app.auth import Access, bearer_token

PREFIX = "/api/v1/"
READS = frozenset({"GET", "HEAD", "OPTIONS"})
#: Body bytes kept for the summary, and the summary's length at most.
BODY_KEEP = 4096
SUMMARY_MAX = 300
#: Error-body bytes kept to read the answer's `code`.
ANSWER_KEEP = 2048

_ARM = re.compile(r"^/api/v1/arms/([^/]+)")
_LEASE_IN_PATH = re.compile(r"(/lease/)[^/]+")
_SECRET_KEY = re.compile(r"(?i)token|secret|password|lease|authorization")


def summarize(body: bytes) -> str:
    """A short, token-free summary of a request body."""
    if not body:
        return ""
    try:
        data = json.loads(body)
    except (ValueError, UnicodeDecodeError):
        return f"({len(body)} bytes, not JSON)"
    text = json.dumps(_blank(data), separators=(",", ":"), allow_nan=True)
    return text if len(text) <= SUMMARY_MAX else text[:SUMMARY_MAX - 3] + "..."


def _blank(data: Any) -> Any:
    if isinstance(data, dict):
        return {k: "***" if isinstance(k, str) and _SECRET_KEY.search(k) else _blank(v)
                for k, v in data.items()}
    if isinstance(data, list):
        return [_blank(v) for v in data]
    return data


def route_of(path: str) -> str:
    return _LEASE_IN_PATH.sub(r"\1{lease}", path)


class AuditLog:
    """ASGI middleware writing one record per changing API request to `app.state.store`."""

    def __init__(self, app: ASGIApp, app_ref: FastAPI, access: Access) -> None:
        self.app = app
        self.ref = app_ref
        self.access = access

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        path = scope.get("path", "")
        if (scope["type"] != "http" or scope.get("method") in READS
                or not path.startswith(PREFIX)):
            await self.app(scope, receive, send)
            return
        started = time.time()
        body = bytearray()
        answer = bytearray()
        status = 0

        async def _receive() -> Message:
            message = await receive()
            if message["type"] == "http.request" and len(body) < BODY_KEEP:
                body.extend(message.get("body", b"")[:BODY_KEEP - len(body)])
            return message

        async def _send(message: Message) -> None:
            nonlocal status
            if message["type"] == "http.response.start":
                status = int(message["status"])
            elif (message["type"] == "http.response.body" and status >= 400
                  and len(answer) < ANSWER_KEEP):
                answer.extend(message.get("body", b"")[:ANSWER_KEEP - len(answer)])
            await send(message)

        try:
            await self.app(scope, _receive, _send)
        finally:
            self._record(scope, path, started, bytes(body), status, bytes(answer))

    def _record(self, scope: Scope, path: str, started: float, body: bytes, status: int,
                answer: bytes) -> None:
        store = getattr(self.ref.state, "store", None)
        if store is None:
            return
        header = dict(scope.get("headers", ())).get(b"authorization")
        who = self.access.identify(bearer_token(header.decode("latin-1") if header else None))
        m = _ARM.match(path)
        code = None
        if status >= 400:
            try:
                code = json.loads(answer).get("code")
            except (ValueError, UnicodeDecodeError, AttributeError):
                code = None
        store.audit((started, who.name if who else "(unauthenticated)",
                     who.role.name.lower() if who else "none", m.group(1)[:64] if m else None,
                     scope.get("method", "?"), route_of(path)[:256], summarize(body),
                     status or 499, code if isinstance(code, str) else None))
