"""Joint calibration (API.md "Calibration (v1.2)"): the joints' zeros on this hardware, the
declaration that sets them, the gravity fit and the motion that makes it."""

from __future__ import annotations

from typing import Literal

from pydantic import Field, model_validator

from app.schemas.common import Bool, Finite, Model

PoseName = Field(pattern=r"^[A-Za-z0-9][A-Za-z0-9_-]{0,31}$")


class ArmCalibrationRequest(Model):
    """Exactly one of `positions` (the joint values the arm is at now, rad or m, one per
    joint) and `pose` (a calibration pose the profile names)."""

    positions: list[Finite] | None = Field(None, min_length=1, max_length=16)
    pose: str | None = Field(None, pattern=r"^[A-Za-z0-9][A-Za-z0-9_-]{0,31}$")

    @model_validator(mode="after")
    def _one(self) -> ArmCalibrationRequest:
        if (self.positions is None) == (self.pose is None):
            raise ValueError("give exactly one of positions and pose")
        return self


class JointCalibration(Model):
    name: str
    calibrated: bool = Field(description="the joint's zero is known on this hardware")
    offset: float = Field(description="the joint value (rad or m) at which the device reads "
                          "zero: what the calibration moves")
    source: Literal["profile", "stored", "declared"] | None = Field(
        description="profile: the hardware (or the firmware's power-on pose) knows it; "
        "stored: found in the store for this hardware; declared: set since the link came up; "
        "null: not calibrated")
    time: float | None = Field(description="Unix time it was declared, null from the profile")


class GravityFit(Model):
    """Joint torques gravity puts on the arm: tau(q) = B(q) weights + bias, B[j][k] the
    height of body point k differentiated by joint j (app/calibration/gravity.py)."""

    weights: list[float] = Field(description="per body point after the base, N")
    bias: list[float] = Field(description="per joint, N m or N")
    poses: list[list[float]] = Field(description="where it was measured, joint values")
    rms: float = Field(description="RMS of the residual torques, N m or N")
    worst: float = Field(description="largest residual torque, N m or N")
    time: float


class GravityRun(Model):
    """The gravity calibration's motion through its poses."""

    status: Literal["running", "done", "failed"]
    poses: list[list[float]]
    done: int = Field(description="poses measured")
    motions: list[str] = Field(description="the joint moves it made, by id")
    reason: str | None = None
    started: float
    ended: float | None = None


class ArmCalibration(Model):
    arm: str
    identity: str | None = Field(description="the hardware the calibration is stored under "
                                 "(HID serial number, servo bus and IDs); null before the "
                                 "link first came up")
    joints: list[JointCalibration]
    gravity: GravityFit | None = Field(description="the gravity fit, null until one is made")
    gravity_run: GravityRun | None = Field(None, description="the last gravity calibration "
                                           "motion, null if none since start")
    poses: dict[str, list[float]] = Field(description="the calibration poses the profile "
                                          "names, joint values")
    power_on_pose: str | None = Field(description="the pose the firmware zeroes at power-on, "
                                      "if the profile says it does")
    stored: bool = Field(description="this calibration is in the store for this hardware")
    store_error: str | None = None


class GravityCalibrationRequest(Model):
    poses: list[list[Finite]] | None = Field(
        None, min_length=2, max_length=16, description="joint values to measure at (default: "
        "home and each joint gravity acts on at a quarter of its range from either end)")
    wait: Bool = Field(False, description="answer when the fit is made (or the run failed)")
