"""The safety guard of one arm: the emergency-stop latch and every check a command that moves
the arm goes through (shutdown, estop, hardware faults, homing, joint and velocity limits, the
safety envelope), in one place.

Motion (app/motion/executor.py), the pass-through routes and the service ask the guard; it reads the
arm's device only through the `Actuator` reading (positions, faults, homed flags) and never
commands it. Checks raise the typed errors of app/errors.py (4xx with a stable code).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import Any

import numpy as np

from app.arms.model import KinematicsModel
from app.config import ArmProfile
from app.device.actuator import Actuator
from app.errors import (
    EstopLatched,
    Fault,
    InvalidRequest,
    JointLimit,
    LinkDown,
    NotCalibrated,
    NotHomed,
    ShuttingDown,
    TorqueOff,
    VelocityLimit,
)
from app.safety.envelope import ArmSafety, path_fractions
from kinematics.limits import within


class SafetyGuard:
    def __init__(self, profile: ArmProfile, model: KinematicsModel, device: Actuator) -> None:
        self.name = profile.name
        self.profile = profile
        self.model = model
        self.device = device
        self.safety = ArmSafety(model, profile.safety)
        #: The emergency stop latch: nothing moves while it is set (DELETE .../estop clears).
        self.estop = False
        #: Set when the server shuts down: no new motion (app.web.serving).
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

    def require_torque(self) -> None:
        """409 `torque_off` while a joint's torque is off (`torque_refusal`)."""
        refusal = self.torque_refusal()
        if refusal is not None:
            raise refusal

    def torque_refusal(self) -> TorqueOff | None:
        """Why nothing may be commanded now, if a joint's torque is off (switched off through
        this server and not on again, `Actuator.torque_off`): a command would go to a servo
        that cannot follow it, and its goal would wait there for the torque to come back, a
        move from wherever a hand or gravity has taken the joint that no check has seen. Every
        joint: a limp one can swing while the others move. None while all hold torque."""
        off = self.device.torque_off
        if not off:
            return None
        names = ", ".join(self.profile.joints[k].name for k in off)
        return TorqueOff(f"{self.name}: the torque of {names} is off, so no command can move "
                         f"the arm; switch it on with PUT /api/v1/arms/{self.name}/torque "
                         '{"on": true}, which holds every joint where it is')

    def tolerance(self) -> np.ndarray:
        """Per joint (rad or m): the profile's `settle_tolerance`, else 8 encoder ticks."""
        return self._tolerance.copy()

    def check_calibrated(self, start: np.ndarray | None, target: np.ndarray) -> None:
        """409 `not_calibrated` for a command that would move a joint whose zero is not known
        on this hardware (the profile's `zero_known = false`, no calibration declared or
        stored): its reading, its limits and the kinematics would all be off by the unknown
        offset."""
        tol = self._tolerance
        moved = [k for k, ok in enumerate(self.device.calibrated) if not ok and (
            start is None or abs(float(target[k]) - float(start[k])) > tol[k])]
        if moved:
            names = ", ".join(self.model.names[k] for k in moved)
            raise NotCalibrated(
                f"{self.name}: joint {names} is not calibrated on this hardware (its zero is "
                "not known): put the arm in a calibration pose and declare it with POST "
                f"/api/v1/arms/{self.name}/calibration (body {{\"pose\": NAME}} or "
                "{\"positions\": [...]}) first; GET it for the poses")

    def check_homed(self, start: np.ndarray | None, target: np.ndarray) -> None:
        """409 `not_calibrated` (`check_calibrated`), then 409 `not_homed` for a command that
        would move a joint that is not homed."""
        self.check_calibrated(start, target)
        tol = self._tolerance
        moved = [k for k, homed in enumerate(self.device.homed) if not homed and (
            start is None or abs(float(target[k]) - float(start[k])) > tol[k])]
        if moved:
            names = ", ".join(self.model.names[k] for k in moved)
            raise NotHomed(f"{self.name}: joint {names} is not homed (its position is not known "
                           f"after a power cycle or reboot): home the arm with POST "
                           f"/api/v1/arms/{self.name}/home first")

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

    def check_passthrough(self, target: np.ndarray, pace: np.ndarray | None = None) -> None:
        """A pass-through position command (rbe3001 SET_PID, Dynamixel goal positions, one or
        several, raw access included) checked like a planned move, as the path the arm will
        take from where it is (measured) to `target` (rad or m, every joint: the caller fills
        the joints it does not command with where they are told to go):

        - the estop, shutdown and faults; a joint's torque off; NaN; homing;
        - the joint limits, unless the profile allows raw access;
        - the envelope (raw access too), along that path: every joint together, each paced
          joint ramping at its own pace (a servo's profile, independent of the others), the
          unpaced ones along the straight line;
        - speed: a joint that goes to a new position as fast as it can (a PID step; `pace`
          NaN or None) may be sent at most `PASSTHROUGH_STEP_S` times its velocity limit
          (times the speed override) from where it is, the longest step the motion executor
          itself sends (app/motion/stream.py MAX_STEP_S); 422 `velocity_limit` beyond. A joint
          whose device paces itself at or under its limit (`pace`, a Dynamixel servo's
          Profile Velocity) may be sent anywhere.
        """
        self.require_motion_allowed()
        self.require_no_fault()
        self.require_torque()
        target = np.asarray(target, dtype=float)
        require_finite(target, "pass-through positions")
        here = self.device.positions
        if here is None or self.device.stale:
            raise LinkDown(f"{self.name}: no fresh joint positions from the device to check a "
                           "pass-through command against")
        self.check_homed(here, target)
        m = self.model
        if not self.profile.raw_access and not within(target, m.lower, m.upper):
            raise JointLimit("pass-through position outside the joint limits (the profile does "
                             "not allow raw access): " + "; ".join(m.violations(target)))
        speed = np.asarray(self.scaled(m.vmax)[0], dtype=float)
        if pace is None:
            paced = np.zeros(m.n, dtype=bool)
        else:
            p = np.asarray(pace, dtype=float)
            paced = np.isfinite(p) & (p > 0) & (p <= m.vmax * (1 + 1e-6))
            speed = np.where(paced, p, speed)
        if self.safety.active:  # an inactive envelope refuses no path: none is built
            self.safety.check_path(passthrough_path(here, target, speed, paced, m.kinds),
                                   "along the path from where the arm is to the commanded "
                                   "position")
        self._check_step(target, here, speed, paced)

    def _check_step(self, target: np.ndarray, here: np.ndarray, speed: np.ndarray,
                    paced: np.ndarray) -> None:
        """A joint its device does not pace follows its setpoint as fast as the error drives
        it: the setpoint may be at most PASSTHROUGH_STEP_S of motion at the limit from where
        the joint is, and may move from the last command no faster than the executor's own
        setpoints do (the limit times the profile's tracking margin, over the time since
        that command, PASSTHROUGH_STEP_S at most). A stream of steps each near the arm but
        sent back to back kept the rbe3001's PID error at 45 mrad and drove it at 1.8 rad/s
        (limit 1.5). Decided on whole arrays; the reasons are written only for a refusal."""
        m = self.model
        eps = np.abs(1.0 / m.transmission.ticks_per_unit)  # one encoder tick
        free = ~paced
        step = np.abs(target - here)
        cap = speed * PASSTHROUGH_STEP_S + eps
        from_here = free & (step > cap)
        told = self.device.commanded
        from_told = np.zeros(m.n, dtype=bool)
        if told is not None and np.any(free & np.isfinite(told)):
            since = min(max(0.0, time.monotonic() - self.device.commanded_at),
                        PASSTHROUGH_STEP_S)
            rate = speed * m.profile.tracking_margin
            moved = np.abs(target - told)
            allowed = rate * since + eps
            from_told = free & np.isfinite(told) & (moved > allowed) & (step <= cap)
        if not (from_here.any() or from_told.any()):
            return
        kinds = list(zip(m.names, m.kinds, strict=True))
        over = [f"{name} {step[k]:.4g} {_unit(kind)} from where it is (at most {cap[k]:.4g}: "
                f"{PASSTHROUGH_STEP_S:g} s at its velocity limit {speed[k]:g} {_unit(kind)}/s)"
                for k, (name, kind) in enumerate(kinds) if from_here[k]]
        over += [f"{name} moved {moved[k]:.4g} {_unit(kind)} from its last command "
                 f"{since * 1e3:.1f} ms after it (at most {allowed[k]:.4g}: "
                 f"{rate[k]:.3g} {_unit(kind)}/s)"
                 for k, (name, kind) in enumerate(kinds) if from_told[k]]
        raise VelocityLimit(
            "pass-through step the device would take faster than the joint's velocity "
            "limit: " + "; ".join(over) + f". Send a planned move (POST /api/v1/arms/"
            f"{self.name}/move/joints), or setpoints at most {PASSTHROUGH_STEP_S:g} s of "
            "motion at the limit from where the joint is, and from the last command no "
            "further than the limit allows in the time since it")

    def check_passthrough_velocity_ticks(self, velocities: np.ndarray) -> None:
        """Raw joint velocities (ticks/s, one per joint: SET_PID's velocity_ticks_s, which the
        firmware carries but does not use) are finite and within the profile's joint velocity
        limits converted to ticks/s, unless the profile allows raw access; 422
        `velocity_limit` naming the joint, the limit and the excess otherwise."""
        require_finite(velocities, "pass-through velocities")
        if self.profile.raw_access:
            return
        m = self.model
        v = np.abs(np.asarray(velocities, dtype=float))
        cap = np.abs(m.transmission.velocity_to_ticks(m.vmax))
        over = [f"{name} {v[k]:.0f} ticks/s is above its limit {cap[k]:.0f} ticks/s "
                f"({m.vmax[k]:g} {_unit(kind)}/s) by {v[k] - cap[k]:.0f} ticks/s"
                for k, (name, kind) in enumerate(zip(m.names, m.kinds, strict=True))
                if v[k] > cap[k] * (1 + 1e-9)]
        if over:
            raise VelocityLimit("pass-through velocity over the joint velocity limits (the "
                                "profile does not allow raw access): " + "; ".join(over))

    def require_not_latched(self) -> None:
        """The owner task's gate (app/device/owner.py): while the estop is latched no command
        that moves the arm is written, whenever it was queued; the hold is not gated."""
        if self.estop:
            raise EstopLatched(f"{self.name}: emergency stop latched before the command was "
                               f"sent; release it with DELETE /api/v1/arms/{self.name}/estop")


#: The longest pass-through step a joint that is not paced by its device may be sent, in
#: seconds of motion at its velocity limit: the executor's own longest setpoint step
#: (app/motion/stream.py MAX_STEP_S, tested equal). The rbe3001's PID takes a step at the speed
#: its error gives (a 3 rad step peaks near 2.9 rad/s, twice the limit); 0.03 s at 1.5 rad/s
#: is 45 mrad, which it takes well under the limit.
PASSTHROUGH_STEP_S = 0.03


def passthrough_path(here: np.ndarray, target: np.ndarray, speed: np.ndarray,
                     paced: np.ndarray, kinds: Sequence[str]) -> np.ndarray:
    """The joint path (N, n) a pass-through command takes from `here` to `target`: joints the
    device paces ramp at their own `speed` (each arrives on its own), the others move along
    the straight line over the slowest paced joint's time (over none: the straight line).
    Sampled where the envelope's path checks look (`path_fractions`)."""
    delta = target - here
    s = path_fractions(delta, kinds)
    if not np.any(paced):
        return np.asarray(here + s * delta, dtype=float)
    t_each = np.where(paced, np.abs(delta) / np.maximum(speed, 1e-12), 0.0)
    total = float(np.max(t_each))
    if total <= 0.0:
        return np.asarray(here + s * delta, dtype=float)
    frac = np.where(paced, np.minimum(1.0, s * total / np.where(t_each > 0, t_each, 1.0)), s)
    return np.asarray(here + frac * delta, dtype=float)


def _unit(kind: str) -> str:
    return "rad" if kind == "revolute" else "m"


def _settle_tolerance(profile: ArmProfile, model: KinematicsModel) -> np.ndarray:
    ticks = np.abs(8.0 / model.transmission.ticks_per_unit)
    return np.array([j.settle_tolerance if j.settle_tolerance is not None else ticks[k]
                     for k, j in enumerate(profile.joints)], dtype=float)


def require_finite(values: Any, what: str) -> None:
    """422 for NaN or infinity: the limit checks compare, and a NaN compares false."""
    a = np.asarray(values, dtype=float)
    if not np.all(np.isfinite(a)):
        raise InvalidRequest(f"{what} must be finite numbers, got {a.tolist()}")
