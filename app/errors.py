"""Every error code of the server, once: `CODES`, the table the rest is made from.

Each row says a code's HTTP status, what it means, the server exception that carries it and
the client exception (`app.client`) it becomes. From this table come:

- the server's exceptions below: a class names its `code`; its `status_code` is the table's (a
  class whose code is not in the table fails at import);
- the OpenAPI error descriptions (`app.web.routes.common.errors`, the `ErrorBody.code` enum);
- the client's error classes for each code (`app.client.errors`).

Routes never build error bodies by hand: they raise one of these and the handler in
`app.web.factory` renders `{"detail": ..., "code": ...}`. `tests/test_errors.py` walks every raise
site and every code literal in app/ against the table.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class ErrorCode:
    """One row of the table."""

    code: str
    #: The HTTP status it is answered with; None for a code that only ends a motion (a failed
    #: motion's `code`, a `motion_ended` / `watchdog` event), never an HTTP answer.
    status: int | None
    #: The server exception class (in this module) that carries it.
    exception: str
    #: The client exception class (in `app.client.errors`) it is raised as.
    client: str
    meaning: str


_ROWS: tuple[tuple[str, int | None, str, str, str], ...] = (
    # code, status, server exception, client exception, meaning
    ("bad_request", 400, "BadRequest", "BadRequest", "the HTTP request is malformed"),
    ("bad_host", 400, "BadHost", "BadRequest",
     "the Host header is not a name this server is bound to (ARMSERVER_ALLOWED_HOSTS)"),
    ("http_error", 400, "HttpError", "BadRequest",
     "another refusal of the HTTP layer (the answer's status says which)"),
    ("unauthorized", 401, "Unauthorized", "Unauthorized", "missing or unknown bearer token"),
    ("forbidden", 403, "Forbidden", "Forbidden", "the token's role may not do this"),
    ("cross_origin", 403, "CrossOrigin", "Forbidden",
     "a page from another origin may not change anything (ARMSERVER_CORS_ORIGINS)"),
    ("not_found", 404, "NotFound", "NotFound", "no such resource"),
    ("unknown_arm", 404, "UnknownArm", "NotFound", "no arm of that name"),
    ("unknown_motion", 404, "UnknownMotion", "NotFound", "no motion of that id was ever issued"),
    ("unknown_lease", 404, "UnknownLease", "NotFound",
     "no lease of that id (released, lapsed or never issued)"),
    ("unknown_entry", 404, "UnknownEntry", "NotFound", "no queue entry of that id"),
    ("method_not_allowed", 405, "MethodNotAllowed", "BadRequest",
     "the path does not take that HTTP method"),
    ("conflict", 409, "Conflict", "Conflict", "the arm's state does not allow this now"),
    ("estop_latched", 409, "EstopLatched", "EstopLatched",
     "the emergency stop is latched: release it before moving"),
    ("busy", 409, "Busy", "Busy",
     "a motion runs, or the motion or device request queue is full: try again later"),
    ("no_gripper", 409, "NoGripper", "NoGripper", "the arm has no actuated gripper"),
    ("leased", 409, "Leased", "Leased",
     "another client holds the arm's control lease (send yours as X-Arm-Lease)"),
    ("not_supported", 409, "NotSupported", "NotSupported",
     "the arm type does not do this (e.g. a Dynamixel command to the rbe3001)"),
    ("no_force_sensing", 409, "NoForceSensing", "NotSupported", "the arm senses no joint torques"),
    ("fault", 409, "Fault", "Fault", "a servo reports a hardware fault: reboot it"),
    ("not_homed", 409, "NotHomed", "NotHomed", "a joint lost its zero: home the arm first"),
    ("not_calibrated", 409, "NotCalibrated", "NotCalibrated",
     "a joint's zero is not known on this hardware: calibrate it first (POST "
     "/api/v1/arms/{arm}/calibration)"),
    ("already_homed", 409, "AlreadyHomed", "Conflict",
     "the arm knows where it is: an instructor re-homes it, or un-home it first (DELETE /home)"),
    ("torque_off", 409, "TorqueOff", "TorqueOff", "a joint's servo holds no torque"),
    ("in_use", 409, "InUse", "Conflict",
     "the driver relies on this register: pass-through may not write it"),
    ("already_queued", 409, "AlreadyQueued", "Conflict",
     "the caller is in the arm's queue already"),
    ("different_workers", 409, "DifferentWorkers", "Conflict",
     "a lab's recording names arms or cameras on different worker processes: give the arms "
     "recorded together one `worker = K` in the config"),
    ("port_in_use", 409, "PortInUse", "Conflict",
     "the port is the link of an arm this server owns (the detail names it): nothing else "
     "touches it"),
    ("no_servo", 409, "NoServo", "Conflict",
     "servo set-up: no servo to set up answers on the port (power, cable, adapter?)"),
    ("several_servos", 409, "SeveralServos", "Conflict",
     "servo set-up: more than one servo to set up, or two on one ID: connect one at a time"),
    ("id_in_use", 409, "IdInUse", "Conflict",
     "servo set-up: the profile gives that joint's ID to another joint too"),
    ("gone", 410, "Gone", "Gone", "the resource existed but is no longer kept"),
    ("motion_expired", 410, "MotionExpired", "Gone",
     "a motion id this server issued but no longer keeps"),
    ("too_large", 413, "TooLarge", "BadRequest", "the request body is over max_body_bytes"),
    ("unsupported_media_type", 415, "UnsupportedMediaType", "BadRequest",
     "the body's content type is not JSON"),
    ("invalid_request", 422, "InvalidRequest", "InvalidRequest",
     "a body or parameter the server cannot accept"),
    ("invalid_json", 422, "InvalidJson", "InvalidRequest", "the body is not valid JSON"),
    ("invalid_order", 422, "InvalidOrder", "InvalidRequest",
     "a queue order that is not every waiting entry once"),
    ("unknown_register", 422, "UnknownRegister", "InvalidRequest",
     "no control-table item of that name"),
    ("unknown_id", 422, "UnknownId", "InvalidRequest", "that servo id is not one of the arm's"),
    ("read_only", 422, "ReadOnly", "InvalidRequest", "the register is read-only"),
    ("out_of_range", 422, "OutOfRange", "InvalidRequest",
     "a raw value outside the register's range"),
    ("unreachable", 422, "Unreachable", "Unreachable",
     "no inverse-kinematics solution, or the path leaves the workspace"),
    ("joint_limit", 422, "JointLimit", "JointLimit", "a target or path beyond a joint's limits"),
    ("velocity_limit", 422, "VelocityLimit", "VelocityLimit", "a path faster than a joint may go"),
    ("keep_out", 422, "KeepOut", "KeepOut",
     "the path enters a keep-out zone or goes below the floor"),
    ("device_error", 502, "DeviceError", "DeviceError", "the device answered with an error"),
    ("corrupt_reply", 502, "CorruptReply", "DeviceError", "the device's reply was corrupt"),
    ("internal_error", 502, "InternalError", "InternalError",
     "a server bug (logged with its traceback): please report it"),
    ("link_down", 503, "LinkDown", "LinkDown", "the server cannot talk to the arm now"),
    ("shutting_down", 503, "ShuttingDown", "Unavailable",
     "the server is shutting down: no new motion"),
    ("store_unavailable", 503, "StoreUnavailable", "Unavailable",
     "the audit store cannot be read now"),
    ("camera_down", 503, "CameraDown", "Unavailable",
     "the camera gives no frames now (its last error says why); it is being reconnected"),
    ("recording_failed", 503, "RecordingFailed", "Unavailable",
     "a recording's episode could not be written (disk full or another I/O error); the "
     "dataset keeps every earlier episode"),
    ("device_timeout", 504, "DeviceTimeout", "DeviceTimeout",
     "the device did not answer in time"),
    ("not_settled", None, "NotSettled", "ArmServerError",
     "a motion ended without its joints settling at the target"),
    ("internal", None, "MotionInternal", "ArmServerError", "a motion ended on a server bug"),
)

#: code -> its row.
CODES: dict[str, ErrorCode] = {r[0]: ErrorCode(*r) for r in _ROWS}
assert len(CODES) == len(_ROWS), "a code appears twice in the table"


def codes_with_status(status: int) -> list[ErrorCode]:
    return [c for c in CODES.values() if c.status == status]


def describe(status: int) -> str:
    """An OpenAPI description of an error status: every code the table gives it."""
    return "; ".join(f"`{c.code}`: {c.meaning}" for c in codes_with_status(status))


class ArmError(Exception):
    """Base of every error the server reports to a client. Raise a subclass (or give a `code`
    of the table): the base's own code says a bug, as the last-resort handler does."""

    code: str = "internal_error"
    status_code: int = 502

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        if "code" not in cls.__dict__:
            return
        row = CODES.get(cls.code)
        if row is None:
            raise TypeError(f"{cls.__name__}.code {cls.code!r} is not in app.errors.CODES")
        # A motion-only code is never answered; were it raised, it would be a conflict.
        cls.status_code = row.status if row.status is not None else 409
        if cls.__doc__ is None:
            cls.__doc__ = f"`{row.code}` ({row.status or 'motion'}): {row.meaning}."

    def __init__(self, detail: str, *, code: str | None = None,
                 status_code: int | None = None) -> None:
        super().__init__(detail)
        self.detail = detail
        if code is not None:
            self.code = code
            row = CODES.get(code)
            if status_code is None and row is not None and row.status is not None:
                status_code = row.status
        if status_code is not None:
            self.status_code = status_code


# ---------------------------------------------------------------- 400, 401, 403


class BadRequest(ArmError):
    code = "bad_request"


class BadHost(BadRequest):
    code = "bad_host"


class HttpError(BadRequest):
    code = "http_error"


class Unauthorized(ArmError):
    code = "unauthorized"


class Forbidden(ArmError):
    code = "forbidden"


class CrossOrigin(Forbidden):
    code = "cross_origin"


# ---------------------------------------------------------------- 404, 405, 410


class NotFound(ArmError):
    code = "not_found"


class UnknownArm(NotFound):
    code = "unknown_arm"


class UnknownMotion(NotFound):
    code = "unknown_motion"


class UnknownLease(NotFound):
    code = "unknown_lease"


class UnknownEntry(NotFound):
    code = "unknown_entry"


class MethodNotAllowed(ArmError):
    code = "method_not_allowed"


class Gone(ArmError):
    code = "gone"


class MotionExpired(Gone):
    """A motion id this server issued but no longer keeps (the detail says what is known)."""

    code = "motion_expired"


# ---------------------------------------------------------------- 409


class Conflict(ArmError):
    code = "conflict"


class EstopLatched(Conflict):
    code = "estop_latched"


class Busy(Conflict):
    code = "busy"


class NoGripper(Conflict):
    code = "no_gripper"


class Leased(Conflict):
    code = "leased"


class NotSupported(Conflict):
    code = "not_supported"


class NoForceSensing(NotSupported):
    code = "no_force_sensing"


class Fault(Conflict):
    """A servo reports a hardware fault (Dynamixel Hardware Error Status): nothing moves until
    it is cleared (reboot)."""

    code = "fault"


class NotHomed(Conflict):
    """A joint that loses its zero at power-up has not been homed (POST /home)."""

    code = "not_homed"


class NotCalibrated(Conflict):
    """A joint whose zero the hardware does not know has no calibration on this hardware (POST
    /calibration declares the pose the arm is at)."""

    code = "not_calibrated"


class AlreadyHomed(Conflict):
    """A home declaration on an arm whose joints are all homed (it would move its limits)."""

    code = "already_homed"


class TorqueOff(Conflict):
    """A joint's servo holds no torque: it cannot reach, or be held at, a target."""

    code = "torque_off"


class InUse(Conflict):
    code = "in_use"


class DifferentWorkers(Conflict):
    code = "different_workers"


class PortInUse(Conflict):
    code = "port_in_use"


class NoServo(Conflict):
    code = "no_servo"


class SeveralServos(Conflict):
    code = "several_servos"


class IdInUse(Conflict):
    code = "id_in_use"


class AlreadyQueued(Conflict):
    code = "already_queued"


# ---------------------------------------------------------------- 413, 415, 422


class TooLarge(ArmError):
    code = "too_large"


class UnsupportedMediaType(ArmError):
    code = "unsupported_media_type"


class InvalidRequest(ArmError):
    code = "invalid_request"


class InvalidJson(InvalidRequest):
    code = "invalid_json"


class InvalidOrder(InvalidRequest):
    code = "invalid_order"


class UnknownRegister(InvalidRequest):
    code = "unknown_register"


class UnknownId(InvalidRequest):
    code = "unknown_id"


class ReadOnly(InvalidRequest):
    code = "read_only"


class OutOfRange(InvalidRequest):
    code = "out_of_range"


class Unreachable(ArmError):
    code = "unreachable"


class JointLimit(ArmError):
    code = "joint_limit"


class VelocityLimit(ArmError):
    code = "velocity_limit"


class KeepOut(ArmError):
    code = "keep_out"


# ---------------------------------------------------------------- 5xx


class DeviceError(ArmError):
    """The device answered, but with an error (e.g. a Dynamixel status error byte)."""

    code = "device_error"


class CorruptReply(DeviceError):
    code = "corrupt_reply"


class InternalError(ArmError):
    code = "internal_error"


class LinkDown(ArmError):
    code = "link_down"


class ShuttingDown(ArmError):
    code = "shutting_down"


class StoreUnavailable(ArmError):
    code = "store_unavailable"


class CameraDown(ArmError):
    code = "camera_down"


class RecordingFailed(ArmError):
    code = "recording_failed"


class DeviceTimeout(ArmError):
    code = "device_timeout"


# ---------------------------------------------------------------- motion-only codes


class NotSettled(ArmError):
    code = "not_settled"


class MotionInternal(ArmError):
    code = "internal"
