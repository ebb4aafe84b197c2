"""One hosted arm: its driver (which owns the link), telemetry hub, motion executor, emergency
stop latch and the safety checks that every path that moves the arm goes through.

Routes call this; it never touches a link itself (the driver's task does).
"""

from __future__ import annotations

import logging
import time
from typing import Any

import numpy as np

from app import schemas as s
from app.arms import arm_type
from app.config import ArmProfile
from app.control import on_control
from app.devices.base import Driver
from app.devices.factory import make_driver
from app.envelope import ArmSafety
from app.errors import (
    ArmError,
    Busy,
    EstopLatched,
    Fault,
    InvalidRequest,
    JointLimit,
    LinkDown,
    NoGripper,
    NotHomed,
    NotSupported,
    VelocityLimit,
)
from app.links.base import LinkState
from app.motion import MotionExecutor
from app.telemetry import TelemetryHub
from kinematics.singular import TIP_FORCE_MAX_COND, condition_number

log = logging.getLogger(__name__)


class ArmService:
    def __init__(self, profile: ArmProfile, driver: Driver | None = None) -> None:
        self.profile = profile
        self.name = profile.name
        self.hub = driver.hub if driver is not None else TelemetryHub(profile.name)
        self.driver = driver if driver is not None else make_driver(profile, self.hub)
        self.model = self.driver.model
        self.estop = False
        self.safety = ArmSafety(self.model, profile.safety)
        #: Set when the server shuts down: no new motion (app.serving).
        self.closing = False
        self.motion = MotionExecutor(self)
        self.driver.annotate = self._annotate

    async def start(self) -> None:
        await self.driver.start()
        self.motion.start()

    async def close(self) -> None:
        await self.motion.close()
        await self.driver.close()

    @property
    def home_loop(self) -> Any:
        """The control loop this arm runs on (`app.control`): its async methods cross there."""
        return self.driver.home_loop

    # --------------------------------------------------------- descriptions

    @property
    def protocol(self) -> str:
        return arm_type(self.profile.model).protocol

    def link_status(self) -> s.LinkStatus:
        link = self.driver.link
        return s.LinkStatus(kind=link.kind, address=link.address, state=link.state.value,
                            connected=link.state is LinkState.UP,
                            last_error=link.last_error or self.driver.last_error)

    def capabilities(self) -> s.Capabilities:
        return s.Capabilities(gripper=self.profile.gripper.actuated,
                              force_sensing=self._force_sensing(), protocol=self.protocol,
                              pitch=self.model.has_pitch)

    def _force_sensing(self) -> bool:
        if self.profile.force is not None:
            return True
        return any(j.stall_torque_nm for j in self.profile.joints)

    def summary(self) -> s.ArmSummary:
        return s.ArmSummary(name=self.name, model=self.profile.model,
                            description=self.profile.description, link=self.link_status(),
                            capabilities=self.capabilities())

    def detail(self) -> s.ArmDetail:
        joints = [s.JointInfo(name=j.name, kind=j.kind, min=j.min, max=j.max,
                              max_velocity=j.max_velocity, max_acceleration=j.max_acceleration)
                  for j in self.profile.joints]
        return s.ArmDetail(**self.summary().model_dump(), joints=joints,
                           geometry=dict(self.profile.geometry), estop=self.estop,
                           poll_hz=self.profile.link.poll_hz,
                           faults=[s.Fault(**f) for f in self.driver.faults],
                           homed=list(self.driver.homed), force=self.force_info(),
                           chain=s.ArmChain.model_validate(self.model.describe()))

    # --------------------------------------------------------- force (API.md "Force")

    def force_info(self) -> s.ForceInfo | None:
        """How far the torques and tip force can be trusted, and why tip_force is null."""
        if not self._force_sensing():
            return None
        f = self.profile.force
        if f is not None:
            source, calibrated = "strain_gauges", f.calibrated
            note = f.note or ("calibrated strain gauges" if calibrated else "uncalibrated "
                              "strain gauges: the readings are not a measurement")
            if not calibrated:
                note += " (README: Calibrating the strain gauges)"
        else:
            source, calibrated = "servo_load", False
            note = ("joint efforts estimated from the servos' Present Load (0.1 % of the stall "
                    "torque): an estimate, not a force sensor")
        tare = self.driver.torque_tare
        info = s.ForceInfo(source=source, calibrated=calibrated, note=note,  # type: ignore[arg-type]
                           tare=None if tare is None else [float(v) for v in tare],
                           max_condition_number=TIP_FORCE_MAX_COND)
        q = self.driver.positions
        if q is not None:
            J = self.model.jacobian(q)
            c = float(condition_number(J))
            info.condition_number = c if np.isfinite(c) else None
            info.tip_force_unavailable = self.model.tip_force_unavailable(q, J)
        return info

    def tare_force(self) -> s.ForceTare:
        """The current joint torques become the zero of `torques` and `tip_force`."""
        self._require_force()
        drv = self.driver
        if drv.stale or drv.torques_raw is None:
            raise LinkDown(f"{self.name}: no fresh torque reading to tare against "
                           f"({drv.last_error or drv.link.state.value})")
        drv.torque_tare = np.array(drv.torques_raw, dtype=float)
        self.hub.event("force_tare", offsets=[float(v) for v in drv.torque_tare])
        return s.ForceTare(joints=list(self.model.names),
                           offsets=[float(v) for v in drv.torque_tare])

    def clear_tare(self) -> s.ForceTare:
        self._require_force()
        self.driver.torque_tare = None
        self.hub.event("force_tare", offsets=None)
        return s.ForceTare(joints=list(self.model.names), offsets=None)

    def _require_force(self) -> None:
        if not self._force_sensing():
            raise NotSupported(f"{self.name} senses no joint torques: nothing to tare",
                               code="no_force_sensing")

    def state(self) -> dict[str, Any]:
        """The latest sample; 503 link_down if the device has never answered."""
        latest = self.hub.latest
        if latest is None:
            raise LinkDown(f"{self.name}: no sample from the device yet "
                           f"({self.driver.link.last_error or self.driver.link.state.value})")
        return latest

    def _annotate(self, sample: dict[str, Any]) -> None:
        sample["estop"] = self.estop
        sample["motion"] = self.motion.brief()
        sample["faults"] = list(self.driver.faults)
        sample["homed"] = list(self.driver.homed)
        if self.profile.gripper.actuated:
            sample["gripper"] = self.driver.gripper

    # --------------------------------------------------------- safety: one place for all paths

    def require_motion_allowed(self) -> None:
        if self.closing:
            raise ArmError(f"{self.name}: the server is shutting down", code="shutting_down",
                           status_code=503)
        if self.estop:
            raise EstopLatched(f"{self.name}: emergency stop is latched; release it with "
                               f"DELETE /api/v1/arms/{self.name}/estop")

    def require_no_fault(self) -> None:
        """409 `fault` while a servo reports a hardware fault: which, which bits, how to clear."""
        faults = self.driver.faults
        if faults:
            raise Fault(f"{self.name}: refused while a servo reports a hardware fault: "
                        + " | ".join(f"servo {f['servo']} ({f['joint']}): "
                                     f"{', '.join(f['bits']) or 'alert'}: {f['advice']}"
                                     for f in faults))

    def check_homed(self, start: np.ndarray | None, target: np.ndarray) -> None:
        """409 `not_homed` for a command that would move a joint that is not homed."""
        tol = self.motion.tolerance()
        moved = [k for k, homed in enumerate(self.driver.homed) if not homed and (
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
        tol = self.motion.tolerance()[joint]
        if start is None or not abs(float(target[joint]) - float(cur[joint])) <= tol:
            self.check_homed(None, target)

    @on_control
    async def home(self, positions: list[float] | None) -> s.ArmDetail:
        """Declare the arm's current physical pose (the profile's home pose by default): the
        joints that need homing take these positions; the others read absolute positions and
        keep them. The commanded state is forgotten, so the next motion starts from the
        measured pose."""
        if self.motion.current is not None or self.motion.queued():
            raise Busy(f"{self.name}: a motion is running or queued; stop it before homing")
        if positions is None:
            if self.profile.home is None:
                raise InvalidRequest(f"{self.name}'s profile has no home pose: give positions")
            positions = list(self.profile.home)
        q = np.array(positions, dtype=float)
        if q.shape != (self.model.n,):
            raise InvalidRequest(f"{self.name} has {self.model.n} joints "
                                 f"({', '.join(self.model.names)}), got {len(positions)} positions")
        self.check_joint_target(q)
        if self.driver.positions is None or self.driver.stale:
            raise LinkDown(f"{self.name}: no fresh joint positions from the device to home from")
        for k, j in enumerate(self.profile.joints):
            if j.needs_homing:
                self.driver.set_home(k, float(q[k]))
        self.motion.forget_command()
        log.info("%s: homed at %s", self.name, [round(float(v), 5) for v in q])
        self.hub.event("homed", positions=[float(v) for v in q])
        return self.detail()

    @on_control
    async def reboot(self, dxl_id: int) -> None:
        """REBOOT one servo and set it up again (the driver); the commanded state is
        forgotten: the servo's goal is now its present position."""
        self.require_motion_allowed()
        if self.motion.current is not None or self.motion.queued():
            raise Busy(f"{self.name}: a motion is running or queued; stop it before a reboot")
        await self.driver.reboot(dxl_id)  # type: ignore[attr-defined]
        self.motion.forget_command()
        self.hub.event("rebooted", servo=dxl_id, homed=list(self.driver.homed))

    def check_joint_target(self, q: np.ndarray) -> None:
        """Joint limits for any commanded position, planned or pass-through."""
        _require_finite(q, "joint positions")
        self.model.check_limits(q)

    def check_passthrough_ticks(self, ticks: np.ndarray,
                                velocities: np.ndarray | None = None) -> None:
        """A raw position command (rbe3001 SET_PID ticks, Dynamixel goal positions) obeys the
        joint limits unless the profile allows raw access, and the estop always. With
        `velocities` (ticks/s, e.g. SET_PID's velocity_ticks_s), those obey the velocity limits
        too (`check_passthrough_velocity_ticks`)."""
        self.require_motion_allowed()
        self.require_no_fault()
        _require_finite(ticks, "pass-through positions")
        if velocities is not None:
            self.check_passthrough_velocity_ticks(velocities)
        q = self.model.transmission.from_ticks(np.asarray(ticks, dtype=float))
        self.check_homed(self.driver.positions, q)
        v = [] if self.profile.raw_access else self.model.violations(q)
        if v:
            raise JointLimit("pass-through position outside the joint limits (the profile does "
                             "not allow raw access): " + "; ".join(v))
        # the envelope holds with raw access too: the target and the straight joint-space path
        self.safety.check_joint_path(self.driver.positions, q)

    def check_passthrough_velocity_ticks(self, velocities: np.ndarray) -> None:
        """Raw joint velocities (ticks/s, one per joint) within the profile's joint velocity
        limits converted to ticks/s, unless the profile allows raw access; 422
        `velocity_limit` naming the joint, the limit and the excess otherwise."""
        _require_finite(velocities, "pass-through velocities")
        if self.profile.raw_access:
            return
        v = np.abs(np.asarray(velocities, dtype=float))
        cap = np.abs(self.model.transmission.velocity_to_ticks(self.model.vmax))
        over = [f"{name} {v[k]:.0f} ticks/s is above its limit {cap[k]:.0f} ticks/s "
                f"({self.model.vmax[k]:g} {'rad' if kind == 'revolute' else 'm'}/s) by "
                f"{v[k] - cap[k]:.0f} ticks/s"
                for k, (name, kind) in enumerate(zip(self.model.names, self.model.kinds,
                                                     strict=True))
                if v[k] > cap[k] * (1 + 1e-9)]
        if over:
            raise VelocityLimit("pass-through velocity over the joint velocity limits (the "
                                "profile does not allow raw access): " + "; ".join(over))

    def check_passthrough_joint_ticks(self, joint: int, ticks: float) -> None:
        """As `check_passthrough_ticks` for one joint's goal (the others unchanged)."""
        self.require_motion_allowed()
        self.require_no_fault()
        if not self.driver.homed[joint]:
            cur = self.driver.positions
            start = None if cur is None else cur[joint:joint + 1]
            self.check_homed_joint(joint, start, ticks)
        if self.profile.raw_access:
            return
        current = self.driver.positions
        base = current.copy() if current is not None else (self.model.lower + self.model.upper) / 2
        all_ticks = self.model.transmission.to_ticks(base)
        all_ticks[joint] = ticks
        self.check_passthrough_ticks(all_ticks)

    # --------------------------------------------------------- stop, estop, gripper

    @on_control
    async def stop(self, reason: str = "stopped by request") -> s.StopResult:
        """Stop all motion; `reason` (who or what stopped it) goes into each motion's record."""
        stopped = await self.motion.stop_all(reason=reason)
        return s.StopResult(stopped=stopped, estop=self.estop)

    @on_control
    async def latch_estop(self) -> s.EstopState:
        """Latch, and command the hold once per latch: a press on a latched estop changes
        nothing (each hold re-commanded at the measured position walked a sagging arm down)."""
        if self.estop:
            return s.EstopState(estop=True)
        self.estop = True
        self.driver.poll_soon()  # a fresh sample that shows the latch, ahead of the schedule
        log.warning("%s: emergency stop latched", self.name)
        self.hub.event("estop", latched=True)
        await self.motion.emergency_stop()
        return s.EstopState(estop=True)

    def release_estop(self) -> s.EstopState:
        if self.estop:
            self.estop = False
            log.info("%s: emergency stop released", self.name)
            self.hub.event("estop_released", latched=False)
        return s.EstopState(estop=False)

    @on_control
    async def set_gripper(self, value: float) -> s.GripperState:
        if not self.profile.gripper.actuated:
            raise NoGripper(f"{self.name} has a {self.profile.gripper.kind} end effector, "
                            "not an actuated gripper")
        self.require_motion_allowed()
        await self.driver.set_gripper(value)  # type: ignore[attr-defined]
        return s.GripperState(value=value)

    def require_protocol(self, protocol: str) -> None:
        if self.protocol != protocol:
            raise NotSupported(f"{self.name} speaks {self.protocol}, not {protocol}")

    def now(self) -> float:
        return time.time()


def _require_finite(values: Any, what: str) -> None:
    """422 for NaN or infinity: the limit checks below compare, and a NaN compares false."""
    a = np.asarray(values, dtype=float)
    if not np.all(np.isfinite(a)):
        raise InvalidRequest(f"{what} must be finite numbers, got {a.tolist()}")
