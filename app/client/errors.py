"""The client's exceptions, one per kind of refusal, mapped from the server's error table.

`app.errors.CODES` names, for each code the server answers, the client class it becomes here
(`ErrorCode.client`): `ERRORS` is built from that table, so a code added to the server is
mapped the moment it is in the table, and a row naming a class this module lacks fails at
import. Two codes are the client's own: `connection_failed` (status 0: no answer at all) and
`turn_lost` (a queue entry ended before its turn).
"""

from __future__ import annotations

import json
from typing import Any

from app.errors import CODES


class ArmServerError(Exception):
    """The server refused a request: `code` is its stable machine code, `status` the HTTP status."""

    code = "error"

    def __init__(self, code: str, detail: Any, status: int) -> None:
        self.code = code
        self.detail = detail
        self.status = status
        super().__init__(f"{status} {code}: {detail}")


class BadRequest(ArmServerError):
    """bad_request, bad_host, too_large, method_not_allowed, ...: the HTTP layer refused it."""


class Unauthorized(ArmServerError):
    """unauthorized: no or an unknown token."""


class Forbidden(ArmServerError):
    """forbidden, cross_origin: the token's role (or the page's origin) may not do this."""


class NotFound(ArmServerError):
    """unknown_arm, unknown_motion, unknown_lease, unknown_entry, not_found."""


class Gone(NotFound):
    """motion_expired: a motion id the server issued but no longer keeps (a `NotFound` too)."""


class Conflict(ArmServerError):
    """conflict, in_use, already_queued: the arm's state does not allow this now."""


class EstopLatched(Conflict):
    """estop_latched: release it with `release_estop` before moving."""


class Busy(Conflict):
    """busy: a motion runs, or the motion (or a device request) queue is full."""


class NoGripper(Conflict):
    """no_gripper: the arm has no actuated gripper."""


class Leased(Conflict):
    """leased: another client holds the arm's control lease."""


class NotSupported(Conflict):
    """not_supported, no_force_sensing: e.g. a Dynamixel command to the rbe3001."""


class Fault(Conflict):
    """fault: a servo reports a hardware fault; reboot it."""


class NotHomed(Conflict):
    """not_homed: a joint lost its zero; home the arm."""


class NotCalibrated(Conflict):
    """not_calibrated: a joint's zero is not known on this hardware; calibrate the arm."""


class TorqueOff(Conflict):
    """torque_off: a joint's servo holds no torque."""


class QueueTurnLost(Conflict):
    """turn_lost: the queue entry ended (offer expired, removed, cleared) before its lease was
    claimed."""


class InvalidRequest(ArmServerError):
    """invalid_request, invalid_json, out_of_range, ...: a body or parameter the server could
    not accept."""


class Unreachable(ArmServerError):
    """unreachable: no IK solution, or a line leaves the workspace."""


class JointLimit(ArmServerError):
    """joint_limit: a target or path outside a joint's limits."""


class VelocityLimit(ArmServerError):
    """velocity_limit: a path faster than a joint may go."""


class KeepOut(ArmServerError):
    """keep_out: the path enters a keep-out zone or goes below the floor."""


class DeviceError(ArmServerError):
    """device_error, corrupt_reply: the device answered with an error."""


class InternalError(ArmServerError):
    """internal_error: a server bug (it is logged there); please report it."""


class Unavailable(ArmServerError):
    """shutting_down, store_unavailable (and link_down): the server cannot do this now."""


class LinkDown(Unavailable):
    """link_down: the server cannot talk to the arm now."""


class DeviceTimeout(ArmServerError):
    """device_timeout: the device did not answer in time."""


class ConnectionFailed(ArmServerError):
    """connection_failed: the server could not be reached (or the connection broke): status 0."""


def _table() -> dict[str, type[ArmServerError]]:
    here = globals()
    out: dict[str, type[ArmServerError]] = {}
    for row in CODES.values():
        cls = here.get(row.client)
        if not (isinstance(cls, type) and issubclass(cls, ArmServerError)):
            raise TypeError(f"app.errors: {row.code} names client class {row.client!r}, "
                            "which app.client.errors does not define")
        out[row.code] = cls
    out["connection_failed"] = ConnectionFailed
    out["turn_lost"] = QueueTurnLost
    return out


#: code -> client exception class, from the server's table (plus the client's own two codes).
ERRORS: dict[str, type[ArmServerError]] = _table()

#: The code of an error answer that carries none (a proxy's page): by status.
STATUS_CODES = {400: "bad_request", 401: "unauthorized", 403: "forbidden", 404: "not_found",
                409: "conflict", 422: "invalid_request", 503: "link_down",
                504: "device_timeout"}


def make_error(code: str, detail: Any, status: int) -> ArmServerError:
    return ERRORS.get(code, ArmServerError)(code, detail, status)


def error_from_body(status: int, body: bytes | str) -> ArmServerError:
    """The exception for an error answer: the body's `code` if it has one, else one by status."""
    code, detail = STATUS_CODES.get(status, "error"), None
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
