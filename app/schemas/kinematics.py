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
