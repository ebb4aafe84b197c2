"""Python client of the arm server's public contract (../shared/API.md), on httpx and websockets.

`AsyncArmClient` (asyncio) and `ArmClient` (blocking, in `app.client_sync`, re-exported here)
have the same methods, one per route, and return the contract's own pydantic models
(`app.schemas`). Request bodies are built from those models too, so a bad request (a NaN, a
speed above 1) is refused before it leaves the process.

Errors: every non-2xx answer raises `ArmServerError` (or the subclass for its `code`) carrying
the server's `code`, `detail` and HTTP `status`. A transport failure raises `ConnectionFailed`
(code "connection_failed", status 0).

Retries: only calls that are safe to repeat are retried, on a connect error (the request never
reached the server) or a 503 `link_down`: GETs, the idempotent PUT/DELETEs, and the POSTs with
no side effect on motion beyond their first effect (kinematics, plans, stop, estop). A move, a
gripper or protocol command is never retried: the caller decides. Backoff is short and bounded.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import time
from collections.abc import AsyncIterator, Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Generic, Literal, TypeVar
from urllib.parse import quote, urlencode

import httpx
from pydantic import BaseModel, TypeAdapter

from app import schemas as s

log = logging.getLogger(__name__)

__all__ = [  # noqa: F822 - ArmClient is loaded lazily by __getattr__ (app.client_sync)
    "ArmClient", "ArmServerError", "AsyncArmClient", "Busy", "ConnectionFailed", "DeviceError",
    "DeviceTimeout", "EstopLatched", "Forbidden", "InvalidRequest", "JointLimit", "Leased",
    "LinkDown", "NoGripper", "NotFound", "NotSupported", "Unauthorized", "Unreachable",
    "VelocityLimit",
]

T = TypeVar("T")

API = "/api/v1"
LEASE_HEADER = "X-Arm-Lease"
#: Attempts for a retry-safe call (1 + retries); backoff doubles from BACKOFF_S up to BACKOFF_MAX_S,
#: so a safe call gives up after about 0.7 s of a server that is restarting or a link that is down.
RETRIES = 2
BACKOFF_S = 0.1
BACKOFF_MAX_S = 1.0
#: How long a `wait=true` move may hold the request open: the planner caps a move at 600 s.
WAIT_TIMEOUT_S = 660.0
TERMINAL = frozenset({"done", "stopped", "failed"})


# ---------------------------------------------------------------- errors


class ArmServerError(Exception):
    """The server refused a request: `code` is its stable machine code, `status` the HTTP status."""

    code = "error"

    def __init__(self, code: str, detail: Any, status: int) -> None:
        self.code = code
        self.detail = detail
        self.status = status
        super().__init__(f"{status} {code}: {detail}")


class NotFound(ArmServerError):
    """unknown_arm, unknown_motion, not_found."""


class InvalidRequest(ArmServerError):
    """invalid_request: a body or parameter the server could not accept."""


class Unreachable(ArmServerError):
    """unreachable: no IK solution, or a line leaves the workspace."""


class JointLimit(ArmServerError):
    """joint_limit: a target or path outside a joint's limits."""


class VelocityLimit(ArmServerError):
    """velocity_limit."""


class EstopLatched(ArmServerError):
    """estop_latched: release it with `release_estop` before moving."""


class Busy(ArmServerError):
    """busy: the motion queue (or a request queue) is full."""


class NoGripper(ArmServerError):
    """no_gripper: the arm has no actuated gripper."""


class Leased(ArmServerError):
    """leased: another client holds the arm's control lease."""


class NotSupported(ArmServerError):
    """not_supported: e.g. a Dynamixel command to the rbe3001."""


class QueueTurnLost(ArmServerError):
    """The queue entry ended (offer expired, removed, cleared) before its lease was claimed."""


class Unauthorized(ArmServerError):
    """unauthorized: no or an unknown token."""


class Forbidden(ArmServerError):
    """forbidden: a viewer token asked for an operator's route."""


class DeviceError(ArmServerError):
    """device_error, corrupt_reply: the device answered with an error."""


class LinkDown(ArmServerError):
    """link_down: the server cannot talk to the arm now."""


class DeviceTimeout(ArmServerError):
    """device_timeout: the device did not answer in time."""


class ConnectionFailed(ArmServerError):
    """The server could not be reached (or the connection broke): no HTTP status."""


ERRORS: dict[str, type[ArmServerError]] = {
    "not_found": NotFound, "unknown_arm": NotFound, "unknown_motion": NotFound,
    "motion_expired": NotFound, "bad_host": ArmServerError, "cross_origin": Forbidden,
    "unknown_lease": NotFound, "unknown_entry": NotFound, "invalid_json": InvalidRequest,
    "invalid_request": InvalidRequest, "unreachable": Unreachable, "joint_limit": JointLimit,
    "velocity_limit": VelocityLimit, "estop_latched": EstopLatched, "busy": Busy,
    "no_gripper": NoGripper, "leased": Leased, "not_supported": NotSupported,
    "unauthorized": Unauthorized, "forbidden": Forbidden, "device_error": DeviceError,
    "corrupt_reply": DeviceError, "link_down": LinkDown, "device_timeout": DeviceTimeout,
    "connection_failed": ConnectionFailed,
}
_STATUS_CODES = {401: "unauthorized", 403: "forbidden", 404: "not_found", 409: "conflict",
                 422: "invalid_request", 503: "link_down", 504: "device_timeout"}


def make_error(code: str, detail: Any, status: int) -> ArmServerError:
    return ERRORS.get(code, ArmServerError)(code, detail, status)


def error_from_body(status: int, body: bytes | str) -> ArmServerError:
    """The exception for an error answer: the body's `code` if it has one, else one by status."""
    code, detail = _STATUS_CODES.get(status, "error"), None
    try:
        data = json.loads(body)
    except (ValueError, TypeError):
        data = None
    if isinstance(data, dict):
        code = str(data.get("code") or code)
        detail = data.get("detail")
    if detail is None:
        text = body.decode(errors="replace") if isinstance(body, bytes) else str(body)
        detail = text.strip() or f"HTTP {status}"
    return make_error(code, detail, status)


# ---------------------------------------------------------------- requests, shared by both clients


@dataclass(frozen=True)
class Call(Generic[T]):
    """One request of the contract: what to send, how to read the answer, whether to retry."""

    method: str
    path: str
    parse: Callable[[Any], T]
    body: Any = None
    params: Mapping[str, Any] | None = None
    arm: str | None = None
    safe: bool = False
    timeout: float | None = None
    headers: dict[str, str] = field(default_factory=dict)
    #: Parse the answer's text rather than its JSON (e.g. the audit log as CSV).
    text: bool = False


def _p(*parts: object) -> str:
    return API + "".join("/" + quote(str(x), safe="") for x in parts)


def _model(model: type[BaseModel]) -> Callable[[Any], Any]:
    return model.model_validate


def _none(_: Any) -> None:
    return None


def _audit_rows(data: Any) -> list[s.AuditRecord]:
    return [s.AuditRecord.model_validate(r) for r in data]


def _arms(data: Any) -> list[s.ArmSummary]:
    items = data["arms"] if isinstance(data, dict) and "arms" in data else data
    return TypeAdapter(list[s.ArmSummary]).validate_python(items)


def _body(model: BaseModel) -> dict[str, Any]:
    return model.model_dump(mode="json", exclude_none=True)


def _pid(j: s.PidSetpoint | Mapping[str, float] | float) -> s.PidSetpoint:
    if isinstance(j, s.PidSetpoint):
        return j
    if isinstance(j, Mapping):
        return s.PidSetpoint.model_validate(j)
    return s.PidSetpoint(position_ticks=float(j))


class Requests:
    """Builds the `Call` for every route; both clients send these. Arguments in SI units."""

    @staticmethod
    def health() -> Call[s.Health]:
        return Call("GET", _p("health"), _model(s.Health), safe=True)

    @staticmethod
    def arms() -> Call[list[s.ArmSummary]]:
        return Call("GET", _p("arms"), _arms, safe=True)

    @staticmethod
    def arm(arm: str) -> Call[s.ArmDetail]:
        return Call("GET", _p("arms", arm), _model(s.ArmDetail), arm=arm, safe=True)

    @staticmethod
    def state(arm: str) -> Call[s.Sample]:
        return Call("GET", _p("arms", arm, "state"), _model(s.Sample), arm=arm, safe=True)

    @staticmethod
    def joints_request(verb: str, arm: str, req: s.MoveJoints, safe: bool) -> Call[s.Motion]:
        return Call("POST", _p("arms", arm, verb, "joints"), _model(s.Motion), _body(req), arm=arm,
                    safe=safe, timeout=WAIT_TIMEOUT_S if req.wait else None)

    @staticmethod
    def pose_request(verb: str, arm: str, req: s.MovePose, safe: bool) -> Call[s.Motion]:
        return Call("POST", _p("arms", arm, verb, "pose"), _model(s.Motion), _body(req), arm=arm,
                    safe=safe, timeout=WAIT_TIMEOUT_S if req.wait else None)

    @staticmethod
    def motion(arm: str, motion_id: str) -> Call[s.Motion]:
        return Call("GET", _p("arms", arm, "motions", motion_id), _model(s.Motion), arm=arm,
                    safe=True)

    @staticmethod
    def cancel_motion(arm: str, motion_id: str) -> Call[s.Motion]:
        # The server answers once a running motion has decelerated: allow for it.
        return Call("DELETE", _p("arms", arm, "motions", motion_id), _model(s.Motion), arm=arm,
                    safe=True, timeout=60.0)

    @staticmethod
    def stop(arm: str) -> Call[s.StopResult]:
        return Call("POST", _p("arms", arm, "stop"), _model(s.StopResult), arm=arm, safe=True,
                    timeout=60.0)

    @staticmethod
    def estop(arm: str) -> Call[s.EstopState]:
        return Call("POST", _p("arms", arm, "estop"), _model(s.EstopState), arm=arm, safe=True)

    @staticmethod
    def release_estop(arm: str) -> Call[s.EstopState]:
        return Call("DELETE", _p("arms", arm, "estop"), _model(s.EstopState), arm=arm, safe=True)

    @staticmethod
    def gripper(arm: str, value: float) -> Call[s.GripperState]:
        return Call("POST", _p("arms", arm, "gripper"), _model(s.GripperState),
                    _body(s.GripperCommand(value=value)), arm=arm)

    @staticmethod
    def tare_force(arm: str) -> Call[s.ForceTare]:
        return Call("POST", _p("arms", arm, "force", "tare"), _model(s.ForceTare), arm=arm)

    @staticmethod
    def clear_tare(arm: str) -> Call[s.ForceTare]:
        return Call("DELETE", _p("arms", arm, "force", "tare"), _model(s.ForceTare), arm=arm)

    @staticmethod
    def forward(arm: str, positions: Sequence[float]) -> Call[s.ForwardResult]:
        return Call("POST", _p("arms", arm, "kinematics", "forward"), _model(s.ForwardResult),
                    _body(s.JointVector(positions=list(positions))), arm=arm, safe=True)

    @staticmethod
    def inverse(arm: str, req: s.InverseRequest) -> Call[s.InverseResult]:
        return Call("POST", _p("arms", arm, "kinematics", "inverse"), _model(s.InverseResult),
                    _body(req), arm=arm, safe=True)

    @staticmethod
    def workspace(arm: str, params: Mapping[str, Any]) -> Call[s.Workspace]:
        return Call("GET", _p("arms", arm, "workspace"), _model(s.Workspace), params=params or None,
                    arm=arm, safe=True)

    @staticmethod
    def rbe3001_set_pid(arm: str, joints: Sequence[Any]) -> Call[s.SetPidReply]:
        body = _body(s.SetPid(joints=[_pid(j) for j in joints]))
        return Call("POST", _p("arms", arm, "rbe3001", "set-pid"), _model(s.SetPidReply), body,
                    arm=arm)

    @staticmethod
    def rbe3001_status(arm: str) -> Call[s.Rbe3001Status]:
        return Call("GET", _p("arms", arm, "rbe3001", "status"), _model(s.Rbe3001Status), arm=arm,
                    safe=True)

    @staticmethod
    def rbe3001_set_gain(arm: str, axis: int, kp: float, ki: float, kd: float) -> Call[s.Ack]:
        body = _body(s.SetGain(axis=axis, kp=kp, ki=ki, kd=kd))
        return Call("POST", _p("arms", arm, "rbe3001", "set-gain"), _model(s.Ack), body, arm=arm)

    @staticmethod
    def rbe3001_set_claw(arm: str, value: float) -> Call[s.Ack]:
        return Call("POST", _p("arms", arm, "rbe3001", "set-claw"), _model(s.Ack),
                    _body(s.SetClaw(value=value)), arm=arm)

    @staticmethod
    def dxl_ping(arm: str, dxl_id: int | None) -> Call[s.PingResult]:
        return Call("POST", _p("arms", arm, "dynamixel", "ping"), _model(s.PingResult),
                    s.PingRequest(id=dxl_id).model_dump(mode="json"), arm=arm, safe=True)

    @staticmethod
    def dxl_read_register(arm: str, dxl_id: int, name: str) -> Call[s.RegisterValue]:
        return Call("GET", _p("arms", arm, "dynamixel", dxl_id, "registers", name),
                    _model(s.RegisterValue), arm=arm, safe=True)

    @staticmethod
    def dxl_write_register(arm: str, dxl_id: int, name: str, raw: int) -> Call[s.RegisterValue]:
        return Call("PUT", _p("arms", arm, "dynamixel", dxl_id, "registers", name),
                    _model(s.RegisterValue), _body(s.RegisterWrite(raw=raw)), arm=arm, safe=True)

    @staticmethod
    def dxl_sync_read(arm: str, name: str, ids: Sequence[int]) -> Call[s.SyncReadResult]:
        return Call("POST", _p("arms", arm, "dynamixel", "sync-read"), _model(s.SyncReadResult),
                    _body(s.SyncReadRequest(name=name, ids=list(ids))), arm=arm, safe=True)

    @staticmethod
    def dxl_sync_write(arm: str, name: str, values: Mapping[int, int]) -> Call[s.Ack]:
        return Call("POST", _p("arms", arm, "dynamixel", "sync-write"), _model(s.Ack),
                    _body(s.SyncWriteRequest(name=name, values=dict(values))), arm=arm)

    @staticmethod
    def dxl_reboot(arm: str, dxl_id: int) -> Call[s.Ack]:
        return Call("POST", _p("arms", arm, "dynamixel", dxl_id, "reboot"), _model(s.Ack), arm=arm)

    @staticmethod
    def safety(arm: str) -> Call[s.Safety]:
        return Call("GET", _p("arms", arm, "safety"), _model(s.Safety), arm=arm, safe=True)

    @staticmethod
    def set_safety(arm: str, update: s.SafetyUpdate) -> Call[s.Safety]:
        body = update.model_dump(mode="json", exclude_unset=True)  # floor_z None: no floor
        return Call("PUT", _p("arms", arm, "safety"), _model(s.Safety), body, arm=arm,
                    safe=True)

    @staticmethod
    def home(arm: str, positions: Sequence[float] | None = None) -> Call[s.ArmDetail]:
        body = None if positions is None else _body(s.HomeRequest(positions=list(positions)))
        return Call("POST", _p("arms", arm, "home"), _model(s.ArmDetail), body, arm=arm)

    @staticmethod
    def take_lease(arm: str) -> Call[s.Lease]:
        return Call("POST", _p("arms", arm, "lease"), _model(s.Lease), arm=arm)

    @staticmethod
    def renew_lease(arm: str, lease_id: str) -> Call[s.Lease]:
        return Call("PUT", _p("arms", arm, "lease", lease_id), _model(s.Lease), arm=arm,
                    safe=True, headers={LEASE_HEADER: lease_id})

    @staticmethod
    def release_lease(arm: str, lease_id: str) -> Call[None]:
        return Call("DELETE", _p("arms", arm, "lease", lease_id), _none, arm=arm, safe=True,
                    headers={LEASE_HEADER: lease_id})

    # classroom: people, queue, audit (API.md "People and roles", "Queue and hand-off")

    @staticmethod
    def me() -> Call[s.Me]:
        return Call("GET", _p("me"), _model(s.Me), safe=True)

    @staticmethod
    def join_queue(arm: str) -> Call[s.QueueEntry]:
        return Call("POST", _p("arms", arm, "queue"), _model(s.QueueEntry), arm=arm)

    @staticmethod
    def queue(arm: str) -> Call[s.QueueStatus]:
        return Call("GET", _p("arms", arm, "queue"), _model(s.QueueStatus), arm=arm, safe=True)

    @staticmethod
    def queue_entry(arm: str, entry_id: str) -> Call[s.QueueEntry]:
        return Call("GET", _p("arms", arm, "queue", entry_id), _model(s.QueueEntry), arm=arm,
                    safe=True)

    @staticmethod
    def leave_queue(arm: str, entry_id: str) -> Call[s.QueueEntry]:
        return Call("DELETE", _p("arms", arm, "queue", entry_id), _model(s.QueueEntry),
                    arm=arm, safe=True)

    @staticmethod
    def reorder_queue(arm: str, order: Sequence[str]) -> Call[s.QueueStatus]:
        return Call("PUT", _p("arms", arm, "queue"), _model(s.QueueStatus),
                    s.QueueOrder(order=list(order)).model_dump(), arm=arm, safe=True)

    @staticmethod
    def clear_queue(arm: str) -> Call[s.QueueStatus]:
        return Call("DELETE", _p("arms", arm, "queue"), _model(s.QueueStatus), arm=arm,
                    safe=True)

    @staticmethod
    def revoke_lease(arm: str) -> Call[None]:
        return Call("DELETE", _p("arms", arm, "lease"), _none, arm=arm)

    @staticmethod
    def audit(params: Mapping[str, Any], csv: bool = False) -> Call[Any]:
        given = {k: v for k, v in params.items() if v is not None}
        if csv:
            return Call("GET", _p("audit"), str, params=given, safe=True, text=True,
                        headers={"Accept": "text/csv"})
        return Call("GET", _p("audit"), _audit_rows, params=given, safe=True)


def move_joints_model(positions: Sequence[float], duration: float | None, speed: float,
                      mode: s.QueueMode, wait: bool) -> s.MoveJoints:
    return s.MoveJoints(positions=list(positions), duration=duration, speed=speed, mode=mode,
                        wait=wait)


def move_pose_model(x: float, y: float, z: float, path: Literal["joint", "line"],
                    branch: int | None, ik_case: Literal["dx_zero", "dx_used"] | None,
                    duration: float | None, speed: float, mode: s.QueueMode,
                    wait: bool) -> s.MovePose:
    return s.MovePose(x=x, y=y, z=z, path=path, branch=branch, ik_case=ik_case,
                      duration=duration, speed=speed, mode=mode, wait=wait)


def parse_answer(call: Call[T], resp: httpx.Response) -> T:
    if resp.status_code >= 400:
        raise error_from_body(resp.status_code, resp.content)
    if resp.status_code == 204 or not resp.content:
        return call.parse(None)
    if call.text:
        return call.parse(resp.text)
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
    return min(BACKOFF_S * (2 ** attempt), BACKOFF_MAX_S)


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
    url = base + _p("arms", arm, "telemetry")
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


#: Telemetry close codes that carry an error (app/api/telemetry.py): code -> (code, status).
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
    if code in WS_CLOSE:
        name, status = WS_CLOSE[code]
        return make_error(name, reason or name, status)
    if code is not None and 4000 <= code < 5000:
        return make_error(_STATUS_CODES.get(code - 4000, "error"), reason, code - 4000)
    return ConnectionFailed("connection_failed", f"telemetry closed: {exc}", 0)


# ---------------------------------------------------------------- the asyncio client


class AsyncArmClient:
    """Asyncio client: one method per route, returning `app.schemas` models.

    `token` is sent as `Authorization: Bearer`; `lease` (a lease id) as `X-Arm-Lease` on every
    request, unless the arm has its own lease taken with `hold_lease`.
    """

    def __init__(self, base_url: str = "http://127.0.0.1:8000", token: str | None = None,
                 lease: str | None = None, timeout: float = 10.0,
                 transport: httpx.AsyncBaseTransport | None = None) -> None:
        self.base_url = base_url.rstrip("/")
        self.token = token
        self.lease = lease
        self.leases: dict[str, str] = {}
        self.timeout = timeout
        headers = {"Authorization": f"Bearer {token}"} if token else {}
        self._http = httpx.AsyncClient(base_url=self.base_url, headers=headers, timeout=timeout,
                                       transport=transport)

    async def __aenter__(self) -> AsyncArmClient:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.aclose()

    async def aclose(self) -> None:
        await self._http.aclose()

    def _headers(self, call: Call[Any]) -> dict[str, str]:
        headers = dict(call.headers)
        lease = self.leases.get(call.arm or "", self.lease)
        if lease and LEASE_HEADER not in headers:
            headers[LEASE_HEADER] = lease
        return headers

    async def send(self, call: Call[T]) -> T:
        """Send one request, retrying only where `should_retry` says it is safe."""
        timeout = self.timeout if call.timeout is None else max(call.timeout, self.timeout)
        attempt = 0
        while True:
            try:
                resp = await self._http.request(call.method, call.path, json=call.body,
                                                params=call.params, headers=self._headers(call),
                                                timeout=timeout)
            except httpx.HTTPError as exc:
                if should_retry(call, attempt, exc, None):
                    await asyncio.sleep(backoff(attempt))
                    attempt += 1
                    continue
                raise transport_error(exc, call) from exc
            if should_retry(call, attempt, None, resp):
                await asyncio.sleep(backoff(attempt))
                attempt += 1
                continue
            return parse_answer(call, resp)

    # --------------------------------------------------------- arms

    async def health(self) -> s.Health:
        return await self.send(Requests.health())

    async def arms(self) -> list[s.ArmSummary]:
        return await self.send(Requests.arms())

    async def arm(self, arm: str) -> s.ArmDetail:
        return await self.send(Requests.arm(arm))

    async def state(self, arm: str) -> s.Sample:
        return await self.send(Requests.state(arm))

    # --------------------------------------------------------- motion

    async def move_joints(self, arm: str, positions: Sequence[float], *,
                          duration: float | None = None, speed: float = 1.0,
                          mode: s.QueueMode = "queue", wait: bool = False) -> s.Motion:
        """Joint-space move (rad / m). 202 with the queued motion, or the final one if `wait`."""
        req = move_joints_model(positions, duration, speed, mode, wait)
        return await self.send(Requests.joints_request("move", arm, req, safe=False))

    async def move_pose(self, arm: str, x: float, y: float, z: float, *,
                        path: Literal["joint", "line"] = "joint", branch: int | None = None,
                        ik_case: Literal["dx_zero", "dx_used"] | None = None,
                        duration: float | None = None, speed: float = 1.0,
                        mode: s.QueueMode = "queue", wait: bool = False) -> s.Motion:
        """Move the tip to (x, y, z) m along a joint-space or straight-line path."""
        req = move_pose_model(x, y, z, path, branch, ik_case, duration, speed, mode, wait)
        return await self.send(Requests.pose_request("move", arm, req, safe=False))

    async def plan_joints(self, arm: str, positions: Sequence[float], *,
                          duration: float | None = None, speed: float = 1.0,
                          mode: s.QueueMode = "queue") -> s.Motion:
        """Preview a joint move: the motion it would be, nothing moves."""
        req = move_joints_model(positions, duration, speed, mode, False)
        return await self.send(Requests.joints_request("plan", arm, req, safe=True))

    async def plan_pose(self, arm: str, x: float, y: float, z: float, *,
                        path: Literal["joint", "line"] = "joint", branch: int | None = None,
                        ik_case: Literal["dx_zero", "dx_used"] | None = None,
                        duration: float | None = None, speed: float = 1.0,
                        mode: s.QueueMode = "queue") -> s.Motion:
        """Preview a pose move (planned duration, target joints, tip path); nothing moves."""
        req = move_pose_model(x, y, z, path, branch, ik_case, duration, speed, mode, False)
        return await self.send(Requests.pose_request("plan", arm, req, safe=True))

    async def motion(self, arm: str, motion_id: str) -> s.Motion:
        return await self.send(Requests.motion(arm, motion_id))

    async def cancel_motion(self, arm: str, motion_id: str) -> s.Motion:
        return await self.send(Requests.cancel_motion(arm, motion_id))

    async def wait_motion(self, arm: str, motion_id: str, timeout: float = 120.0,
                          poll: float = 0.05) -> s.Motion:
        """Poll a motion until it is done, stopped or failed; TimeoutError after `timeout` s."""
        deadline = time.monotonic() + timeout
        while True:
            m = await self.motion(arm, motion_id)
            if m.status in TERMINAL:
                return m
            if time.monotonic() > deadline:
                raise TimeoutError(f"motion {motion_id} still {m.status} after {timeout} s")
            await asyncio.sleep(poll)

    async def stop(self, arm: str) -> s.StopResult:
        return await self.send(Requests.stop(arm))

    async def estop(self, arm: str) -> s.EstopState:
        return await self.send(Requests.estop(arm))

    async def release_estop(self, arm: str) -> s.EstopState:
        return await self.send(Requests.release_estop(arm))

    async def gripper(self, arm: str, value: float) -> s.GripperState:
        """0.0 open .. 1.0 closed; `NoGripper` on an arm without an actuated gripper."""
        return await self.send(Requests.gripper(arm, value))

    async def tare_force(self, arm: str) -> s.ForceTare:
        """The current joint torques become the zero of `torques` and `tip_force`."""
        return await self.send(Requests.tare_force(arm))

    async def clear_tare(self, arm: str) -> s.ForceTare:
        return await self.send(Requests.clear_tare(arm))

    # --------------------------------------------------------- kinematics

    async def forward(self, arm: str, positions: Sequence[float]) -> s.ForwardResult:
        return await self.send(Requests.forward(arm, positions))

    async def inverse(self, arm: str, x: float, y: float, z: float, *,
                      ik_case: Literal["dx_zero", "dx_used"] | None = None,
                      theta3: float | None = None) -> s.InverseResult:
        req = s.InverseRequest(x=x, y=y, z=z, ik_case=ik_case, theta3=theta3)
        return await self.send(Requests.inverse(arm, req))

    async def workspace(self, arm: str, **params: Any) -> s.Workspace:
        return await self.send(Requests.workspace(arm, params))

    # --------------------------------------------------------- rbe3001 pass-through

    async def rbe3001_set_pid(self, arm: str, joints: Sequence[Any]) -> s.SetPidReply:
        """Three setpoints: `PidSetpoint`s, dicts, or bare position ticks."""
        return await self.send(Requests.rbe3001_set_pid(arm, joints))

    async def rbe3001_status(self, arm: str) -> s.Rbe3001Status:
        return await self.send(Requests.rbe3001_status(arm))

    async def rbe3001_set_gain(self, arm: str, axis: int, kp: float, ki: float,
                               kd: float) -> s.Ack:
        return await self.send(Requests.rbe3001_set_gain(arm, axis, kp, ki, kd))

    async def rbe3001_set_claw(self, arm: str, value: float) -> s.Ack:
        return await self.send(Requests.rbe3001_set_claw(arm, value))

    # --------------------------------------------------------- dynamixel pass-through

    async def dxl_ping(self, arm: str, dxl_id: int | None = None) -> s.PingResult:
        return await self.send(Requests.dxl_ping(arm, dxl_id))

    async def dxl_read_register(self, arm: str, dxl_id: int, name: str) -> s.RegisterValue:
        return await self.send(Requests.dxl_read_register(arm, dxl_id, name))

    async def dxl_write_register(self, arm: str, dxl_id: int, name: str,
                                 raw: int) -> s.RegisterValue:
        return await self.send(Requests.dxl_write_register(arm, dxl_id, name, raw))

    async def dxl_sync_read(self, arm: str, name: str, ids: Sequence[int]) -> s.SyncReadResult:
        return await self.send(Requests.dxl_sync_read(arm, name, ids))

    async def dxl_sync_write(self, arm: str, name: str, values: Mapping[int, int]) -> s.Ack:
        return await self.send(Requests.dxl_sync_write(arm, name, values))

    async def dxl_reboot(self, arm: str, dxl_id: int) -> s.Ack:
        return await self.send(Requests.dxl_reboot(arm, dxl_id))

    async def home(self, arm: str, positions: Sequence[float] | None = None) -> s.ArmDetail:
        """Declare the arm's current pose (the profile's home pose without positions)."""
        return await self.send(Requests.home(arm, positions))

    # --------------------------------------------------------- lease

    async def safety(self, arm: str) -> s.Safety:
        """The arm's safety envelope: keep-out zones, floor, speed override."""
        return await self.send(Requests.safety(arm))

    async def set_safety(self, arm: str, **fields: Any) -> s.Safety:
        """Change the envelope (instructor): `zones=[...]`, `floor_z=` (None removes the
        floor), `speed_override=`; fields not given are kept."""
        return await self.send(Requests.set_safety(arm, s.SafetyUpdate(**fields)))

    async def take_lease(self, arm: str) -> s.Lease:
        return await self.send(Requests.take_lease(arm))

    async def renew_lease(self, arm: str, lease_id: str) -> s.Lease:
        return await self.send(Requests.renew_lease(arm, lease_id))

    async def release_lease(self, arm: str, lease_id: str) -> None:
        return await self.send(Requests.release_lease(arm, lease_id))

    # --------------------------------------------------------- classroom

    async def me(self) -> s.Me:
        return await self.send(Requests.me())

    async def join_queue(self, arm: str) -> s.QueueEntry:
        return await self.send(Requests.join_queue(arm))

    async def queue(self, arm: str) -> s.QueueStatus:
        return await self.send(Requests.queue(arm))

    async def queue_entry(self, arm: str, entry_id: str) -> s.QueueEntry:
        return await self.send(Requests.queue_entry(arm, entry_id))

    async def leave_queue(self, arm: str, entry_id: str) -> s.QueueEntry:
        return await self.send(Requests.leave_queue(arm, entry_id))

    async def reorder_queue(self, arm: str, order: Sequence[str]) -> s.QueueStatus:
        """Instructor: every waiting entry's id, in the new order."""
        return await self.send(Requests.reorder_queue(arm, order))

    async def clear_queue(self, arm: str) -> s.QueueStatus:
        return await self.send(Requests.clear_queue(arm))

    async def revoke_lease(self, arm: str) -> None:
        """Instructor: end the arm's lease whoever holds it (and retry a failed hand-off)."""
        return await self.send(Requests.revoke_lease(arm))

    async def audit(self, arm: str | None = None, who: str | None = None,
                    since: float | None = None, until: float | None = None,
                    limit: int = 100) -> list[s.AuditRecord]:
        """Instructor: audit records, newest first."""
        return await self.send(Requests.audit(  # type: ignore[no-any-return]
            {"arm": arm, "who": who, "since": since, "until": until, "limit": limit}))

    async def audit_csv(self, arm: str | None = None, who: str | None = None,
                        since: float | None = None, until: float | None = None,
                        limit: int = 100) -> str:
        """The same as CSV text (a header row, then one row per record)."""
        return await self.send(Requests.audit(  # type: ignore[no-any-return]
            {"arm": arm, "who": who, "since": since, "until": until, "limit": limit}, csv=True))

    @contextlib.asynccontextmanager
    async def queue_turn(self, arm: str, poll: float = 0.25, every: float | None = None,
                         timeout: float | None = None) -> AsyncIterator[LeaseKeeper]:
        """Join the arm's queue, wait for the offer, claim the lease and renew it for the
        duration of the block (its id goes on this client's requests to the arm); on exit
        release it, or leave the queue if the turn never came. The slot ends when the server
        says: then `keeper.error` is set and moves answer 409 `leased`."""
        entry = await self.join_queue(arm)
        deadline = None if timeout is None else time.monotonic() + timeout
        try:
            while turn_pending(arm, entry, deadline, timeout):
                await asyncio.sleep(poll)
                entry = await self.queue_entry(arm, entry.id)
            lease = await self.renew_lease(arm, entry.lease_id or "")  # claims it
        except BaseException:
            with contextlib.suppress(ArmServerError):
                await self.leave_queue(arm, entry.id)
            raise
        async with self._keep(arm, lease, every) as keeper:
            yield keeper

    @contextlib.asynccontextmanager
    async def hold_lease(self, arm: str, every: float | None = None) -> AsyncIterator[LeaseKeeper]:
        """Take the arm's lease, send its id on this client's requests to the arm and renew it in
        the background (every `ttl / 3` s unless `every`); release it on exit."""
        lease = await self.take_lease(arm)
        async with self._keep(arm, lease, every) as keeper:
            yield keeper

    @contextlib.asynccontextmanager
    async def _keep(self, arm: str, lease: s.Lease, every: float | None
                    ) -> AsyncIterator[LeaseKeeper]:
        keeper = LeaseKeeper(lease)
        previous = self.leases.get(arm)
        self.leases[arm] = lease.id
        period = every if every is not None else max(lease.ttl / 3.0, 0.05)

        async def beat() -> None:
            while True:
                await asyncio.sleep(period)
                try:
                    keeper.lease = await self.renew_lease(arm, lease.id)
                    keeper.renewals += 1
                except ArmServerError as exc:
                    keeper.error = exc
                    log.warning("%s: lease %s not renewed: %s", arm, lease.id, exc)
                    if exc.status != 0:
                        return

        task = asyncio.create_task(beat(), name=f"lease:{arm}")
        try:
            yield keeper
        finally:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task
            if previous is None:
                self.leases.pop(arm, None)
            else:
                self.leases[arm] = previous
            with contextlib.suppress(ArmServerError):
                await self.release_lease(arm, lease.id)

    # --------------------------------------------------------- telemetry

    async def telemetry_messages(self, arm: str, rate: float | None = None
                                 ) -> AsyncIterator[s.TelemetryMessage | s.EventMessage]:
        """Every WebSocket message, parsed: telemetry batches (with `dropped`) and events."""
        from websockets.asyncio.client import connect
        from websockets.exceptions import ConnectionClosed, InvalidHandshake

        headers = {"Authorization": f"Bearer {self.token}"} if self.token else None
        url = ws_url(self.base_url, arm, rate, None)
        try:
            ws = await connect(url, additional_headers=headers, open_timeout=self.timeout,
                               max_size=2 ** 24)
        except (InvalidHandshake, OSError, TimeoutError) as exc:
            raise ws_handshake_error(exc) from exc
        try:
            while True:
                try:
                    raw = await ws.recv()
                except ConnectionClosed as exc:
                    err = ws_close_error(exc)
                    if err is not None:
                        raise err from exc
                    return
                yield parse_ws_message(raw)
        finally:
            await ws.close()

    async def telemetry(self, arm: str, rate: float | None = None, events: bool = False
                        ) -> AsyncIterator[s.Sample | s.EventMessage]:
        """Samples in `seq` order, each once (a sample repeated across messages is skipped);
        events too if `events`. A gap in `seq` means the server dropped samples for this
        client (see `telemetry_messages` for the `dropped` counts)."""
        last = -1
        async for msg in self.telemetry_messages(arm, rate):
            if isinstance(msg, s.EventMessage):
                if events:
                    yield msg
                continue
            for sample in msg.samples:
                if sample.seq > last:
                    last = sample.seq
                    yield sample


@dataclass
class LeaseKeeper:
    """A held lease: the latest `Lease`, how often it was renewed, the last renewal error."""

    lease: s.Lease
    renewals: int = 0
    error: ArmServerError | None = None

    @property
    def id(self) -> str:
        return self.lease.id


def __getattr__(name: str) -> Any:
    if name == "ArmClient":  # lazy: client_sync imports this module
        from app.client_sync import ArmClient
        return ArmClient
    raise AttributeError(name)
