"""The audit log (API.md "Audit log", README "Reading the log"): who did what to which arm.

One ASGI middleware, outermost, sees every /api/v1 request that may change something (every
method but GET, HEAD and OPTIONS) and its answer:

- **A request that passes the gates** (Host and Origin, the token, the body limit: the app has
  read its whole body) is recorded once it has run START_DEFER_S (20 ms), with no status, and
  completed with its status and code when it ends; one that ends sooner is recorded whole
  when it ends, after its answer went out. Either way the records are queued in the order
  the requests passed the gates, with the time each started, and none is built on the
  request's own path (issue 23: a pass-through goal's). The store writes a start within
  START_DEFER_S + AUDIT_FLUSH_S (0.12 s), so a kill -9 during a `wait: true` move keeps the
  attempt; on the next start such a record gets the code `interrupted`.
- **A refused request** (REFUSALS: 400 bad_host, 401 unauthorized, 403 forbidden and
  cross_origin, 404 not_found and unknown_arm, 405 method_not_allowed, 413 too_large: refused
  before any route's own work) is not recorded one by one: one `refusals` record per client
  address and reason (status and code) per `audit_refusal_interval_s` counts them, with the
  first and the last time. At most MAX_REFUSAL_KEYS such records an interval; beyond, the
  reason's refusals from every other address share one record (address `(others)`). A flood
  of bad tokens grows the log by a few rows a minute, not one row a request.
- Every other answer (409, 422, 2xx ...) completes the request's own record.

Records go to the store's writer thread without waiting (app/store.py): the event loop never
blocks on the disk; the store bounds what waits in memory and how many rows the log keeps.

No token is ever recorded: the caller is named (app/web/security.py), lease ids in paths become
`{lease}`, and body fields whose name says token, secret, password or lease are blanked. The
arm column names an arm only if it is one of the server's (a path's arm name is the client's
text: `=HYPERLINK(...)` is no arm); the CSV export neutralises formula cells
(app/web/routes/audit.py).
"""

from __future__ import annotations

import asyncio
import json
import logging
import re
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from typing import Any, TypeVar

from fastapi import FastAPI
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from app import schemas as s
from app.store import AuditEntry, Store
from app.web.security import Access, Identity, bearer_token_of

log = logging.getLogger(__name__)

T = TypeVar("T")

PREFIX = s.API_PREFIX + "/"
READS = frozenset({"GET", "HEAD", "OPTIONS"})
#: Body bytes kept for the summary, and the summary's length at most.
BODY_KEEP = 4096
SUMMARY_MAX = 300
#: Error-body bytes kept to read the answer's `code`.
ANSWER_KEEP = 2048
#: The answers of the gates in front of every route's own work, (status, code): counted per
#: address and reason, not recorded one by one.
REFUSALS = frozenset({(400, "bad_host"), (401, "unauthorized"), (403, "forbidden"),
                      (403, "cross_origin"), (404, "not_found"), (404, "unknown_arm"),
                      (405, "method_not_allowed"), (413, "too_large")})
#: How long a request's start record may wait to be built, s: one that ends sooner gets one
#: complete record, built after its answer went out (issue 23: the record's build was on a
#: pass-through goal's path, before the route); one that runs on gets its start record then,
#: in the store within this plus AUDIT_FLUSH_S (app/store.py).
START_DEFER_S = 0.02
#: `refusals` records of one interval at most (then the rest share one per reason).
MAX_REFUSAL_KEYS = 100
OTHERS = "(others)"
UNAUTHENTICATED = "(unauthenticated)"

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


class Refusals:
    """The current interval's `refusals` records, by (address, name, role, status, code)."""

    def __init__(self, interval_s: float, max_keys: int = MAX_REFUSAL_KEYS) -> None:
        self.interval_s = interval_s
        self.max_keys = max_keys
        self._bucket: int | None = None
        self._open: dict[tuple[str, str, str, int, str], AuditEntry] = {}

    def count(self, store: Store, at: float, address: str, name: str, role: str, method: str,
              route: str, status: int, code: str) -> None:
        bucket = int(at // self.interval_s)
        if bucket != self._bucket:  # the last interval's records are complete
            self._bucket = bucket
            self._open = {}
        key = (address, name, role, status, code)
        if key not in self._open and len(self._open) >= self.max_keys:
            key = (OTHERS, OTHERS, "none", status, code)
            address, name, role = key[:3]
        entry = self._open.get(key)
        if entry is None or entry.dropped:
            self._open[key] = store.audit(AuditEntry(
                at, name, role, None, method, route, _refused(1, status, code, address), status,
                code, kind="refusals", count=1, ended=at, address=address))
        else:
            store.audit_update(entry, count=entry.count + 1, ended=at,
                               summary=_refused(entry.count + 1, status, code, address))


def _refused(n: int, status: int, code: str, address: str) -> str:
    return f"{n} request(s) refused {status} {code} from {address}"


@dataclass(eq=False)
class _Start:
    """A request past the gates whose start record is not built yet (`AuditLog._defer`)."""

    scope: Scope
    path: str
    started: float
    body: bytes
    entry: AuditEntry | None = None


class AuditLog:
    """ASGI middleware recording every changing API request to `app.state.store`."""

    def __init__(self, app: ASGIApp, app_ref: FastAPI, access: Access) -> None:
        self.app = app
        self.ref = app_ref
        self.access = access
        settings = getattr(app_ref.state, "settings", None)
        self.refusals = Refusals(float(getattr(settings, "audit_refusal_interval_s", 60.0)))
        #: start records not built yet, in the order their requests passed the gates
        self._waiting: deque[_Start] = deque()
        self._timer: asyncio.TimerHandle | None = None

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        path = scope.get("path", "")
        store: Store | None = getattr(self.ref.state, "store", None)
        if (scope["type"] != "http" or scope.get("method") in READS
                or not path.startswith(PREFIX) or store is None):
            await self.app(scope, receive, send)
            return
        started = time.time()
        body = bytearray()
        answer = bytearray()
        status = 0
        start: _Start | None = None

        async def _receive() -> Message:
            nonlocal start
            message = await receive()
            if message["type"] == "http.request" and start is None:
                if len(body) < BODY_KEEP:
                    body.extend(message.get("body", b"")[:BODY_KEEP - len(body)])
                if not message.get("more_body", False):  # past the gates: the app reads it
                    start = _Start(scope, path, started, bytes(body))
                    self._defer(store, start)
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
            entry = None
            if start is not None:  # its start record, built now if it still waits
                self._guarded(lambda: self._starts(store, upto=start, last=False))
                entry = start.entry
            self._guarded(lambda: self._end(store, scope, path, started, entry, bytes(body),
                                            status or 499, bytes(answer)))

    def _defer(self, store: Store, start: _Start) -> None:
        """Queue a request's start record, to be built at its end or START_DEFER_S from now,
        whichever comes first (`_starts`): not on the request's path."""
        self._waiting.append(start)
        if self._timer is None:
            self._timer = asyncio.get_running_loop().call_later(
                START_DEFER_S, lambda: self._guarded(lambda: self._starts(store)))

    def _starts(self, store: Store, upto: _Start | None = None, last: bool = True) -> None:
        """Build the waiting start records in the order their requests passed the gates: all
        of them (the timer), or up to `upto` (a request that ends), `upto`'s own only if
        `last` (a request that ends gets one complete record instead: `_end`)."""
        if upto is None:
            self._timer = None
        elif upto not in self._waiting:
            return  # built already
        while self._waiting:
            s = self._waiting.popleft()
            if s is not upto or last:
                s.entry = self._guarded(partial(self._record_start, store, s))
            if s is upto:
                break
        if not self._waiting and self._timer is not None:
            self._timer.cancel()
            self._timer = None

    def _record_start(self, store: Store, s: _Start) -> AuditEntry:
        return store.audit(self._entry(s.scope, s.path, s.started, s.body))

    def _guarded(self, fn: Callable[[], T]) -> T | None:
        """`fn()`; a bug in recording is logged and counted (as app/web/middleware.py's last resort
        does), never the request's failure: this middleware is outside that last resort."""
        try:
            return fn()
        except Exception:
            self.ref.state.internal_errors += 1
            log.exception("audit: recording failed")
            return None

    def _who(self, scope: Scope) -> Identity | None:
        header = dict(scope.get("headers", ())).get(b"authorization")
        return self.access.identify(bearer_token_of(header))

    def _entry(self, scope: Scope, path: str, started: float, body: bytes) -> AuditEntry:
        who = self._who(scope)
        m = _ARM.match(path)
        arms = getattr(self.ref.state, "services", {})
        client = scope.get("client")
        return AuditEntry(started, who.name if who else UNAUTHENTICATED,
                          who.role.name.lower() if who else "none",
                          m.group(1) if m and m.group(1) in arms else None,
                          scope.get("method", "?"), route_of(path)[:256], summarize(body), None,
                          None, address=str(client[0])[:64] if client else None)

    def _end(self, store: Store, scope: Scope, path: str, started: float,
             entry: AuditEntry | None, body: bytes, status: int, answer: bytes) -> None:
        code = None
        if status >= 400:
            try:
                code = json.loads(answer).get("code")
            except (ValueError, UnicodeDecodeError, AttributeError):
                code = None
        code = code[:64] if isinstance(code, str) else None
        if code is not None and (status, code) in REFUSALS:
            if entry is not None:
                store.audit_cancel(entry)
            else:
                entry = self._entry(scope, path, started, b"")
            self.refusals.count(store, started, entry.address or "?", entry.name, entry.role,
                                entry.method, entry.route, status, code)
            return
        if entry is not None:
            store.audit_update(entry, status=status, code=code, ended=time.time())
            return
        entry = self._entry(scope, path, started, body)  # answered before its body was read
        entry.status, entry.code, entry.ended = status, code, time.time()
        store.audit(entry)
