"""Motion: joint and pose moves, the motion record, stop, estop and gripper."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from app.schemas.arms import Tip, Vec3
from app.schemas.common import Bool, Duration, Finite, Int, Model, Speed, Unit

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
