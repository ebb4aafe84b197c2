"""One hosted arm: its driver (which owns the link), telemetry hub, motion executor and safety
guard (the emergency stop latch and the checks that every path that moves the arm goes
through, app/safety/guard.py), wired together here and nowhere else.

Routes call this; it never touches a link itself (the driver's task does). The motion executor
gets the guard, the driver as its actuator and the model, not the service; the hub stamps each
sample with the estop latch and the motion in progress (app/telemetry/arm_hub.py).
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import logging
import threading
import time
from collections.abc import Awaitable, Callable
from typing import Any, TypeVar

import numpy as np

from app import schemas as s
from app.arms import arm_type, describe
from app.calibration import gravity_run
from app.calibration.book import CalibrationBook
from app.calibration.gravity import GravityFit, default_poses
from app.config import ArmProfile, SafetySettings
from app.device.driver import Driver
from app.device.factory import make_driver
from app.errors import (
    AlreadyHomed,
    Busy,
    InvalidRequest,
    LinkDown,
    NoForceSensing,
    NoGripper,
    NotSupported,
)
from app.links.base import LinkState
from app.motion import replay
from app.motion.executor import MotionExecutor, MotionRecord
from app.motion.stream import AT_REST
from app.runtime import gc_policy
from app.runtime.control_thread import on_home, start_now
from app.runtime.tasks import retrieve, running_loop, soon_on
from app.safety.envelope import ArmSafety
from app.safety.guard import SafetyGuard
from app.sim.hand import Hand
from app.sim.world import World
from app.sim.world_tap import hand_of, world_of
from app.store import Store, StoreError, saved_within
from app.telemetry.arm_hub import ArmHub
from app.telemetry.hub import Subscription, TelemetryHub
from kinematics.singular import TIP_FORCE_MAX_COND, condition_number

log = logging.getLogger(__name__)

#: Longest the estop fast path holds the HTTP thread for the latch, s (see press_estop).
PRESS_WAIT_S = 0.005

T = TypeVar("T")
D = TypeVar("D", bound=Driver)


class ArmService:
    def __init__(self, profile: ArmProfile, driver: Driver | None = None) -> None:
        self.profile = profile
        self.name = profile.name
        #: The arm's hub; a driver built elsewhere (tests) keeps its own, and its samples
        #: then carry the device's fields only.
        self.hub: TelemetryHub = (driver.hub if driver is not None
                                  else ArmHub(profile.name, self._stamp))
        self.driver = driver if driver is not None else make_driver(profile, self.hub)
        self.model = self.driver.model
        self.guard = SafetyGuard(profile, self.model, self.driver)
        self.motion = MotionExecutor(profile.name, self.model, self.guard, self.driver, self.hub,
                                     control_hz=profile.link.control_hz,
                                     cartesian=profile.cartesian)
        # nothing that moves the arm is written while the estop is latched, whenever queued
        self.driver.motion_gate = self.guard.require_not_latched
        #: The joints' zeros on this hardware and the gravity fit (app/calibration), found in
        #: the store as the link comes up.
        self.calibration = CalibrationBook(profile, self.driver, self.hub)
        self.driver.on_link_ready = self.calibration.on_connect
        self._gravity_run: gravity_run.GravityRun | None = None
        #: The hold of the current estop latch (commanded once per latch, app loop), and
        #: whether a press has been told how it went.
        self._hold: asyncio.Future[None] | None = None
        self._hold_told = True
        #: Stop requests served (`stop`, POST /stop): a teleoperation session driving this
        #: arm ends at the next one (app/teleop/session.py). Counted on the control loop.
        self.stops = 0
        #: The gripper's last command (0 open .. 1 closed), None before any (control thread).
        self._gripper_told: float | None = None
        #: Replays' gripper followers (app/motion/replay.py `follow_gripper`), control loop.
        self._grippers: set[asyncio.Task[None]] = set()
        #: Where the estop latch is kept across restarts (`keep_latch_in`); None: nowhere.
        self._latch_store: Store | None = None
        #: The store write of the last latch (`_keep_latch`): a press answers once it is done.
        self._latch_saved: concurrent.futures.Future[bool] | None = None
        #: A latch whose record waits for the estop fast path's sample (`_save_latch`), control
        #: loop.
        self._latch_unsaved = False

    async def start(self) -> None:
        await self.driver.start()
        self.motion.start()

    async def close(self) -> None:
        for task in list(self._grippers):  # a replay's gripper follower ends with the arm
            task.cancel()
        await self.motion.close()
        await self.driver.close()

    @property
    def home_loop(self) -> Any:
        """The control loop this arm runs on (`app.runtime.control_thread`): its async methods
        cross there."""
        return self.driver.home_loop

    @property
    def world(self) -> World | None:
        """The arm's simulated world (app/sim/world.py) when its link is simulated in this
        process, else None (a real arm, or a simulator on a pty or socket)."""
        return world_of(getattr(self.driver.link, "device", None))

    @property
    def hand(self) -> Hand | None:
        """The hand in the arm's simulated world (app/sim/hand.py: it moves the simulated
        servos whose torque is off), else None (a real arm, no world, no servos)."""
        return hand_of(getattr(self.driver.link, "device", None))

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
        return describe.capabilities(self.profile, self.model)

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
                           # the rate polled: a Dynamixel bus too slow for the profile's
                           # polls at what it carries (app/arms/dynamixel/bus_rate.py)
                           poll_hz=self.driver.profile.link.poll_hz,
                           faults=[s.Fault(**f) for f in self.driver.faults],
                           homed=list(self.driver.homed),
                           calibrated=list(self.driver.calibrated),
                           torque=[k not in self.driver.torque_off
                                   for k in range(len(self.profile.joints))],
                           firmware=self.driver.firmware_note, force=self.force_info(),
                           chain=s.ArmChain.model_validate(self.model.describe()),
                           telemetry=s.TelemetryStats(subscribers=self.hub.subscriber_count,
                                                      published=self.hub.published,
                                                      dropped=self.hub.dropped_total))

    # --------------------------------------------------------- force (API.md "Force")

    def force_info(self) -> s.ForceInfo | None:
        """How far the torques and tip force can be trusted, and why tip_force is null."""
        if not describe.force_sensing(self.profile):
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
        info = s.ForceInfo(source=source, calibrated=calibrated, note=note,
                           tare=None if tare is None else [float(v) for v in tare],
                           max_condition_number=TIP_FORCE_MAX_COND,
                           gravity_compensated=self.driver.gravity is not None)
        q = self.driver.positions
        if q is not None:
            J = self.model.jacobian(q)
            c = float(condition_number(J))
            info.condition_number = c if np.isfinite(c) else None
            info.tip_force_unavailable = self.model.tip_force_unavailable(q, J)
        return info

    async def tare_force(self) -> s.ForceTare:
        """Runs `_tare_force` on the arm's control loop (the tare is the owner task's)."""
        return await on_home(self.home_loop, self._tare_force)

    async def _tare_force(self) -> s.ForceTare:
        """The current joint torques become the zero of `torques` and `tip_force`."""
        self._require_force()
        drv = self.driver
        if drv.stale or drv.torques_raw is None:
            raise LinkDown(f"{self.name}: no fresh torque reading to tare against "
                           f"({drv.last_error or drv.link.state.value})")
        drv.torque_tare = np.array(drv.torques_raw, dtype=float)
        if drv.gravity is not None and drv.positions is not None:  # the tool's load only
            drv.torque_tare = drv.torque_tare - drv.gravity(drv.positions)
        self.hub.event("force_tare", offsets=[float(v) for v in drv.torque_tare])
        return s.ForceTare(joints=list(self.model.names),
                           offsets=[float(v) for v in drv.torque_tare])

    async def clear_tare(self) -> s.ForceTare:
        """Runs `_clear_tare` on the arm's control loop (the tare is the owner task's)."""
        return await on_home(self.home_loop, self._clear_tare)

    async def _clear_tare(self) -> s.ForceTare:
        self._require_force()
        self.driver.torque_tare = None
        self.hub.event("force_tare", offsets=None)
        return s.ForceTare(joints=list(self.model.names), offsets=None)

    def _require_force(self) -> None:
        if not describe.force_sensing(self.profile):
            raise NoForceSensing(f"{self.name} senses no joint torques: nothing to tare")

    def state(self) -> dict[str, Any]:
        """The latest sample; 503 link_down if the device has never answered."""
        latest = self.hub.latest
        if latest is None:
            raise LinkDown(f"{self.name}: no sample from the device yet "
                           f"({self.driver.link.last_error or self.driver.link.state.value})")
        return latest

    def _stamp(self, sample: dict[str, Any]) -> None:
        """The arm's own fields of a sample, set where it is published (the hub)."""
        sample["estop"] = self.guard.estop
        sample["motion"] = self.motion.brief()

    # --------------------------------------------------------- safety: the guard's, one place

    @property
    def estop(self) -> bool:
        return self.guard.estop

    @property
    def closing(self) -> bool:
        return self.guard.closing

    @closing.setter
    def closing(self, value: bool) -> None:
        self.guard.closing = value

    @property
    def safety(self) -> ArmSafety:
        return self.guard.safety

    # --------------------------------------------------------- pass-through commands

    def require_motion_allowed(self) -> None:
        self.guard.require_motion_allowed()

    def require_torque(self) -> None:
        self.guard.require_torque()

    def _require_no_motion(self, then: str) -> None:
        """409 `busy` while a planned motion runs or is queued (on the control loop): `then`
        says when to stop it ("before homing", "first")."""
        if self.motion.current is not None or self.motion.queued():
            raise Busy(f"{self.name}: a motion is running or queued; stop it {then}")

    async def command_passthrough(self, goals: dict[int, float],
                                  send: Callable[[], Awaitable[T]]) -> T:
        """Runs `_command_passthrough` on the arm's control loop (its state changes only there).
        The goal holds automatic garbage collections off until its effect can have been seen
        (`gc_policy.hold`: a collection stops every thread, and set the goal's p99, issue 23)."""
        gc_policy.hold()
        return await on_home(self.home_loop, lambda: self._command_passthrough(goals, send))

    async def _command_passthrough(self, goals: dict[int, float],
                                   send: Callable[[], Awaitable[T]]) -> T:
        """A pass-through position command (joint index -> encoder ticks), checked and sent
        on the control thread in one step: nothing (an estop, a motion, another command)
        comes between the check and the queue, and the owner task still refuses it if the
        estop latches before it is written. Checked like a planned move (the guard's
        `check_passthrough`): from where the arm is, to the joints' last commands with these
        goals in place. 409 `busy` while a planned motion runs or is queued: the arm has one
        commanded state, and the executor is streaming it."""
        if self.motion.current is not None or self.motion.queued():
            raise Busy(f"{self.name}: a planned motion is running or queued: stop it "
                       f"(POST /api/v1/arms/{self.name}/stop) before a pass-through command")
        told = self.driver.told()
        if told is None or self.driver.stale:
            raise LinkDown(f"{self.name}: no fresh joint positions from the device to check a "
                           "pass-through command against")
        tr = self.model.transmission
        ticks_all = np.array(tr.to_ticks(told), dtype=float)
        for k, ticks in goals.items():
            ticks_all[k] = ticks
        self.guard.check_passthrough(np.asarray(tr.from_ticks(ticks_all), dtype=float),
                                     self.driver.pace())
        return await send()

    async def command_setpoint(self, q: np.ndarray) -> None:
        """Runs `_command_setpoint` on the arm's control loop (its state changes only there)."""
        return await on_home(self.home_loop, lambda: self._command_setpoint(q))

    async def _command_setpoint(self, q: np.ndarray) -> None:
        """One streamed joint setpoint (rad or m, every joint) from a source outside the
        planner that sends one each period (teleoperation, app/teleop/): checked and sent in
        one step on the control thread like a pass-through position (the guard's
        `check_passthrough`: the latch, faults, homing, the joint limits, the envelope along
        the path from where the arm is, the step speed) and written as the executor's own
        setpoints are (`command_joints`, gated by the latch, noted as the commanded state).
        409 `busy` while a planned motion runs or is queued (it streams the one commanded
        state); a refused setpoint sends nothing, so the arm holds its last command."""
        if self.motion.current is not None or self.motion.queued():
            raise Busy(f"{self.name}: a planned motion is running or queued: stop it "
                       f"(POST /api/v1/arms/{self.name}/stop) before streaming setpoints")
        target = np.asarray(q, dtype=float)
        if target.shape != (self.model.n,):
            raise InvalidRequest(f"{self.name}: a setpoint takes {self.model.n} joints, got "
                                 f"shape {list(target.shape)}")
        self.guard.check_passthrough(target, self.driver.pace())
        await self.driver.command_joints(target)

    # --------------------------------------------------------- the envelope, at once

    async def apply_safety(self, new: SafetySettings) -> None:
        """Runs `_apply_safety` on the arm's control loop (its state changes only there)."""
        return await on_home(self.home_loop, lambda: self._apply_safety(new))

    async def _apply_safety(self, new: SafetySettings) -> None:
        """Change the envelope on the control thread, where motion is planned and checked.
        It applies at once: a change that adds or moves a zone or raises the floor is
        refused with 409 `busy` while a motion runs or is queued or the arm moves (the
        running plan was checked against the old envelope; stop it, change, move again);
        422 `keep_out` if the arm, or the path to where it was last told to go, is inside
        the new envelope. A change that only loosens it (a zone removed, the floor lowered or
        removed, the speed override) applies whatever the arm does."""
        cur = self.safety.settings
        tighter = (any(z not in cur.zones for z in new.zones)
                   or (new.floor_z is not None
                       and (cur.floor_z is None or new.floor_z > cur.floor_z)))
        if tighter:
            drv = self.driver
            moving = drv.velocities is not None and bool(np.any(
                np.abs(drv.velocities) > self.model.vmax * AT_REST))
            if self.motion.current is not None or self.motion.queued() or moving:
                raise Busy(f"{self.name}: the arm is moving: a new keep-out zone or floor "
                           "applies at once, and the running motion was checked against the "
                           f"old envelope. Stop it (POST /api/v1/arms/{self.name}/stop) and "
                           "change the envelope, then move again")
            here, told = drv.positions, drv.told()
            if here is not None:
                check = self.safety.preview(new)
                check.check_pose(here, "where the arm is now (move it out first)")
                if told is not None:
                    check.check_joint_path(here, told)
        self.safety.apply(new, "stored")

    async def home(self, positions: list[float] | None, rehome: bool = False) -> s.ArmDetail:
        """Runs `_home` on the arm's control loop (its state changes only there)."""
        return await on_home(self.home_loop, lambda: self._home(positions, rehome))

    async def _home(self, positions: list[float] | None, rehome: bool = False) -> s.ArmDetail:
        """Declare the arm's current physical pose (the profile's home pose by default): the
        joints that need homing take these positions; the others read absolute positions and
        keep them. The commanded state is forgotten, so the next motion starts from the
        measured pose. On an arm whose joints that need homing are all homed, a declaration
        would move the joint limits and the zones with it: 409 `already_homed` unless
        `rehome` (an instructor's) or the arm was un-homed first (`unhome`)."""
        self._require_no_motion("before homing")
        needs = [k for k, j in enumerate(self.profile.joints) if j.needs_homing]
        if needs and all(self.driver.homed[k] for k in needs) and not rehome:
            raise AlreadyHomed(
                f"{self.name} is homed: it knows where its joints are, and a new declaration "
                "would move its joint limits and keep-out zones with it. An instructor may "
                f"re-home it; or un-home it first on purpose (DELETE /api/v1/arms/{self.name}"
                "/home), then home it")
        if positions is None:
            if self.profile.home is None:
                raise InvalidRequest(f"{self.name}'s profile has no home pose: give positions")
            positions = list(self.profile.home)
        q = self.model.joint_vector(positions)
        self.guard.check_joint_target(q)
        if self.driver.positions is None or self.driver.stale:
            raise LinkDown(f"{self.name}: no fresh joint positions from the device to home from")
        for k, j in enumerate(self.profile.joints):
            if j.needs_homing:
                self.driver.set_home(k, float(q[k]))
        self.motion.forget_command()
        log.info("%s: homed at %s", self.name, [round(float(v), 5) for v in q])
        self.hub.event("homed", positions=[float(v) for v in q])
        return self.detail()

    async def unhome(self) -> s.ArmDetail:
        """Runs `_unhome` on the arm's control loop (its state changes only there)."""
        return await on_home(self.home_loop, lambda: self._unhome())

    async def _unhome(self) -> s.ArmDetail:
        """Forget the zero of every joint that needs homing, on purpose: moves that would move
        them are refused (409 `not_homed`) until the arm is homed again."""
        self._require_no_motion("before un-homing")
        for k, j in enumerate(self.profile.joints):
            if j.needs_homing:
                self.driver.homed[k] = False
        log.info("%s: un-homed", self.name)
        self.hub.event("unhomed", homed=list(self.driver.homed))
        return self.detail()

    # --------------------------------------------------------- calibration (API.md v1.2)

    def use_store(self, store: Store) -> None:
        """At start-up, before the arm runs: the store its calibration is kept in."""
        self.calibration.store = store

    def keep_latch_in(self, store: Store) -> None:
        """At start-up, before the arm runs: the estop latch is kept in `store` from now on,
        and a latch it holds from before is set again. A server, or a lab's worker, that
        stopped, crashed or was killed while the estop was latched comes back latched: only a
        release (DELETE .../estop) releases it, never a restart. A record the store cannot
        read is said in the log and latches nothing (as a stored envelope that cannot be read
        leaves the profile's)."""
        self._latch_store = store
        try:
            record = store.latch_of(self.name)
        except (StoreError, ValueError) as exc:
            log.error("%s: the stored estop latch could not be read: %s",  # noqa: TRY400
                      self.name, exc)
            return
        if isinstance(record, dict) and record.get("latched") is True:
            self.guard.latch()
            log.warning("%s: emergency stop latched since %s, before this start: still latched "
                        "(DELETE /api/v1/arms/%s/estop releases it)", self.name,
                        record.get("at", "an unknown time"), self.name)

    def _keep_latch(self, latched: bool) -> concurrent.futures.Future[bool] | None:
        """Record the latch in the store without waiting for the disk (it lands in order
        with the other settings; one the disk refuses is kept and retried): the write's
        future (True: on disk), None without a store."""
        if self._latch_store is None:
            return None
        return self._latch_store.put_latch(self.name, latched)

    def calibration_view(self) -> s.ArmCalibration:
        return self.calibration.view(self._gravity_run)

    async def calibrate(self, positions: list[float] | None,
                        pose: str | None) -> s.ArmCalibration:
        """Runs `_calibrate` on the arm's control loop (the transmission is its)."""
        return await on_home(self.home_loop, lambda: self._calibrate(positions, pose))

    async def _calibrate(self, positions: list[float] | None,
                         pose: str | None) -> s.ArmCalibration:
        """The arm is at `positions` (or the profile's calibration pose `pose`) now: the
        joints whose zero the hardware does not know take these values (nothing moves), and
        the calibration is stored under the hardware's identity. 409 `busy` while a motion
        runs or is queued; 503 `link_down` without a fresh reading."""
        if pose is not None:
            named = self.profile.calibration_poses.get(pose)
            if named is None:
                raise InvalidRequest(f"{self.name} has no calibration pose {pose!r}; it has "
                                  f"{sorted(self.profile.calibration_poses) or 'none'}")
            positions = list(named)
        assert positions is not None  # (the schema gives one of the two)
        q = self.model.joint_vector(positions)
        self.guard.check_joint_target(q)
        if not self.profile.calibration_joints:
            raise NotSupported(f"every joint's zero is known to {self.name}'s hardware: "
                               "nothing to calibrate")
        self._require_no_motion("before calibrating")
        if self.driver.positions is None or self.driver.stale:
            raise LinkDown(f"{self.name}: no fresh joint positions from the device to "
                           "calibrate against")
        joints = self.calibration.declare(q)
        self.motion.forget_command()
        await self.calibration.save()
        log.info("%s: calibrated %s at %s (%s)", self.name,
                 [self.model.names[k] for k in joints], [round(float(v), 5) for v in q],
                 self.calibration.identity)
        self.hub.event("calibrated", positions=[float(v) for v in q],
                       calibrated=list(self.driver.calibrated))
        return self.calibration_view()

    async def forget_calibration(self) -> s.ArmCalibration:
        """Runs `_forget_calibration` on the arm's control loop."""
        return await on_home(self.home_loop, self._forget_calibration)

    async def _forget_calibration(self) -> s.ArmCalibration:
        """Drop the stored calibration of this hardware and go back to what the profile
        knows: joints whose zero the hardware does not know are not calibrated again, and
        the gravity fit is gone. 409 `busy` while a motion runs or is queued."""
        self._require_no_motion("first")
        self.calibration.forget()
        self.motion.forget_command()
        await self.calibration.drop()
        self.hub.event("calibrated", positions=None, calibrated=list(self.driver.calibrated))
        return self.calibration_view()

    async def calibrate_gravity(self, poses: list[list[float]] | None,
                                wait: bool) -> s.GravityRun:
        """Runs `_calibrate_gravity` on the arm's control loop."""
        return await on_home(self.home_loop, lambda: self._calibrate_gravity(poses, wait))

    async def _calibrate_gravity(self, poses: list[list[float]] | None,
                                 wait: bool) -> s.GravityRun:
        """Start the gravity calibration's motion (app/calibration/gravity_run.py): each pose
        a planned joint move (every check of a move applies), the raw torques measured at
        rest there; then the fit, stored with the calibration. 409 `busy` while a motion (or
        another run) is running or queued; 409 `no_force_sensing` on an arm without torques."""
        self._require_force()
        self.guard.require_motion_allowed()
        run = self._gravity_run
        if (run is not None and run.status == "running") or self.motion.current is not None \
                or self.motion.queued():
            raise Busy(f"{self.name}: a motion or a gravity calibration is running")
        m = self.model
        lower, upper = np.array(self.profile.lower), np.array(self.profile.upper)
        if poses is None:
            home = self.profile.home or list((lower + upper) / 2.0)
            qs = default_poses(m, m.joint_vector(home), lower, upper)
        else:
            qs = np.array([m.joint_vector(p) for p in poses])
        for q in qs:
            self.guard.check_joint_target(q)
            self.guard.check_calibrated(None, q)
        run = gravity_run.GravityRun(poses=qs.tolist())
        self._gravity_run = run
        run.task = asyncio.ensure_future(gravity_run.run(
            run, m, self._gravity_move, self._gravity_rest, self._gravity_done))
        run.task.add_done_callback(lambda t: self._gravity_ended(run, t))
        if wait:
            await asyncio.shield(run.task)
        return self.calibration.run_view(run)

    async def _gravity_move(self, q: list[float]) -> tuple[str, str, str | None]:
        rec = await self.motion.move_joints(s.MoveJoints(positions=q))
        await rec.wait()
        return rec.id, rec.status, rec.reason

    async def _gravity_rest(self, n: int, timeout: float) -> tuple[np.ndarray,
                                                                   np.ndarray] | None:
        """`n` readings in a row at rest (every joint under AT_REST of its limit), averaged:
        joint values and raw torques (no gravity fit, no tare)."""
        drv, vmax = self.driver, self.model.vmax
        got: list[tuple[np.ndarray, np.ndarray]] = []

        def collect(sample: dict[str, Any]) -> bool:
            q, qd, tau = drv.positions, drv.velocities, drv.torques_raw
            if sample.get("stale") or q is None or qd is None or tau is None \
                    or np.any(np.abs(qd) > vmax * AT_REST):
                got.clear()
                return False
            got.append((np.array(q, dtype=float), np.array(tau, dtype=float)))
            return len(got) >= n

        if not await self.hub.sample_where(collect, timeout):
            return None
        return (np.mean([g[0] for g in got], axis=0), np.mean([g[1] for g in got], axis=0))

    async def _gravity_done(self, fit: GravityFit) -> None:
        self.calibration.set_gravity(fit)
        await self.calibration.save()
        self.hub.event("gravity_calibrated", rms=fit.rms, worst=fit.worst)

    def _gravity_ended(self, run: gravity_run.GravityRun, task: asyncio.Task[None]) -> None:
        if task.cancelled():
            run.fail("cancelled")
        elif task.exception() is not None:
            exc = task.exception()
            run.fail(f"{type(exc).__name__}: {getattr(exc, 'detail', exc)}")

    async def reboot(self, dxl_id: int) -> None:
        """Runs `_reboot` on the arm's control loop (its state changes only there)."""
        return await on_home(self.home_loop, lambda: self._reboot(dxl_id))

    async def _reboot(self, dxl_id: int) -> None:
        """REBOOT one servo and set it up again (the driver); the commanded state is
        forgotten: the servo's goal is now its present position."""
        self.guard.require_motion_allowed()
        self._require_no_motion("before a reboot")
        await self.driver.reboot(dxl_id)
        self.motion.forget_command()
        self.hub.event("rebooted", servo=dxl_id, homed=list(self.driver.homed))

    async def torque_on_holding(self, hold: Callable[[], Awaitable[None]],
                                send: Callable[[], Awaitable[T]]) -> T:
        """Runs `_torque_on_holding` on the arm's control loop (its state changes only there)."""
        return await on_home(self.home_loop, lambda: self._torque_on_holding(hold, send))

    async def _torque_on_holding(self, hold: Callable[[], Awaitable[None]],
                                 send: Callable[[], Awaitable[T]]) -> T:
        """A pass-through Torque Enable 1 to joint servos (raw access): as the torque route,
        `hold()` first writes each one's Goal Position as its Present Position, so that it
        holds where a hand or gravity left it instead of driving to an older goal no check
        has seen (the envelope holds with raw access too); then `send()` writes the Torque
        Enable. 409 `busy` while a planned motion runs or is queued (it streams the commanded
        state)."""
        self._require_no_motion("before switching the torque")
        await hold()
        self.motion.forget_command()
        return await send()

    async def set_torque(self, on: bool) -> None:
        """Runs `_set_torque` on the arm's control loop (its state changes only there)."""
        return await on_home(self.home_loop, lambda: self._set_torque(on))

    async def _set_torque(self, on: bool) -> None:
        """The joints' torque off (the arm free to be moved by hand: a teleoperation leader) or
        on again holding where it is (the driver's `set_torque`; 409 `not_supported` where
        the device cannot). 409 `busy` while a motion runs or is queued. The executor's last
        setpoint is forgotten: the arm is wherever the hand leaves it."""
        self._require_no_motion("before switching the torque")
        await self.driver.set_torque(on)
        self.motion.forget_command()
        log.info("%s: torque %s", self.name, "on" if on else "off")
        self.hub.event("torque", on=on)

    # --------------------------------------------------------- stop, estop, gripper

    async def stop(self, reason: str = "stopped by request") -> s.StopResult:
        """Runs `_stop` on the arm's control loop (its state changes only there)."""
        return await on_home(self.home_loop, lambda: self._stop(reason))

    async def _stop(self, reason: str = "stopped by request") -> s.StopResult:
        """Stop all motion; `reason` (who or what stopped it) goes into each motion's record.
        Counted in `stops`: a teleoperation session driving the arm ends too."""
        self.stops += 1
        stopped = await self.motion.stop_all(reason=reason)
        return s.StopResult(stopped=stopped, estop=self.estop)

    async def latch_estop(self) -> s.EstopState:
        """Runs `_latch_estop` on the arm's control loop (its state changes only there)."""
        return await on_home(self.home_loop, lambda: self._latch_estop())

    async def _latch_estop(self) -> s.EstopState:
        """Latch, and command the hold once per latch: a press on a latched estop changes
        nothing (each hold re-commanded at the measured position walked a sagging arm down).
        Answers when the latch's hold is commanded; its error, if it failed, goes to the
        presses that waited for it (the estop fast path's press and the route's that follows
        it are two presses of one request)."""
        return await self._latch()

    def press_estop(self) -> None:
        """Latch from the HTTP thread without waiting for its loop: the estop fast path
        (app/web/routes/arms.py) presses as soon as a request's head is read; the route's press
        follows and reports. With the arm on the control thread, this thread then waits (up
        to PRESS_WAIT_S) until the latch is set there: both threads share one core and one
        GIL, and the control thread, woken, would otherwise wait for the rest of this
        request (about half a millisecond) before latching and publishing the sample that
        shows it."""
        latched = threading.Event()
        home = self.home_loop
        start_now(home, self._latch(latched))
        if home is not None and home is not running_loop():
            latched.wait(PRESS_WAIT_S)

    def pressed_sample_sent(self) -> None:
        """The estop fast path's word, from the HTTP thread, that the sample showing its
        latch is out (or will not come): the latch's record goes to the store's writer now.
        The writer's thread woken with the latch took the GIL from the HTTP thread sending
        that sample: 0.3 ms of the estop seen's median, 0.3-0.5 ms of its p99 in one process
        (docs/performance.md, session 35). The record waits for this, for the hold's end or
        for the route's press, whichever comes first."""
        home = self.home_loop
        if home is None or home.is_closed():
            self._save_latch()
        else:
            soon_on(home, self._save_latch)

    def _save_latch(self) -> None:
        """On the control loop: a latch whose record waits (`_latch` from the fast path) goes
        to the store's writer. A release in between wrote its own record and cleared it."""
        if self._latch_unsaved:
            self._latch_unsaved = False
            self._latch_saved = self._keep_latch(True)

    async def _latch(self, latched: threading.Event | None = None) -> s.EstopState:
        fresh = self.guard.latch()
        if fresh:
            self.driver.hold_coming()  # no poll goes before the hold queued below
            # The latch shows at once, in a sample of the latest reading: clients do not wait
            # a device round trip for it, and the hold goes to the device before any poll.
            self.driver.publish_state()
        if latched is not None:
            latched.set()
        if fresh:
            # The hold's task is there before this yields (a press that comes meanwhile waits
            # for it). The log line and the event come once it has ended: between the hold's
            # start and its write they kept the control thread (and the GIL) 0.15-0.3 ms longer
            # from the hold and the HTTP thread from the sample above (issue 27).
            started = asyncio.ensure_future(self.motion.emergency_stop())
            started.add_done_callback(retrieve)  # (the presses that waited were told)
            self._hold, self._hold_told = started, False
            # The record goes to the store's writer before the hold ends (after it, a crash
            # during the hold's device round trip lost it); the writer's thread does the disk.
            # A press from the fast path (`latched`) has its thread send the sample first
            # (`pressed_sample_sent`); any other goes now.
            if latched is None:
                self._latch_saved = self._keep_latch(True)
            else:
                self._latch_unsaved = True
        hold = self._hold
        try:
            if hold is not None and not hold.done():
                self._hold_told = True
                await asyncio.shield(hold)  # (a client that gives up does not cancel the hold)
            elif hold is not None and not self._hold_told:  # it ended before this press came
                self._hold_told = True
                hold.result()  # its error, if it failed
            # An answered press is on disk: a crash after the answer starts the arm latched.
            # A disk that refuses it (kept in memory, retried; health says) or holds it longer
            # than LATCH_SAVE_WAIT_S (app/store.py) does not hold the answer back.
            self._save_latch()
            await saved_within(self._latch_saved)
        finally:
            if fresh:
                self._save_latch()  # (a hold that failed: the latch is kept all the same)
                log.warning("%s: emergency stop latched", self.name)
                self.hub.event("estop", latched=True)
        return s.EstopState(estop=True)

    async def release_estop(self) -> s.EstopState:
        """Runs `_release_estop` on the arm's control loop (the latch is its)."""
        return await on_home(self.home_loop, self._release_estop)

    async def _release_estop(self) -> s.EstopState:
        if self.guard.release():
            # As the latch: the release shows at once, in a sample of the latest reading, so a
            # client that reads the state after the DELETE sees it (an arm at rest publishes
            # its repeats in batches; its latest sample could still say latched).
            self.driver.publish_state()
            self._latch_unsaved = False  # (this record is the newer)
            self._keep_latch(False)
            log.info("%s: emergency stop released", self.name)
            self.hub.event("estop_released", latched=False)
        return s.EstopState(estop=False)

    async def set_gripper(self, value: float) -> s.GripperState:
        """On the control loop: `_set_gripper`."""
        return await on_home(self.home_loop, lambda: self._set_gripper(value))

    async def _set_gripper(self, value: float) -> s.GripperState:
        if not self.profile.gripper.actuated:
            raise NoGripper(f"{self.name} has a {self.profile.gripper.kind} end effector, "
                            "not an actuated gripper")
        self.guard.require_motion_allowed()
        await self.driver.set_gripper(value)
        self._gripper_told = value
        return s.GripperState(value=value)

    # --------------------------------------------------------- the facade: motion

    async def move_joints(self, req: s.MoveJoints) -> MotionRecord:
        return await self.motion.move_joints(req)

    async def move_pose(self, req: s.MovePose) -> MotionRecord:
        return await self.motion.move_pose(req)

    async def replay(self, targets: np.ndarray, fps: float,
                     gripper: np.ndarray | None = None) -> MotionRecord:
        """Play joint targets (T, n) back at `fps` as one motion: a soft start to the first,
        then the frames, checked and streamed like a move (app/motion/replay.py). `gripper`
        (T,), 0 open .. 1 closed: each frame's gripper action sent as the motion reaches the
        frame, through `set_gripper` (409 `no_gripper` on an arm without an actuated one)."""
        return await on_home(self.home_loop, lambda: self._replay(targets, fps, gripper))

    async def _replay(self, targets: np.ndarray, fps: float,
                      gripper: np.ndarray | None) -> MotionRecord:
        g = None
        if gripper is not None:
            if not self.profile.gripper.actuated:
                raise NoGripper(f"{self.name} has a {self.profile.gripper.kind} end effector: "
                                "a gripper's actions cannot be replayed on it")
            g = replay.check_gripper(gripper, len(targets))
        rec = await self.motion.replay(targets, fps)
        if g is not None and isinstance(rec.planner, replay.ReplayPlanner):
            task = asyncio.create_task(replay.follow_gripper(rec, rec.planner, g,
                                                             self.set_gripper),
                                       name=f"replay-gripper:{self.name}")
            self._grippers.add(task)
            task.add_done_callback(self._grippers.discard)
            task.add_done_callback(retrieve)
        return rec

    async def preview_joints(self, req: s.MoveJoints) -> s.Motion:
        """A joint move's plan, nothing sent (planned on the control loop, from its queue)."""
        async def plan() -> s.Motion:
            return self.motion.preview_joints(req)
        return await on_home(self.home_loop, plan)

    async def preview_pose(self, req: s.MovePose) -> s.Motion:
        async def plan() -> s.Motion:
            return self.motion.preview_pose(req)
        return await on_home(self.home_loop, plan)

    def motion_record(self, motion_id: str) -> MotionRecord:
        return self.motion.get(motion_id)

    async def cancel_motion(self, motion_id: str, reason: str) -> MotionRecord:
        return await self.motion.cancel(motion_id, reason)

    async def stop_all(self, reason: str) -> list[str]:
        return await self.motion.stop_all(reason=reason)

    async def emergency_hold(self) -> None:
        """Stop streaming and hold where the arm is (the executor's), without the latch."""
        await self.motion.emergency_stop()

    @property
    def moving(self) -> bool:
        """A motion is running."""
        return self.motion.current is not None

    @property
    def in_motion(self) -> bool:
        """A motion is running, or the last reading had a joint moving (a pass-through goal's
        servos on their way): what the garbage-collection policy waits out (app/runtime/
        gc_policy.py; read from any thread)."""
        if self.motion.current is not None:
            return True
        qd = self.driver.velocities
        return qd is not None and bool(np.any(np.abs(qd) > self.model.vmax * AT_REST))

    # --------------------------------------------------------- the facade: the device

    @property
    def positions(self) -> np.ndarray | None:
        """The last joint reading (rad, m), None before any."""
        return self.driver.positions

    def setpoint(self) -> np.ndarray | None:
        """Where each joint was last told to go (rad, m): the one commanded record
        (`Driver.told`), the measured position for a joint told nothing since the link came
        up; None before any reading. A plain read, from any thread (a recording's action)."""
        return self.driver.told()

    def gripper_setpoint(self) -> float | None:
        """The gripper's last command (0 open .. 1 closed) since the server started, None before
        any. A plain read, from any thread (a recording's action)."""
        return self._gripper_told

    # --------------------------------------------------------- the facade: telemetry

    def event(self, name: str, **data: Any) -> None:
        """An event on the arm's telemetry stream."""
        self.hub.event(name, **data)

    def subscribe(self, backlog: int | None = None) -> Subscription:
        return self.hub.subscribe(backlog)

    @property
    def subscriber_count(self) -> int:
        return self.hub.subscriber_count

    @property
    def latest_bytes(self) -> bytes | None:
        return self.hub.latest_bytes

    async def sample_where(self, pred: Callable[[dict[str, Any]], bool], timeout: float,
                           then: Callable[[], None] | None = None) -> bool:
        return await self.hub.sample_where(pred, timeout, then)

    def bind_fanout(self) -> None:
        self.hub.bind_fanout()

    # --------------------------------------------------------- the facade: the envelope

    def safety_view(self, stored: bool, store_error: str | None, settings_pending: int,
                    editable: bool) -> s.Safety:
        """The envelope as API.md's `Safety`: `persisted` unless there is no store (`stored`
        False) or a stored setting waits."""
        env, cfg = self.safety, self.safety.settings
        persisted = env.source == "profile" or (stored and settings_pending == 0)
        return s.Safety(zones=list(cfg.zones), floor_z=cfg.floor_z,
                        speed_override=cfg.speed_override, tool_margin=env.profile.tool_margin,
                        body_margin=env.profile.body_margin, body_points=list(env.bodies),
                        source=env.source, persisted=persisted, editable=editable,
                        store_error=store_error)

    @property
    def safety_settings(self) -> SafetySettings:
        return self.safety.settings

    def restore_safety(self, settings: SafetySettings) -> None:
        """At start-up, before the arm runs: the stored settings replace the profile's."""
        self.safety.apply(settings, "stored")

    def check_passthrough_velocities(self, velocities: np.ndarray) -> None:
        self.guard.check_passthrough_velocity_ticks(velocities)

    @property
    def faults(self) -> list[dict[str, Any]]:
        """The hardware faults the driver reports now (API "Faults and homing"); empty when
        all is well."""
        return list(self.driver.faults)

    def require_protocol(self, protocol: str) -> None:
        if self.protocol != protocol:
            raise NotSupported(f"{self.name} speaks {self.protocol}, not {protocol}")

    def protocol_driver(self, protocol: str, kind: type[D]) -> D:
        """The arm's driver as `kind`, the driver of the wire protocol a pass-through router
        speaks (its reads; its commands go through `command_passthrough`), or 409
        `not_supported` on an arm that speaks another protocol."""
        self.require_protocol(protocol)
        if not isinstance(self.driver, kind):
            raise NotSupported(f"{self.name}'s driver is not a {kind.__name__}")
        return self.driver

    def now(self) -> float:
        return time.time()

