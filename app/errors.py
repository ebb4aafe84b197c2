"""One error root for the whole server, each with a stable machine code and HTTP status.

Routes never build error bodies by hand: they raise one of these and the handler in
`app.main` renders `{"detail": ..., "code": ...}`.
"""

from __future__ import annotations


class ArmError(Exception):
    """Base of every error the server reports to a client."""

    code = "error"
    status_code = 400

    def __init__(self, detail: str, *, code: str | None = None, status_code: int | None = None):
        super().__init__(detail)
        self.detail = detail
        if code is not None:
            self.code = code
        if status_code is not None:
            self.status_code = status_code


class NotFound(ArmError):
    code = "not_found"
    status_code = 404


class UnknownArm(NotFound):
    code = "unknown_arm"


class UnknownMotion(NotFound):
    code = "unknown_motion"


class Gone(ArmError):
    code = "gone"
    status_code = 410


class MotionExpired(Gone):
    """A motion id this server issued but no longer keeps (the detail says what is known)."""

    code = "motion_expired"


class InvalidRequest(ArmError):
    code = "invalid_request"
    status_code = 422


class Unreachable(ArmError):
    code = "unreachable"
    status_code = 422


class JointLimit(ArmError):
    code = "joint_limit"
    status_code = 422


class VelocityLimit(ArmError):
    code = "velocity_limit"
    status_code = 422


class Conflict(ArmError):
    status_code = 409
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


class Fault(Conflict):
    """A servo reports a hardware fault (Dynamixel Hardware Error Status): nothing moves until
    it is cleared (reboot)."""

    code = "fault"


class NotHomed(Conflict):
    """A joint that loses its zero at power-up has not been homed (POST /home)."""

    code = "not_homed"


class TorqueOff(Conflict):
    """A joint's servo holds no torque: it cannot reach, or be held at, a target."""

    code = "torque_off"


class Unauthorized(ArmError):
    code = "unauthorized"
    status_code = 401


class Forbidden(ArmError):
    code = "forbidden"
    status_code = 403


class DeviceError(ArmError):
    """The device answered, but with an error (e.g. a Dynamixel status error byte)."""

    code = "device_error"
    status_code = 502


class CorruptReply(DeviceError):
    code = "corrupt_reply"


class LinkDown(ArmError):
    code = "link_down"
    status_code = 503


class DeviceTimeout(ArmError):
    code = "device_timeout"
    status_code = 504


class QueueFull(ArmError):
    code = "busy"
    status_code = 503
