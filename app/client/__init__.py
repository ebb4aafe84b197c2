"""Python client of the arm server's public contract (../shared/API.md), on httpx and websockets.

`AsyncArmClient` (asyncio, `app.client.aio`) and `ArmClient` (blocking, `app.client.sync`, made
from the async class) have the same methods, one per route, and return the contract's own
pydantic models (`app.schemas`). Errors are `ArmServerError` and its subclasses
(`app.client.errors`, mapped from the server's table `app.errors.CODES`); routes are built in
`app.client.routes`, answers read and retries decided in `app.client.core`. The command line
(`armserver call` / `watch`) is `app.client.cli`.

    from app.client import ArmClient
    with ArmClient("http://127.0.0.1:8000") as c:
        c.move_pose("rbe3001", 0.15, 0.0, 0.12, wait=True)
"""

from __future__ import annotations

from app.client.aio import AsyncArmClient
from app.client.core import (
    BACKOFF_MAX_S,
    BACKOFF_S,
    RETRIES,
    TERMINAL,
    WS_CLOSE,
    LeaseKeeper,
    parse_answer,
    should_retry,
    ws_close_error,
    ws_url,
)
from app.client.errors import (
    ERRORS,
    ArmServerError,
    BadRequest,
    Busy,
    Conflict,
    ConnectionFailed,
    DeviceError,
    DeviceTimeout,
    EstopLatched,
    Fault,
    Forbidden,
    Gone,
    InternalError,
    InvalidRequest,
    JointLimit,
    KeepOut,
    Leased,
    LinkDown,
    NoGripper,
    NotCalibrated,
    NotFound,
    NotHomed,
    NotSupported,
    QueueTurnLost,
    TorqueOff,
    Unauthorized,
    Unavailable,
    Unreachable,
    VelocityLimit,
    error_from_body,
    make_error,
)
from app.client.routes import API, LEASE_HEADER, WAIT_TIMEOUT_S, Call, Requests
from app.client.sync import ArmClient

#: The same blocking client under the name that says so.
SyncArmClient = ArmClient

__all__ = [
    "API", "BACKOFF_MAX_S", "BACKOFF_S", "ERRORS", "LEASE_HEADER", "RETRIES", "TERMINAL",
    "WAIT_TIMEOUT_S", "WS_CLOSE", "ArmClient", "ArmServerError", "AsyncArmClient", "BadRequest",
    "Busy", "Call", "Conflict", "ConnectionFailed", "DeviceError", "DeviceTimeout",
    "EstopLatched", "Fault", "Forbidden", "Gone", "InternalError", "InvalidRequest",
    "JointLimit", "KeepOut", "LeaseKeeper", "Leased", "LinkDown", "NoGripper",
    "NotCalibrated", "NotFound", "NotHomed", "NotSupported", "QueueTurnLost", "Requests",
    "SyncArmClient", "TorqueOff",
    "Unauthorized", "Unavailable", "Unreachable", "VelocityLimit", "error_from_body",
    "make_error", "parse_answer", "should_retry", "ws_close_error", "ws_url",
]
