"""The arms: what an arm is and says about itself (summary, detail, joints, chain, link,
capabilities, faults, force) and the homing request."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from app.schemas.common import Bool, Finite, Model

# ---------------------------------------------------------------- arms


class Vec3(Model):
    x: Finite
    y: Finite
    z: Finite


class Tip(Vec3):
    """A tool tip: its position (m, base frame) and, for an arm with a wrist, the tool's pitch
    (rad, from the horizontal in the arm's vertical plane; API.md "Wrist pitch"). Absent (not
    null) for arms without a wrist."""

    pitch: Finite | None = Field(None, exclude_if=lambda v: v is None,
                                 description="rad, arms with a wrist only")


class ChainStep(Model):
    """One elementary transform of the joint chain (app/arms/model.py `ChainStep`)."""

    kind: Literal["rotate", "translate"]
    axis: list[float] = Field(min_length=3, max_length=3, description="unit axis in the "
                              "current frame")
    offset: float = Field(description="rad or m, added to the joint's position")
    joint: int | None = Field(description="index of the joint that drives it, or null: fixed")
    point: str | None = Field(description="the body point at this frame's origin, or null")


class ArmChain(Model):
    """How to draw the arm: start at the base (origin) and apply `steps` in order, each in
    the frame the previous ones left; every step with a `point` gives a body point (`points`,
    base first, tip last; the same points the safety envelope checks)."""

    points: list[str]
    side_axis: int = Field(description="the horizontal axis (0 x, 1 y) a side view plots "
                           "against z")
    steps: list[ChainStep]


class JointInfo(Model):
    name: str
    kind: Literal["revolute", "prismatic"]
    min: float
    max: float
    max_velocity: float
    max_acceleration: float


class LinkStatus(Model):
    kind: Literal["sim", "hid", "serial"]
    address: str
    state: Literal["connecting", "up", "down"]
    connected: bool
    last_error: str | None = None


class Capabilities(Model):
    gripper: bool
    force_sensing: bool
    protocol: str = Field(description="what the pass-through routes speak: rbe3001, dynamixel")
    pitch: bool = Field(False, exclude_if=lambda v: not v, description="true: poses carry the "
                        "tool's `pitch` (a wrist); absent for arms without one")
    paths: list[Literal["joint", "line"]] = ["joint", "line"]


class ArmSummary(Model):
    name: str
    model: str
    description: str
    link: LinkStatus
    capabilities: Capabilities


class Fault(Model):
    """A servo's hardware fault (Dynamixel Hardware Error Status, address 70)."""

    joint: str
    servo: int
    bits: list[str] = Field(description="input_voltage, overheating, motor_encoder, "
                            "electrical_shock, overload")
    raw: int
    advice: str


class ForceInfo(Model):
    """What the arm's `torques` and `tip_force` are worth (API.md "Force")."""

    source: Literal["strain_gauges", "servo_load"]
    calibrated: bool = Field(description="false: the conversion constants are placeholders or "
                             "estimates, the readings are not a measurement")
    note: str
    tare: list[float] | None = Field(None, description="joint torques subtracted from every "
                                     "reading since the last tare (N m or N), or null")
    max_condition_number: float = Field(description="the singularity rule: tip_force is null "
                                        "where the Jacobian's condition number exceeds this")
    condition_number: float | None = Field(None, description="at the latest sample (null if "
                                           "none, or infinite)")
    tip_force_unavailable: str | None = Field(None, description="why tip_force is null at the "
                                              "latest sample, or null")
    gravity_compensated: bool = Field(False, description="a gravity fit is subtracted from "
                                      "`torques` and `tip_force` at every pose (POST "
                                      ".../calibration/gravity); the tare then zeroes the "
                                      "tool's load")


class ForceTare(Model):
    joints: list[str]
    offsets: list[float] | None = Field(description="the torques now taken as zero (N m or N, "
                                        "per joint), null once cleared")


class TelemetryStats(Model):
    """The arm's telemetry since the server started (API.md "Telemetry")."""

    subscribers: int = Field(description="WebSocket clients and other subscribers now")
    published: int = Field(description="samples published")
    dropped: int = Field(description="samples subscribers lost to their backlog bound, all "
                         "together (each was told in its `dropped`): 0, every subscriber got "
                         "every sample")


class ArmDetail(ArmSummary):
    joints: list[JointInfo]
    geometry: dict[str, float]
    estop: bool
    poll_hz: float
    faults: list[Fault] = Field(default_factory=list, description="empty when healthy")
    homed: list[bool] = Field(default_factory=list, description="one flag per joint")
    calibrated: list[bool] = Field(default_factory=list, description="one flag per joint: "
                                   "its zero is known on this hardware (API.md Calibration)")
    torque: list[bool] = Field(default_factory=list, description="one flag per joint: its "
                               "servo holds torque; false where it was switched off through "
                               "this server (PUT .../torque, a teleoperation session's leader, "
                               "a pass-through Torque Enable 0) and not on again, while "
                               "everything that moves the arm is 409 `torque_off` (an addition "
                               "to API.md)")
    firmware: str | None = Field(None, description="what the server found out about the "
                                 "device's firmware at connect, and what to do, where it "
                                 "matters (e.g. an rbe3001 build without STATUS)")
    force: ForceInfo | None = None
    chain: ArmChain | None = Field(None, description="the joint chain, to draw the arm")
    telemetry: TelemetryStats | None = None


class HomeRequest(Model):
    positions: list[Finite] | None = Field(
        None, min_length=1, max_length=16,
        description="the arm's current physical joint positions (rad, m); none: the "
        "profile's home pose")


class TorqueRequest(Model):
    """The joints' torque off (the arm free to be moved by hand) or on again, holding where
    it is (an addition to API.md)."""

    on: Bool
    load_supported: Bool = Field(
        False, description="the joints that fall without torque (the profile's "
        "`falls_without_torque`: the angler's z winch, an OpenManipulator-X's shoulder, elbow "
        "and wrist) are held by hand or rest: without it torque off is 409 `in_use` (gravity "
        "would move them where no planned move may go), as a reboot's")


class TorqueState(Model):
    arm: str
    on: bool = Field(description="the joints' torque as just switched")
