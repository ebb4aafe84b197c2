"""The safety guard of one arm: the emergency-stop latch and every check a command that moves
the arm goes through (shutdown, estop, hardware faults, homing, joint and velocity limits, the
safety envelope), in one place.

Motion (app/motion.py), the pass-through routes and the service ask the guard; it reads the
arm's device only through the `Actuator` reading (positions, faults, homed flags) and never
commands it. Checks raise the typed errors of app/errors.py (4xx with a stable code).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from app.actuator import Actuator
from app.arm_model import KinematicsModel
from app.config import ArmProfile
from app.envelope import ArmSafety
from app.errors import (
    EstopLatched,
    Fault,
    InvalidRequest,
    JointLimit,
    NotHomed,
    ShuttingDown,
    VelocityLimit,
)


class SafetyGuard:
    def __init__(self, profile: ArmProfile, model: KinematicsModel, device: Actuator) -> None:
        self.name = profile.name
        self.profile = profile
        self.model = model
        self.device = device
        self.safety = ArmSafety(model, profile.safety)
        #: The emergency stop latch: nothing moves while it is set (DELETE .../estop clears).
        self.estop = False
        #: Set when the server shuts down: no new motion (app.serving).
        self.closing = False
        self._tolerance = _settle_tolerance(profile, model)

    # --------------------------------------------------------- the latch

    def latch(self) -> bool:
        """Latch the emergency stop; False if it was latched already."""
        was, self.estop = self.estop, True
        return not was

    def release(self) -> bool:
        """Release the emergency stop; False if it was not latched."""
        was, self.estop = self.estop, False
        return was

    # --------------------------------------------------------- what may move

    def require_motion_allowed(self) -> None:
        if self.closing:
            raise ShuttingDown(f"{self.name}: the server is shutting down")
        if self.estop:
            raise EstopLatched(f"{self.name}: emergency stop is latched; release it with "
                               f"DELETE /api/v1/arms/{self.name}/estop")

    def require_no_fault(self) -> None:
        """409 `fault` while a servo reports a hardware fault: which, which bits, how to clear."""
        faults = self.device.faults
        if faults:
            raise Fault(f"{self.name}: refused while a servo reports a hardware fault: "
                        + " | ".join(f"servo {f['servo']} ({f['joint']}): "
                                     f"{', '.join(f['bits']) or 'alert'}: {f['advice']}"
                                     for f in faults))

    def tolerance(self) -> np.ndarray:
        """Per joint (rad or m): the profile's `settle_tolerance`, else 8 encoder ticks."""
        return self._tolerance.copy()

    def check_homed(self, start: np.ndarray | None, target: np.ndarray) -> None:
        """409 `not_homed` for a command that would move a joint that is not homed."""
        tol = self._tolerance
        moved = [k for k, homed in enumerate(self.device.homed) if not homed and (
            start is None or abs(float(target[k]) - float(start[k])) > tol[k])]
        if moved:
            names = ", ".join(self.model.names[k] for k in moved)
            raise NotHomed(f"{self.name}: joint {names} is not homed (its position is not known "
                           f"after a power cycle or reboot): home the arm with POST "
                           f"/api/v1/arms/{self.name}/home first")

    def check_homed_joint(self, joint: int, start: np.ndarray | None, ticks: float) -> None:
        """`check_homed` for one joint's raw goal (ticks)."""
        q = np.full(self.model.n, np.nan)
        q[joint] = ticks
        target = self.model.transmission.from_ticks(q)
        cur = np.full(self.model.n, np.nan) if start is None else np.full(self.model.n, start[0])
        tol = self._tolerance[joint]
        if start is None or not abs(float(target[joint]) - float(cur[joint])) <= tol:
            self.check_homed(None, target)

    def check_joint_target(self, q: np.ndarray) -> None:
        """Joint limits for any commanded position, planned or pass-through."""
        require_finite(q, "joint positions")
        self.model.check_limits(q)

    # --------------------------------------------------------- planned motion

    def scaled(self, *limits: np.ndarray | float) -> tuple[np.ndarray, ...]:
        """Motion limits times the speed override (the envelope's setting)."""
        return self.safety.scaled(*limits)

    def check_trajectory(self, traj: object, dt: float) -> None:
        """The safety envelope along a planned trajectory at the control period `dt`."""
        self.safety.check_trajectory(traj, dt)

    # --------------------------------------------------------- pass-through commands

    def check_passthrough_ticks(self, ticks: np.ndarray,
                                velocities: np.ndarray | None = None) -> None:
        """A raw position command (rbe3001 SET_PID ticks, Dynamixel goal positions) obeys the
        joint limits unless the profile allows raw access, and the estop always. With
        `velocities` (ticks/s, e.g. SET_PID's velocity_ticks_s), those obey the velocity limits
        too (`check_passthrough_velocity_ticks`)."""
        self.require_motion_allowed()
        self.require_no_fault()
        require_finite(ticks, "pass-through positions")
        if velocities is not None:
            self.check_passthrough_velocity_ticks(velocities)
        q = self.model.transmission.from_ticks(np.asarray(ticks, dtype=float))
        self.check_homed(self.device.positions, q)
        v = [] if self.profile.raw_access else self.model.violations(q)
        if v:
            raise JointLimit("pass-through position outside the joint limits (the profile does "
                             "not allow raw access): " + "; ".join(v))
        # the envelope holds with raw access too: the target and the straight joint-space path
        self.safety.check_joint_path(self.device.positions, q)

    def check_passthrough_velocity_ticks(self, velocities: np.ndarray) -> None:
        """Raw joint velocities (ticks/s, one per joint) within the profile's joint velocity
        limits converted to ticks/s, unless the profile allows raw access; 422
        `velocity_limit` naming the joint, the limit and the excess otherwise."""
        require_finite(velocities, "pass-through velocities")
        if self.profile.raw_access:
            return
        m = self.model
        v = np.abs(np.asarray(velocities, dtype=float))
        cap = np.abs(m.transmission.velocity_to_ticks(m.vmax))
        over = [f"{name} {v[k]:.0f} ticks/s is above its limit {cap[k]:.0f} ticks/s "
                f"({m.vmax[k]:g} {'rad' if kind == 'revolute' else 'm'}/s) by "
                f"{v[k] - cap[k]:.0f} ticks/s"
                for k, (name, kind) in enumerate(zip(m.names, m.kinds, strict=True))
                if v[k] > cap[k] * (1 + 1e-9)]
        if over:
            raise VelocityLimit("pass-through velocity over the joint velocity limits (the "
                                "profile does not allow raw access): " + "; ".join(over))

    def check_passthrough_joint_ticks(self, joint: int, ticks: float) -> None:
        """As `check_passthrough_ticks` for one joint's goal (the others unchanged)."""
        self.require_motion_allowed()
        self.require_no_fault()
        if not self.device.homed[joint]:
            cur = self.device.positions
            start = None if cur is None else cur[joint:joint + 1]
            self.check_homed_joint(joint, start, ticks)
        if self.profile.raw_access:
            return
        current = self.device.positions
        base = current.copy() if current is not None else (self.model.lower + self.model.upper) / 2
        all_ticks = self.model.transmission.to_ticks(base)
        all_ticks[joint] = ticks
        self.check_passthrough_ticks(all_ticks)


def _settle_tolerance(profile: ArmProfile, model: KinematicsModel) -> np.ndarray:
    ticks = np.abs(8.0 / model.transmission.ticks_per_unit)
    return np.array([j.settle_tolerance if j.settle_tolerance is not None else ticks[k]
                     for k, j in enumerate(profile.joints)], dtype=float)


def require_finite(values: Any, what: str) -> None:
    """422 for NaN or infinity: the limit checks compare, and a NaN compares false."""
    a = np.asarray(values, dtype=float)
    if not np.all(np.isfinite(a)):
        raise InvalidRequest(f"{what} must be finite numbers, got {a.tolist()}")
