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
from app.config import ArmProfile
from app.control import on_control
from app.devices.base import Driver
from app.devices.factory import make_driver
from app.errors import (
    ArmError,
    EstopLatched,
    InvalidRequest,
    JointLimit,
    LinkDown,
    NoGripper,
    NotSupported,
    VelocityLimit,
)
from app.links.base import LinkState
from app.motion import MotionExecutor
from app.telemetry import TelemetryHub

log = logging.getLogger(__name__)


class ArmService:
    def __init__(self, profile: ArmProfile, driver: Driver | None = None) -> None:
        self.profile = profile
        self.name = profile.name
        self.hub = driver.hub if driver is not None else TelemetryHub(profile.name)
        self.driver = driver if driver is not None else make_driver(profile, self.hub)
        self.model = self.driver.model
        self.estop = False
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
        return "rbe3001" if self.profile.model == "rbe3001" else "dynamixel"

    def link_status(self) -> s.LinkStatus:
        link = self.driver.link
        return s.LinkStatus(kind=link.kind, address=link.address, state=link.state.value,
                            connected=link.state is LinkState.UP,
                            last_error=link.last_error or self.driver.last_error)

    def capabilities(self) -> s.Capabilities:
        return s.Capabilities(gripper=self.profile.gripper.actuated,
                              force_sensing=self._force_sensing(), protocol=self.protocol)

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
                           poll_hz=self.profile.link.poll_hz)

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
        _require_finite(ticks, "pass-through positions")
        if velocities is not None:
            self.check_passthrough_velocity_ticks(velocities)
        if self.profile.raw_access:
            return
        q = self.model.transmission.from_ticks(np.asarray(ticks, dtype=float))
        v = self.model.violations(q)
        if v:
            raise JointLimit("pass-through position outside the joint limits (the profile does "
                             "not allow raw access): " + "; ".join(v))

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
        if self.profile.raw_access:
            return
        current = self.driver.positions
        base = current.copy() if current is not None else (self.model.lower + self.model.upper) / 2
        all_ticks = self.model.transmission.to_ticks(base)
        all_ticks[joint] = ticks
        self.check_passthrough_ticks(all_ticks)

    # --------------------------------------------------------- stop, estop, gripper

    @on_control
    async def stop(self) -> s.StopResult:
        stopped = await self.motion.stop_all(reason="stopped by request")
        return s.StopResult(stopped=stopped, estop=self.estop)

    @on_control
    async def latch_estop(self) -> s.EstopState:
        """Latch, and command the hold once per latch: a press on a latched estop changes
        nothing (each hold re-commanded at the measured position walked a sagging arm down)."""
        if self.estop:
            return s.EstopState(estop=True)
        self.estop = True
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
