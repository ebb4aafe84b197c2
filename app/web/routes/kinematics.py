"""Kinematics without motion: forward (tip and Jacobian), inverse (every solution, flagged) and
the workspace. Pure computation on the arm's model (`ArmService.model`); nothing reaches the
device, so a viewer token suffices."""

from __future__ import annotations

from typing import Annotated

import numpy as np
from fastapi import APIRouter, Query

from app import schemas as s
from app.arms import arm_type
from app.errors import Unreachable
from app.web.deps import ViewerArm
from app.web.routes.common import READ, check_joint_count, errors, finite
from kinematics.singular import TIP_FORCE_MAX_COND, condition_number

router = APIRouter(tags=["kinematics"])

#: Points in a workspace answer: 500 by default, at most 5000 (about 250 kB of JSON).
WORKSPACE_DEFAULT = 500
WORKSPACE_MAX = 5000


def _vec(v: np.ndarray) -> s.Vec3:
    return s.Vec3(x=float(v[0]), y=float(v[1]), z=float(v[2]))


@router.post(
    "/arms/{arm}/kinematics/forward",
    response_model=s.ForwardResult,
    summary="Forward kinematics",
    description="Joint positions (rad/m, the arm's joint order) -> tip position (m, base frame) "
    "and the 3 x n Jacobian d tip / d q. Positions outside the joint limits are computed all "
    "the same (this is geometry, not a command).",
    responses=errors(*READ),
)
async def forward(svc: ViewerArm, req: s.JointVector) -> s.ForwardResult:
    check_joint_count(svc, req.positions)
    q = np.asarray(req.positions, dtype=float)
    jac = svc.model.jacobian(q)
    finite(svc.model.fk(q), "the tip")
    finite(jac, "the Jacobian")
    return s.ForwardResult(tip=s.Tip(**svc.model.tip(q)),
                           jacobian=[[float(x) for x in row] for row in jac])


@router.post(
    "/arms/{arm}/kinematics/inverse",
    response_model=s.InverseResult,
    summary="Inverse kinematics",
    description="Tip position (m) -> every IK solution, each with `within_limits`, the "
    "`violations` (which joint, which limit, how far) and its `branch` index (usable as "
    "`branch` in move/pose). 422 `unreachable` with the reason where there is none. Angler: "
    "`ik_case` `dx_zero` (dx = 0, theta3 reaches x) or `dx_used` (the design's case 2: "
    "dx = px -/+ r, theta3 = -/+90 deg, or the `theta3` given); with no case, the solutions "
    "of both, the design's choice first (dx = 0 where |px| <= r).",
    responses=errors(*READ),
)
async def inverse(svc: ViewerArm, req: s.InverseRequest) -> s.InverseResult:
    p = np.array([req.x, req.y, req.z], dtype=float)
    sols = svc.model.ik(p, req.pitch, arm_type(svc.profile.model).options(req))
    out = [s.IKSolution(positions=[float(x) for x in sol.positions],
                        within_limits=sol.within_limits, violations=list(sol.violations),
                        branch=sol.branch)
           for sol in sols if np.all(np.isfinite(sol.positions))]
    if not out:
        raise Unreachable(f"no inverse kinematics solution for ({req.x}, {req.y}, {req.z}) m")
    return s.InverseResult(solutions=out)


@router.post(
    "/arms/{arm}/kinematics/inverse-velocity",
    response_model=s.InverseVelocityResult,
    summary="Inverse velocity kinematics",
    description="Joint positions and a tip velocity (m/s) -> the joint velocities that give it, "
    "q' = J^-1 x' (the design document's section 4.2; for an arm with more joints than tip "
    "coordinates, the angler's four, the least-norm J^T (J J^T)^-1 x', which weighs 1 rad/s "
    "as 1 m/s). 422 `unreachable` with the reason near a singularity: the Jacobian's "
    "condition number above the one rule's bound (kinematics/singular.py), where a small "
    "tip velocity needs unbounded joint velocities. Geometry only: no limit is checked.",
    responses=errors(*READ),
)
async def inverse_velocity(svc: ViewerArm, req: s.InverseVelocityRequest
                           ) -> s.InverseVelocityResult:
    check_joint_count(svc, req.positions)
    q = np.asarray(req.positions, dtype=float)
    jac = np.asarray(svc.model.jacobian(q), dtype=float)
    finite(jac, "the Jacobian")
    cond = float(condition_number(jac))
    if not np.isfinite(cond) or cond > TIP_FORCE_MAX_COND:
        shown = "infinite" if not np.isfinite(cond) else f"{cond:.3g}"
        raise Unreachable(f"near a singularity: the Jacobian's condition number is {shown}, "
                          f"above {TIP_FORCE_MAX_COND:g}; no joint velocities give every tip "
                          "velocity here (the arm is stretched out, folded, or the tip is over "
                          "the base axis): move away from it")
    xd = np.array([req.velocity.x, req.velocity.y, req.velocity.z], dtype=float)
    qd = np.linalg.pinv(jac) @ xd  # J^-1 x' when J is square; least-norm otherwise
    return s.InverseVelocityResult(velocities=[float(v) for v in qd], condition=cond,
                                   tip_velocity=_vec(jac @ qd))


@router.get(
    "/arms/{arm}/workspace",
    response_model=s.Workspace,
    summary="Workspace: bounds and a sampled point cloud",
    description="The axis-aligned box of reachable tip positions (m), the joint limits, and `n` "
    "tip positions from joints drawn uniformly within the limits (a fixed seed: the same `n` "
    "gives the same points).",
    responses=errors(*READ),
)
async def workspace(
    svc: ViewerArm,
    n: Annotated[int, Query(ge=1, le=WORKSPACE_MAX, description="points to sample")] = (
        WORKSPACE_DEFAULT),
) -> s.Workspace:
    lo, hi = svc.model.bounds()  # computed once per model
    pts = svc.model.workspace(n)
    return s.Workspace(lower=_vec(lo), upper=_vec(hi),
                       points=[s.Vec3(x=float(p[0]), y=float(p[1]), z=float(p[2])) for p in pts],
                       joint_lower=[float(x) for x in svc.model.lower],
                       joint_upper=[float(x) for x in svc.model.upper])
