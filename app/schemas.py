"""Pydantic models of the public contract (../shared/API.md). SI units throughout,
except under the protocol pass-through models, whose raw fields say so in their names.

Every float is finite (NaN and infinities are refused with 422), every list has bounds.
The client (`app.client`) imports these same models.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from app.config import KeepOutBox
from app.errors import CODES

#: Numbers are strict (issue 11.10): `true` or `"1"` is not a number (it moved a joint to 1 rad);
#: an integer is a number. Integers are strict likewise: `true`, `"1"` and `1.0` are refused.
Finite = Annotated[float, Field(allow_inf_nan=False, strict=True)]
Unit = Annotated[float, Field(ge=0.0, le=1.0, allow_inf_nan=False, strict=True)]
Int = Annotated[int, Field(strict=True)]
Bool = Annotated[bool, Field(strict=True)]
Duration = Annotated[float, Field(gt=0.0, le=600.0, allow_inf_nan=False, strict=True)]
Speed = Annotated[float, Field(gt=0.0, le=1.0, allow_inf_nan=False, strict=True)]
DxlIdValue = Annotated[int, Field(ge=0, le=252, strict=True)]


class Model(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


# ---------------------------------------------------------------- errors


class ErrorBody(Model):
    detail: str | list[dict[str, object]]
    code: str = Field(description="a stable machine code of the error table (`app.errors`): "
                      + "; ".join(f"`{c.code}` ({c.status}) {c.meaning}"
                                  for c in CODES.values() if c.status is not None),
                      json_schema_extra={"enum": [c for c, r in CODES.items()
                                                  if r.status is not None]})


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


class ForceTare(Model):
    joints: list[str]
    offsets: list[float] | None = Field(description="the torques now taken as zero (N m or N, "
                                        "per joint), null once cleared")


class ArmDetail(ArmSummary):
    joints: list[JointInfo]
    geometry: dict[str, float]
    estop: bool
    poll_hz: float
    faults: list[Fault] = Field(default_factory=list, description="empty when healthy")
    homed: list[bool] = Field(default_factory=list, description="one flag per joint")
    force: ForceInfo | None = None
    chain: ArmChain | None = Field(None, description="the joint chain, to draw the arm")


class HomeRequest(Model):
    positions: list[Finite] | None = Field(
        None, min_length=1, max_length=16,
        description="the arm's current physical joint positions (rad, m); none: the "
        "profile's home pose")


class StoreStatus(Model):
    ok: bool
    path: str
    pending: int = Field(description="changes kept in memory until the database takes them")
    error: str | None = None


class MqttStatus(Model):
    """The MQTT bridge (API.md "Lab-wide telemetry over MQTT")."""

    state: Literal["connecting", "up", "down", "refused"] = Field(
        description="`refused`: the broker refused our credentials or client id")
    broker: str = Field(description="the broker's URL, without the password")
    prefix: str
    rate_hz: float
    last_error: str | None = None
    connects: int = Field(description="successful connections since the server started")
    published: int = Field(description="messages handed to the broker")
    dropped_samples: int = Field(description="samples not sent (broker away or too slow)")
    dropped_events: int
    tick_cpu_s: float = Field(0.0, description="CPU time the bridge spent publishing (its "
                              "ticks: collect, build, queue, write), s")


class Health(Model):
    status: Literal["ok", "degraded"]
    arms: dict[str, LinkStatus]
    auth: bool
    store: StoreStatus | None = None
    mqtt: MqttStatus | None = Field(None, description="present when ARMSERVER_MQTT_URL is set")


# ---------------------------------------------------------------- telemetry


class MotionBrief(Model):
    id: str
    status: Literal["queued", "running", "done", "stopped", "failed"]
    progress: float


class Sample(Model):
    """One device sample, as in `/state` and in every telemetry message."""

    seq: int
    time: float = Field(description="Unix time the device sample was taken, s")
    positions: list[float]
    velocities: list[float]
    torques: list[float] | None = None
    tip: Tip
    tip_velocity: Vec3
    tip_force: Vec3 | None = None
    gripper: float | None = None
    motion: MotionBrief | None = None
    estop: bool = False
    link: Literal["connecting", "up", "down"] = "up"
    stale: bool = False
    faults: list[Fault] = Field(default_factory=list)
    homed: list[bool] = Field(default_factory=list)


class TelemetryMessage(Model):
    type: Literal["telemetry"] = "telemetry"
    arm: str
    samples: list[Sample]
    dropped: int = 0


class EventMessage(Model):
    type: Literal["event"] = "event"
    arm: str
    event: str = Field(description="motion_started, motion_ended, estop, estop_released, "
                       "link_lost, link_back, lease_expired, watchdog")
    time: float
    data: dict[str, object] = {}


# ---------------------------------------------------------------- motion

QueueMode = Literal["queue", "replace"]


class MoveJoints(Model):
    positions: list[Finite] = Field(min_length=1, max_length=16)
    duration: Duration | None = None
    speed: Speed = 1.0
    mode: QueueMode = "queue"
    wait: Bool = False


class MovePose(Model):
    x: Finite
    y: Finite
    z: Finite
    pitch: Finite | None = Field(None, description="the tool's pitch, rad (arms with a wrist; "
                                 "422 `unreachable` on an arm without one); none: the arm's "
                                 "choice")
    path: Literal["joint", "line"] = "joint"
    branch: Int | None = Field(None, ge=0, le=16, description="IK solution index; default: the "
                               "within-limits solution nearest the current joints")
    ik_case: Literal["dx_zero", "dx_used"] | None = Field(
        None, description="angler only: `dx_zero` (dx = 0, theta3 reaches x) or `dx_used` (the "
        "design's case 2: dx = px -/+ r, theta3 = -/+90 deg; a line keeps theta3); none: "
        "the design's choice, dx_zero where |px| <= r")
    duration: Duration | None = None
    speed: Speed = 1.0
    mode: QueueMode = "queue"
    wait: Bool = False


class Motion(Model):
    id: str
    arm: str
    kind: Literal["joints", "pose"]
    path: Literal["joint", "line"]
    status: Literal["queued", "running", "done", "stopped", "failed"]
    progress: float
    planned_duration: float
    target_positions: list[float]
    target_tip: Tip
    reason: str | None = None
    code: str | None = None
    created: float
    started: float | None = None
    ended: float | None = None
    final_positions: list[float] | None = None
    final_tip: Tip | None = None
    planned_path: list[Vec3] = Field(default_factory=list, description="tip path preview, "
                                     "up to 50 points")


class StopResult(Model):
    stopped: list[str]
    estop: bool


class EstopState(Model):
    estop: bool


class GripperCommand(Model):
    value: Unit


class GripperState(Model):
    value: float


# ---------------------------------------------------------------- kinematics


class JointVector(Model):
    positions: list[Finite] = Field(min_length=1, max_length=16)


class ForwardResult(Model):
    tip: Tip
    jacobian: list[list[float]]


class InverseRequest(Tip):
    ik_case: Literal["dx_zero", "dx_used"] | None = None
    theta3: Finite | None = Field(None, description="angler dx_used case: theta3 to use, rad "
                                  "(none: the design's -/+90 deg)")


class IKSolution(Model):
    positions: list[float]
    within_limits: bool
    violations: list[str] = []
    branch: int


class InverseResult(Model):
    solutions: list[IKSolution]


class Workspace(Model):
    lower: Vec3
    upper: Vec3
    points: list[Vec3]
    joint_lower: list[float]
    joint_upper: list[float]


# ---------------------------------------------------------------- rbe3001 pass-through


class PidSetpoint(Model):
    position_ticks: Finite
    velocity_ticks_s: Finite = 0.0
    force: Finite = 0.0


class SetPid(Model):
    joints: list[PidSetpoint] = Field(min_length=3, max_length=3)


class SetPidReply(Model):
    position_ticks: list[float]


class Rbe3001Status(Model):
    position_ticks: list[float]
    velocity_ticks_s: list[float]
    strain_adc: list[float]


#: A PID gain in the firmware's units (the default kp is 0.005; the output saturates at 0.2,
#: so 1000 already means full output at 0.0002 ticks of error). A negative gain makes the loop
#: unstable and is refused.
Gain = Annotated[float, Field(ge=0.0, le=1000.0, allow_inf_nan=False, strict=True)]


class SetGain(Model):
    axis: Int = Field(ge=0, le=2)
    kp: Gain
    ki: Gain
    kd: Gain


class SetClaw(Model):
    value: Unit


class Ack(Model):
    ok: bool = True
    command: str


# ---------------------------------------------------------------- dynamixel pass-through


class PingRequest(Model):
    id: DxlIdValue | None = Field(None, description="one id, or none for every id")


class PingDevice(Model):
    id: int
    model_number: int
    firmware_version: int


class PingResult(Model):
    devices: list[PingDevice]


class RegisterValue(Model):
    id: int
    name: str
    address: int
    size: int
    raw: int
    unit: str | None = None
    value: float | None = Field(None, description="raw converted to the item's unit, if any")


class RegisterWrite(Model):
    raw: Int


class SyncReadRequest(Model):
    name: str
    ids: list[DxlIdValue] = Field(min_length=1, max_length=32)


class SyncReadResult(Model):
    name: str
    values: dict[int, int]


class SyncWriteRequest(Model):
    name: str
    # keys are JSON object keys, so strings: "1" is id 1; the values are strict
    values: dict[Annotated[int, Field(ge=0, le=252)], Int] = Field(min_length=1, max_length=32)


# ---------------------------------------------------------------- lease


class Lease(Model):
    id: str
    arm: str
    expires: float = Field(description="Unix time the lease lapses unless renewed")
    ttl: float


# ---------------------------------------------------------------- classroom: people, queue, audit


class Me(Model):
    name: str = Field(description="the caller's name (never the token)")
    role: Literal["viewer", "operator", "instructor"]


class QueueEntry(Model):
    id: str
    arm: str
    name: str
    position: int | None = Field(None, description="1 = next; 0 = offered or holding; None "
                                 "once ended")
    status: Literal["waiting", "offered", "holding", "done", "expired"]
    created: float
    lease_id: str | None = Field(None, description="the offered lease's id, for its owner only: "
                                 "renew it (PUT /lease/{id}) within the claim window to hold it")
    offered_until: float | None = Field(None, description="Unix time the offer passes on")
    started: float | None = None
    slot_end: float | None = Field(None, description="Unix time the slot ends, renewed or not")
    ended: float | None = None
    reason: str | None = None


class QueueStatus(Model):
    arm: str
    holder: str | None = Field(None, description="who holds the arm's lease now")
    slot_left: float | None = Field(None, description="seconds left in the holder's slot")
    entries: list[QueueEntry] = Field(description="the current (offered or holding) entry "
                                      "first, then the waiting ones in order")
    handing_off: bool
    blocked: str | None = Field(None, description="why the last hand-off failed (the arm is "
                                "left with nobody until an instructor's DELETE /lease)")
    last_handoff: dict[str, Any] | None = None
    claim_s: float
    slot_s: float


class QueueOrder(Model):
    order: list[Annotated[str, Field(max_length=64)]] = Field(
        max_length=1000, description="every waiting entry's id, in the new order")


class AuditRecord(Model):
    time: float
    name: str
    role: str
    arm: str | None
    method: str
    route: str
    summary: str
    status: int
    code: str | None


# ---------------------------------------------------------------- safety envelope


class SafetyUpdate(Model):
    """A change of an arm's safety envelope: each field given replaces the current one, each
    omitted keeps it (`floor_z: null` removes the floor)."""

    zones: list[KeepOutBox] | None = Field(None, max_length=32)
    floor_z: Annotated[
        float, Field(ge=-10.0, le=10.0, allow_inf_nan=False, strict=True)] | None = None
    speed_override: Annotated[
        float, Field(ge=0.05, le=1.0, allow_inf_nan=False, strict=True)] | None = None


class Safety(Model):
    zones: list[KeepOutBox]
    floor_z: float | None = Field(description="no body point below this height, m")
    speed_override: float = Field(description="0.05..1: scales every planned limit")
    tool_margin: float = Field(description="zones and floor grown by this for the tip, m "
                               "(profile)")
    body_margin: float = Field(description="the same for the other body points, m (profile)")
    body_points: list[str] = Field(description="the points checked: every joint origin and "
                                   "the tip")
    source: Literal["profile", "stored"]
    persisted: bool = Field(description="false while a change waits for the database")
    editable: bool = Field(description="whether the caller may change it (instructor)")
    store_error: str | None = None
