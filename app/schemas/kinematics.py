"""Kinematics: forward and inverse requests and results, the workspace."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from app.schemas.arms import Tip, Vec3
from app.schemas.common import Finite, Model

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


class InverseVelocityRequest(Model):
    """Joint positions (the arm's joint order, rad/m) and a tip velocity (m/s, base frame)."""

    positions: list[Finite] = Field(min_length=1, max_length=16)
    velocity: Vec3 = Field(description="tip velocity, m/s, in the arm's base frame")


class InverseVelocityResult(Model):
    velocities: list[float] = Field(description="joint velocities (rad/s, m/s): q' = J^-1 x' "
                                    "for a square Jacobian, the least-norm J^T (J J^T)^-1 x' for "
                                    "an arm with more joints than tip coordinates")
    condition: float = Field(description="the 2-norm condition number of the Jacobian")
    tip_velocity: Vec3 = Field(description="J q': the tip velocity those joint velocities give")
