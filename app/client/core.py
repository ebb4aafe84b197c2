"""The part both clients share beyond the routes: reading an answer (the error mapping of
`app.client.errors`), the retry policy, the telemetry WebSocket's URL and close codes, the
queue-turn check and the lease keeper's record. Nothing here does I/O.

Retries: only calls that are safe to repeat are retried, on a connect error (the request never
reached the server) or a 503 `link_down`: GETs, the idempotent PUT/DELETEs, and the POSTs with
no side effect on motion beyond their first effect (kinematics, plans, stop, estop). A move, a
gripper or protocol command is never retried: the caller decides. Backoff is short and bounded.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from typing import Any, TypeVar
from urllib.parse import urlencode

import httpx

from app import schemas as s
from app.client.errors import (
    STATUS_CODES,
    ArmServerError,
    ConnectionFailed,
    QueueTurnLost,
    error_from_body,
    make_error,
)
from app.client.routes import Call, url_path
from app.errors import CODES

T = TypeVar("T")

#: Attempts for a retry-safe call (1 + retries); backoff doubles from BACKOFF_S up to BACKOFF_MAX_S,
#: so a safe call gives up after about 0.7 s of a server that is restarting or a link that is down.
RETRIES = 2
BACKOFF_S = 0.1
BACKOFF_MAX_S = 1.0
TERMINAL = frozenset({"done", "stopped", "failed"})


def auth_headers(token: str | None) -> dict[str, str]:
    return {"Authorization": f"Bearer {token}"} if token else {}


def parse_answer(call: Call[T], resp: httpx.Response) -> T:
    if resp.status_code >= 400:
        raise error_from_body(resp.status_code, resp.content)
    if resp.status_code == 204 or not resp.content:
        return call.parse(None)
    if call.text:
        return call.parse(resp.text)
    if call.raw:
        return call.parse(resp.content)
    return call.parse(resp.json())


def turn_pending(arm: str, entry: s.QueueEntry, deadline: float | None,
                 timeout: float | None) -> bool:
    """True while a queue entry still waits for its offer; raises once the turn is lost (the
    entry ended) or `deadline` (monotonic) has passed; False once the offer is ours."""
    if entry.status == "offered" and entry.lease_id is not None:
        return False
    if entry.status not in ("waiting", "offered"):
        raise QueueTurnLost("turn_lost", f"{arm}: entry {entry.id} is {entry.status}: "
                            f"{entry.reason}", 409)
    if deadline is not None and time.monotonic() > deadline:
        raise TimeoutError(f"{arm}: no offer within {timeout} s (position {entry.position})")
    return True


def backoff(attempt: int) -> float:
    return min(BACKOFF_S * float(2 ** attempt), BACKOFF_MAX_S)


def should_retry(call: Call[Any], attempt: int, exc: BaseException | None,
                 resp: httpx.Response | None) -> bool:
    """A safe call is retried when the request never reached the server or the link is down."""
    if not call.safe or attempt >= RETRIES:
        return False
    if exc is not None:
        return isinstance(exc, httpx.ConnectError | httpx.ConnectTimeout)
    if resp is not None and resp.status_code == 503:
        try:
            return bool(resp.json().get("code") == "link_down")
        except (ValueError, AttributeError):
            return False
    return False


def transport_error(exc: httpx.HTTPError, call: Call[Any]) -> ConnectionFailed:
    return ConnectionFailed("connection_failed", f"{call.method} {call.path}: "
                            f"{type(exc).__name__}: {exc}", 0)


def ws_url(base_url: str, arm: str, rate: float | None, token: str | None) -> str:
    """The telemetry WebSocket URL: http->ws, https->wss, `rate` and `token` as query."""
    base = base_url.rstrip("/")
    if base.startswith("https://"):
        base = "wss://" + base[len("https://"):]
    elif base.startswith("http://"):
        base = "ws://" + base[len("http://"):]
    query: dict[str, Any] = {}
    if rate is not None:
        query["rate"] = rate
    if token:
        query["token"] = token
    url = base + url_path("arms", arm, "telemetry")
    return url + ("?" + urlencode(query) if query else "")


def parse_ws_message(raw: str | bytes) -> s.TelemetryMessage | s.EventMessage:
    data = json.loads(raw)
    if data.get("type") == "event":
        return s.EventMessage.model_validate(data)
    return s.TelemetryMessage.model_validate(data)


def ws_handshake_error(exc: Exception) -> ArmServerError:
    """A refused WebSocket handshake (401, 404, ...) as the server's error code."""
    resp = getattr(exc, "response", None)
    status = getattr(resp, "status_code", None)
    if status is not None:
        return error_from_body(int(status), getattr(resp, "body", b"") or b"")
    return ConnectionFailed("connection_failed", f"telemetry: {type(exc).__name__}: {exc}", 0)


#: Telemetry close codes that carry an error (app/web/routes/telemetry.py): code -> (code, status).
WS_CLOSE = {4401: ("unauthorized", 401), 4403: ("forbidden", 403), 4404: ("unknown_arm", 404),
            1008: ("invalid_request", 422), 1009: ("too_large", 413)}


def ws_close_error(exc: Exception) -> ArmServerError | None:
    """The error a closed telemetry socket stands for, or None for a normal close (1000, 1001).

    The server accepts the WebSocket before it checks the token and the arm, so that the
    client learns why: a refusal arrives as a close code, not as an HTTP status."""
    frame = getattr(exc, "rcvd", None)
    code = getattr(frame, "code", None)
    reason = getattr(frame, "reason", "") or ""
    if code in (1000, 1001):
        return None
    carried = _reason_body(reason)
    if carried is not None:  # e.g. 1013 {"code": "busy", "detail": ...}: the table says the rest
        name, detail = carried
        row = CODES.get(name)
        return make_error(name, detail, row.status if row and row.status else 0)
    if code in WS_CLOSE:
        name, status = WS_CLOSE[code]
        return make_error(name, reason or name, status)
    if code is not None and 4000 <= code < 5000:
        return make_error(STATUS_CODES.get(code - 4000, "error"), reason, code - 4000)
    return ConnectionFailed("connection_failed", f"telemetry closed: {exc}", 0)


def _reason_body(reason: str) -> tuple[str, Any] | None:
    """A close reason that is an error body: its (code, detail)."""
    if not reason.startswith("{"):
        return None
    try:
        data = json.loads(reason)
    except ValueError:
        return None
    if isinstance(data, dict) and isinstance(data.get("code"), str):
        return data["code"], data.get("detail", reason)
    return None


@dataclass
class LeaseKeeper:
    """A held lease: the latest `Lease`, how often it was renewed, the last renewal error."""

    lease: s.Lease
    renewals: int = 0
    error: ArmServerError | None = None

    @property
    def id(self) -> str:
        return self.lease.id
