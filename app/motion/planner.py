"""Planning a motion: a joint move or a straight line, from a start state to a goal, under the
profile's joint and Cartesian limits scaled by the speed override, checked against the joint
limits and the safety envelope at the control rate before anything moves.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from app.arms import arm_type
from app.arms.model import KinematicsModel
from app.config import CartesianLimits
from app.errors import ArmError, InvalidRequest, JointLimit, Unreachable
from app.motion.history import Plan
from app.safety.guard import SafetyGuard
from kinematics import trajectory
from kinematics.errors import KinematicsError, LimitViolation, TrajectoryError
from kinematics.errors import Unreachable as KinematicsUnreachable

#: (q, qd, qdd) of a start state
State = tuple[np.ndarray, ...]


class Planner:
    """Plans one arm's moves (`joint` and `pose`); stateless between calls."""

    def __init__(self, name: str, model: KinematicsModel, guard: SafetyGuard,
                 cartesian: CartesianLimits, control_hz: float) -> None:
        self.name = name
        self.model = model
        self.guard = guard
        self.cartesian = cartesian
        self.dt = 1.0 / control_hz

    def joint_vector(self, positions: list[float]) -> np.ndarray:
        q = self.model.joint_vector(positions)
        self.guard.check_joint_target(q)
        return q

    def joint(self, start: State, q1: np.ndarray, req: Any, at_rest: bool) -> Plan:
        q0, v0, a0 = start
        m = self.model
        guard = self.guard
        k = m.profile.tracking_margin  # the measured speed, not only the plan, in limits
        vmax, amax, jmax = guard.scaled(m.vmax * k, m.amax * k, m.jmax)  # speed_override
        try:
            traj = trajectory.plan_joint(q0, q1, vmax, amax, jmax,
                                         v0=None if at_rest else v0, a0=None if at_rest else a0,
                                         duration=req.duration, speed=req.speed)
        except KinematicsError as exc:
            raise InvalidRequest(f"cannot plan the move: {exc}") from None
        guard.check_trajectory(traj, self.dt)
        return Plan(traj, q0, q1, "joint")

    def pose(self, start: State, p: np.ndarray, req: Any, at_rest: bool) -> Plan:
        q0 = start[0]
        m = self.model
        # the arm type's IK options from the request (e.g. the angler's ik_case); the model
        # says how a line keeps a redundant joint (model.line_ik)
        opts = arm_type(m.profile.model).options(req)
        pitch = getattr(req, "pitch", None)
        best = m.ik_best(p, q0, req.branch, pitch, opts)
        if req.path == "joint":
            return self.joint(start, best.positions, req, at_rest)
        cart = self.cartesian
        line_ik = m.line_ik(p, q0, pitch, opts)

        def ik_near(point: np.ndarray, q_prev: np.ndarray | None) -> np.ndarray:
            ref = q0 if q_prev is None else q_prev
            try:
                return line_ik(point, ref)
            except ArmError as exc:
                raise KinematicsUnreachable(exc.detail) from None

        guard = self.guard
        k = m.profile.tracking_margin  # the measured joint speed, not only the plan
        cv, ca, cj, vmax = guard.scaled(  # speed_override
            cart.max_velocity, cart.max_acceleration, cart.max_jerk, m.vmax * k)
        try:
            traj, _tips = trajectory.plan_line(
                m.fk(q0), p, ik_near, m.fk, float(cv), float(ca),
                float(cj), self.dt, vmax, m.lower, m.upper,
                m.names, m.kinds, q_start=q0, speed=req.speed)
        except LimitViolation as exc:
            raise JointLimit(f"line path leaves the joint limits: {exc}") from None
        except TrajectoryError as exc:  # e.g. a speed so small the line would last hours
            raise InvalidRequest(f"cannot plan the line: {exc}") from None
        except KinematicsError as exc:
            raise Unreachable(f"line path leaves the workspace: {exc}") from None
        end = traj.sample(traj.duration)[0]
        guard.check_trajectory(traj, self.dt)
        return Plan(traj, q0, np.asarray(end, dtype=float), "line")
