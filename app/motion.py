"""Per-arm motion queue and executor.

A move is checked and planned when it is submitted (joint limits, reachability, every point of
a line), so a bad move is refused with 422 before anything is sent. It is planned again from the
arm's commanded state when it starts, time-parameterised by ruckig under the profile's velocity,
acceleration and jerk limits, and streamed to the driver as setpoints at the profile's control
rate. It ends `done` only when the measured joints settle at the target; a device that stops
answering fails it with the device's error code (the watchdog), and the arm is told to hold.
"""

from __future__ import annotations

import asyncio
import itertools
import logging
import time
import uuid
from collections import OrderedDict, deque
from dataclasses import dataclass, field
from types import SimpleNamespace
from typing import TYPE_CHECKING, Any, Literal

import numpy as np

from app import schemas as s
from app.control import on_control
from app.errors import (
    ArmError,
    Busy,
    InvalidRequest,
    JointLimit,
    LinkDown,
    MotionExpired,
    UnknownMotion,
    Unreachable,
)
from app.links.base import LinkState
from app.tasks import cancel_and_wait
from kinematics import pprp, trajectory
from kinematics.errors import KinematicsError, LimitViolation, TrajectoryError
from kinematics.errors import Unreachable as KinematicsUnreachable

if TYPE_CHECKING:
    from app.service import ArmService

log = logging.getLogger(__name__)

MAX_QUEUED = 32
#: Motion history (issue 11.12): the last HISTORY motions or those ended within HISTORY_S,
#: whichever is more, never more than MAX_HISTORY records; a forgotten id leaves a tombstone
#: (status, code, times) for the last TOMBSTONES ids, so GET answers 410 `motion_expired`
#: with what is known instead of a 404 as if it never existed.
HISTORY = 256
HISTORY_S = 600.0
MAX_HISTORY = 4096
TOMBSTONES = 16384
#: Consecutive failed setpoints before a motion fails (3 control periods: a single dropped or
#: corrupt reply is ridden through, a device that stopped answering is not).
MAX_SETPOINT_FAILURES = 3
#: How long a finished trajectory may take to settle before the motion fails, s.
SETTLE_TIMEOUT_S = 2.0
PREVIEW_POINTS = 50
#: Trajectory time one tick may advance at most, s: a late tick stretches time (the step stays
#: within the velocity limit over the time it covers) instead of jumping ahead; no setpoint
#: step is more than the velocity limit times this. Two control periods at 100 Hz: a longer
#: step is a setpoint jump the device's controller chases faster than the limit (0.05 s let
#: the rbe3001's measured speed reach 1.1 x its limit on a loaded host, margin or not).
MAX_STEP_S = 0.02
#: A tick later than this, s, is reported (log and a `motion_held_up` event).
HELD_UP_S = 0.1

Status = Literal["queued", "running", "done", "stopped", "failed"]


@dataclass
class Plan:
    traj: Any  # JointTrajectory or SampledTrajectory: .duration, .sample(t) -> (q, qd, qdd)
    start: np.ndarray
    target: np.ndarray
    path: Literal["joint", "line"]


@dataclass
class MotionRecord:
    id: str
    arm: str
    kind: Literal["joints", "pose"]
    path: Literal["joint", "line"]
    request: Any
    target: np.ndarray
    target_tip: np.ndarray
    planned_duration: float
    planned_path: np.ndarray  # (k, 3) m, kept as one small array: the history holds 256
    status: Status = "queued"
    progress: float = 0.0
    reason: str | None = None
    code: str | None = None
    created: float = field(default_factory=time.time)
    started: float | None = None
    ended: float | None = None
    final_positions: list[float] | None = None
    final_tip: dict[str, float] | None = None
    cancel: str | None = None  # "stop" (decelerate), "replace" (hand over now)
    #: How to plan it again when it starts (the planner and its goal); dropped when it ends.
    planner: Any = field(default=None, repr=False)
    goal: np.ndarray | None = field(default=None, repr=False)
    done: asyncio.Event = field(default_factory=asyncio.Event)
    #: The control loop the record's executor runs on (waiting crosses there).
    home_loop: Any = field(default=None, repr=False)

    @on_control
    async def wait(self) -> MotionRecord:
        await self.done.wait()
        return self

    def to_schema(self) -> s.Motion:
        return s.Motion(
            id=self.id, arm=self.arm, kind=self.kind, path=self.path, status=self.status,
            progress=round(self.progress, 4), planned_duration=self.planned_duration,
            target_positions=[float(v) for v in self.target], target_tip=_vec(self.target_tip),
            reason=self.reason, code=self.code, created=self.created, started=self.started,
            ended=self.ended, final_positions=self.final_positions,
            final_tip=None if self.final_tip is None else s.Vec3(**self.final_tip),
            planned_path=[s.Vec3(x=float(p[0]), y=float(p[1]), z=float(p[2]))
                          for p in self.planned_path])


class MotionExecutor:
    def __init__(self, svc: ArmService) -> None:
        self.svc = svc
        self.model = svc.model
        self._queue: deque[MotionRecord] = deque()
        self._records: OrderedDict[str, MotionRecord] = OrderedDict()
        self._tombstones: OrderedDict[str, tuple[str, str | None, float, float | None]] = (
            OrderedDict())
        self._wake = asyncio.Event()
        self._task: asyncio.Task[None] | None = None
        self.current: MotionRecord | None = None
        self.last: MotionRecord | None = None
        #: Commanded state (q, qd, qdd) of the last setpoint sent, for blending and holding.
        self._cmd: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        self._halt = False
        self._ids = itertools.count(1)
        self._next_serial = 1  # the serial of the next motion id (for 410 on forgotten ids)
        #: how many motions, and how many seconds of ended ones, the history keeps at least
        self.history, self.history_s = HISTORY, HISTORY_S
        self.home_loop: asyncio.AbstractEventLoop | None = None

    def start(self) -> None:
        if self._task is None:
            self.home_loop = asyncio.get_running_loop()
            self._task = asyncio.create_task(self._run(), name=f"motion:{self.svc.name}")

    async def close(self) -> None:
        await cancel_and_wait(self._task)
        self._task = None
        for rec in [*self._queue, *( [self.current] if self.current else [])]:
            self._finish(rec, "stopped", "server shutting down")

    # --------------------------------------------------------- requests

    def get(self, motion_id: str) -> MotionRecord:
        rec = self._records.get(motion_id)
        if rec is None:
            gone = self._tombstones.get(motion_id)
            if gone is not None:
                status, code, created, ended = gone
                raise MotionExpired(
                    f"motion {motion_id} of {self.svc.name} has left the history (kept: the last "
                    f"{self.history} motions or those of the last {self.history_s:g} s); it was "
                    f"created "
                    f"at {_utc(created)} and ended {status}"
                    + (f" ({code})" if code else "") + (f" at {_utc(ended)}" if ended else ""))
            if self._issued(motion_id):
                raise MotionExpired(f"motion {motion_id} of {self.svc.name} has left the history "
                                    "long ago; nothing more is known about it")
            raise UnknownMotion(f"{self.svc.name} has no motion {motion_id!r}")
        return rec

    def _issued(self, motion_id: str) -> bool:
        """Whether this executor handed out `motion_id` (ids are m<serial>-<8 hex>)."""
        head, _, tail = motion_id.partition("-")
        if not (head[:1] == "m" and head[1:].isdigit() and len(tail) == 8):
            return False
        return int(head[1:]) < self._next_serial

    def _remember(self, rec: MotionRecord) -> None:
        """Add `rec` to the history; forget ended records beyond both the count and the age."""
        self._records[rec.id] = rec
        now = time.time()
        while len(self._records) > self.history:
            old = next(iter(self._records.values()))
            young = old.ended is None or now - old.ended < self.history_s
            if young and len(self._records) <= MAX_HISTORY:
                break
            del self._records[old.id]
            self._tombstones[old.id] = (old.status, old.code, old.created, old.ended)
            while len(self._tombstones) > TOMBSTONES:
                self._tombstones.popitem(last=False)

    def queued(self) -> bool:
        return bool(self._queue)

    def forget_command(self) -> None:
        """Plan the next motion from the measured pose (after homing or a servo reboot the
        last commanded state no longer means where the arm is)."""
        self._cmd = None

    def brief(self) -> dict[str, Any] | None:
        rec = self.current or self.last
        if rec is None:
            return None
        return {"id": rec.id, "status": rec.status, "progress": round(rec.progress, 4)}

    @on_control
    async def move_joints(self, req: s.MoveJoints) -> MotionRecord:
        q1 = self._joint_vector(req.positions)
        return self._submit("joints", "joint", req, q1, self._plan_joint_from, q1)

    @on_control
    async def move_pose(self, req: s.MovePose) -> MotionRecord:
        p = np.array([req.x, req.y, req.z])
        return self._submit("pose", req.path, req, None, self._plan_pose_from, p)

    def preview_joints(self, req: s.MoveJoints) -> s.Motion:
        q1 = self._joint_vector(req.positions)
        return self._preview("joints", "joint", req, self._plan_joint_from, q1)

    def preview_pose(self, req: s.MovePose) -> s.Motion:
        p = np.array([req.x, req.y, req.z])
        return self._preview("pose", req.path, req, self._plan_pose_from, p)

    @on_control
    async def cancel(self, motion_id: str, reason: str = "cancelled") -> MotionRecord:
        """Cancel one motion; `reason` says who cancelled it (kept in its record)."""
        rec = self.get(motion_id)
        if rec.status == "queued":
            self._queue.remove(rec)
            self._finish(rec, "stopped", f"{reason} before it started")
        elif rec.status == "running":
            if rec.cancel is None and rec.reason is None:
                rec.reason = reason
            rec.cancel = rec.cancel or "stop"
            await rec.wait()
        return rec

    @on_control
    async def stop_all(self, reason: str) -> list[str]:
        stopped = [r.id for r in self._queue]
        while self._queue:
            self._finish(self._queue.popleft(), "stopped", reason)
        cur = self.current
        if cur is not None and cur.status == "running":
            if cur.cancel is None and cur.reason is None:
                cur.reason = reason  # who or what stopped it, not just "cancelled"
            cur.cancel = "stop"
            stopped.append(cur.id)
            await cur.wait()
        return stopped

    @on_control
    async def emergency_stop(self) -> None:
        """Stop streaming now, clear the queue and command a hold at the last commanded
        setpoint (the measured position sags under gravity: holding there again and again
        would walk the arm down). The caller commands it once per latch, not per press."""
        self._halt = True
        while self._queue:
            self._finish(self._queue.popleft(), "stopped", "emergency stop")
        cur = self.current
        if cur is not None and not cur.done.is_set():
            self._finish(cur, "stopped", "emergency stop")
        await self._hold(commanded=True)
        self._halt = False

    # --------------------------------------------------------- planning

    def _joint_vector(self, positions: list[float]) -> np.ndarray:
        if len(positions) != self.model.n:
            raise InvalidRequest(f"{self.svc.name} has {self.model.n} joints "
                                 f"({', '.join(self.model.names)}), got {len(positions)} positions")
        q = np.array(positions, dtype=float)
        self.svc.check_joint_target(q)
        return q

    def _start_state(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        if self._cmd is not None:
            return self._cmd
        q = self.svc.driver.positions
        if q is None:
            raise ArmError(f"{self.svc.name}: no joint positions from the device yet",
                           code="link_down", status_code=503)
        z = np.zeros_like(q)
        return q.copy(), z, z.copy()

    def _plan_joint_from(self, start: tuple[np.ndarray, ...], q1: np.ndarray, req: Any,
                         at_rest: bool) -> Plan:
        q0, v0, a0 = start
        m = self.model
        k = self.svc.profile.tracking_margin  # the measured speed, not only the plan, in limits
        vmax, amax, jmax = self.svc.safety.scaled(m.vmax * k, m.amax * k, m.jmax)  # override
        try:
            traj = trajectory.plan_joint(q0, q1, vmax, amax, jmax,
                                         v0=None if at_rest else v0, a0=None if at_rest else a0,
                                         duration=req.duration, speed=req.speed)
        except KinematicsError as exc:
            raise InvalidRequest(f"cannot plan the move: {exc}") from None
        self.svc.safety.check_trajectory(traj, 1.0 / self.svc.profile.link.control_hz)
        return Plan(traj, q0, q1, "joint")

    def _plan_pose_from(self, start: tuple[np.ndarray, ...], p: np.ndarray, req: Any,
                        at_rest: bool) -> Plan:
        q0 = start[0]
        m = self.model
        # angler: the named IK case, else the design's choice; a line in case dx_used keeps
        # theta3 (the carriages draw it), a joint move takes the design's theta3 (-/+90 deg)
        case = req.ik_case
        if case is None and not m.is_rrr:
            case = pprp.auto_case(p, m.geom)  # type: ignore[arg-type]
        theta3 = float(q0[2]) if case == "dx_used" else None
        best = m.ik_best(p, q0, req.branch, req.ik_case, None)
        if req.path == "joint":
            return self._plan_joint_from(start, best.positions, req, at_rest)
        cart = self.svc.profile.cartesian

        def ik_near(point: np.ndarray, q_prev: np.ndarray | None) -> np.ndarray:
            ref = q0 if q_prev is None else q_prev
            th = float(ref[2]) if theta3 is not None else None
            try:
                return m.ik_nearest(point, ref, case, th)
            except ArmError as exc:
                raise KinematicsUnreachable(exc.detail) from None

        k = self.svc.profile.tracking_margin  # the measured joint speed, not only the plan
        cv, ca, cj, vmax = self.svc.safety.scaled(  # speed_override
            cart.max_velocity, cart.max_acceleration, cart.max_jerk, m.vmax * k)
        try:
            traj, _tips = trajectory.plan_line(
                m.fk(q0), p, ik_near, m.fk, float(cv), float(ca),
                float(cj), 1.0 / self.svc.profile.link.control_hz, vmax, m.lower, m.upper,
                m.names, m.kinds, q_start=q0, speed=req.speed)
        except LimitViolation as exc:
            raise JointLimit(f"line path leaves the joint limits: {exc}") from None
        except TrajectoryError as exc:  # e.g. a speed so small the line would last hours
            raise InvalidRequest(f"cannot plan the line: {exc}") from None
        except KinematicsError as exc:
            raise Unreachable(f"line path leaves the workspace: {exc}") from None
        end = traj.sample(traj.duration)[0]
        self.svc.safety.check_trajectory(traj, 1.0 / self.svc.profile.link.control_hz)
        return Plan(traj, q0, np.asarray(end, dtype=float), "line")

    def _tail_state(self, mode: str) -> tuple[tuple[np.ndarray, ...], bool]:
        """Where a new motion will start: after the queue (at rest) or from now (replace)."""
        if mode == "queue":
            pending = list(self._queue) or ([self.current] if self.current else [])
            if pending:
                q = pending[-1].target
                return (q, np.zeros_like(q), np.zeros_like(q)), True
        st = self._start_state()
        return st, not np.any(st[1])

    def _preview_path(self, plan: Plan) -> np.ndarray:
        t = np.linspace(0.0, plan.traj.duration, PREVIEW_POINTS)
        q = np.asarray(plan.traj.sample(t)[0], dtype=float)
        return np.asarray(self.model.fk(q), dtype=float)

    def _preview(self, kind: str, path: str, req: Any, planner: Any,
                 target: np.ndarray) -> s.Motion:
        self.svc.require_motion_allowed()
        start, at_rest = self._tail_state(req.mode)
        plan = planner(start, target, req, at_rest or path == "line")
        rec = self._record(kind, path, req, plan, "preview")
        return rec.to_schema()

    def _record(self, kind: str, path: str, req: Any, plan: Plan, mid: str) -> MotionRecord:
        return MotionRecord(id=mid, arm=self.svc.name, kind=kind, path=path,  # type: ignore[arg-type]
                            request=req, target=plan.target, target_tip=self.model.fk(plan.target),
                            planned_duration=float(plan.traj.duration),
                            planned_path=self._preview_path(plan))

    def _submit(self, kind: str, path: str, req: Any, _q: Any, planner: Any,
                target: np.ndarray) -> MotionRecord:
        self.svc.require_motion_allowed()
        self.svc.require_no_fault()
        if req.mode == "queue" and len(self._queue) >= MAX_QUEUED:
            raise Busy(f"{self.svc.name}: {MAX_QUEUED} motions already queued")
        start, at_rest = self._tail_state(req.mode)
        plan = planner(start, target, req, at_rest or path == "line")
        self.svc.check_homed(start[0], plan.target)
        serial = next(self._ids)
        self._next_serial = serial + 1
        rec = self._record(kind, path, req, plan, f"m{serial}-{uuid.uuid4().hex[:8]}")
        rec.planner, rec.goal = planner, target
        rec.home_loop = self.home_loop
        self._remember(rec)
        if req.mode == "replace":
            while self._queue:
                self._finish(self._queue.popleft(), "stopped", f"replaced by {rec.id}")
            if self.current is not None and self.current.status == "running":
                self.current.cancel = "replace"
            self._queue.appendleft(rec)
        else:
            self._queue.append(rec)
        self._wake.set()
        return rec

    # --------------------------------------------------------- execution

    async def _run(self) -> None:
        while True:
            if not self._queue:
                self._wake.clear()
                await self._wake.wait()
                continue
            rec = self._queue.popleft()
            self.current = rec
            try:
                await self._execute(rec)
            except ArmError as exc:
                self._finish(rec, "failed", exc.detail, exc.code)
            except Exception as exc:  # a planner bug must not kill the executor
                log.exception("%s: motion %s crashed", self.svc.name, rec.id)
                self._finish(rec, "failed", f"internal error: {type(exc).__name__}", "internal")
            finally:
                self.last = rec
                self.current = None

    async def _execute(self, rec: MotionRecord) -> None:
        self.svc.require_motion_allowed()
        self.svc.require_no_fault()
        start = self._start_state()
        at_rest = not np.any(start[1]) or rec.path == "line"
        if rec.path == "line" and np.any(start[1]):
            await self._brake()
            start = self._start_state()
        plan = rec.planner(start, rec.goal, rec.request, at_rest)
        rec.target, rec.target_tip = plan.target, self.model.fk(plan.target)
        rec.planned_duration = float(plan.traj.duration)
        rec.status, rec.started = "running", time.time()
        self.svc.hub.event("motion_started", id=rec.id, duration=rec.planned_duration)
        outcome = await self._stream(rec, plan.traj)
        if outcome == "replace":
            self._finish(rec, "stopped", "replaced by a new motion")
            return
        if outcome == "stop":
            await self._brake()
            self._finish(rec, "stopped", "cancelled" if rec.reason is None else rec.reason)
            return
        if outcome == "halt":
            return
        await self._settle(rec)

    async def _stream(self, rec: MotionRecord, traj: Any) -> str:
        """Send the trajectory's setpoints at the control rate. Each tick advances trajectory
        time by the wall time since the last one times a rate (0..1), and by MAX_STEP_S at
        most: a late tick stretches time instead of jumping ahead. The rate a tick achieved
        (trajectory time over wall time) is the commanded speed's scale; the next tick may
        raise it only as fast as the acceleration limits allow (`_time_rate`). So after the
        loop was held up (the setpoint stood still meanwhile) the motion picks up again along
        the same path from the last setpoint, never faster than planned and without a jump.
        A joint move asked to last `duration` is planned again instead, after a hold-up, to
        end when it was asked to (`_replan_on_time`)."""
        loop = asyncio.get_running_loop()
        dt = 1.0 / self.svc.profile.link.control_hz
        failures = 0
        duration = float(traj.duration)
        t = 0.0
        rate = 1.0
        qd = qdd = np.zeros(self.model.n)
        last = begun = loop.time()
        due, done_before = begun + duration, 0.0  # when it was asked to end; progress so far
        while True:
            if self._halt or rec.done.is_set():
                return "halt"
            if rec.cancel:
                return rec.cancel
            now = loop.time()
            late, last = now - last, now
            if late > HELD_UP_S and 0.0 < t < duration:
                log.warning("%s: motion %s: control held up %.0f ms; going on from the last "
                            "setpoint", self.svc.name, rec.id, late * 1e3)
                self.svc.hub.event("motion_held_up", id=rec.id, held_up_s=round(late, 4))
                fresh = self._replan_on_time(rec, due - now)
                if fresh is not None:
                    done_before += (1.0 - done_before) * t / duration
                    traj, duration, t, rate = fresh, float(fresh.duration), 0.0, 1.0
                    qd = qdd = np.zeros(self.model.n)
                    rec.planned_duration = now - begun + duration
                    self.svc.hub.event("motion_replanned", id=rec.id,
                                       remaining_s=round(duration, 4),
                                       duration=round(rec.planned_duration, 4),
                                       late_s=round(max(0.0, now + duration - due), 4))
            step = min(self._time_rate(rate, qd, qdd, late) * late, MAX_STEP_S)
            if late > 0.0:
                rate = step / late
            t = min(t + step, duration)
            q, qd, qdd = (np.asarray(v, dtype=float) for v in traj.sample(t))
            q = self._within_limits(q)
            try:
                await self.svc.driver.command_joints(q)  # type: ignore[attr-defined]
                # A setpoint that needs no reply (Dynamixel SYNC_WRITE) goes through even when
                # the device is silent: failing polls count as failed setpoints too.
                err = self.svc.driver.stale_error
            except ArmError as exc:
                err = exc
            failures = failures + 1 if err is not None else 0
            if err is not None and (err.code == "link_down" or failures >= MAX_SETPOINT_FAILURES):
                await self._watchdog(rec, err)
                return "halt"
            if self._halt:
                return "halt"
            self._cmd = (q, qd * rate, qdd * rate * rate)
            rec.progress = done_before + (1.0 - done_before) * (t / duration if duration > 0
                                                                 else 1.0)
            if t >= duration:
                self._cmd = (q, np.zeros_like(q), np.zeros_like(q))
                return "end"
            await asyncio.sleep(max(0.0, last + dt - loop.time()))

    def _replan_on_time(self, rec: MotionRecord, remaining: float) -> Any:
        """After a hold-up, a joint move with a requested `duration` is planned again from the
        last setpoint (where the arm held, at rest) to its target, to end `remaining` s from
        now, when it was asked to end; as soon as the limits allow if that is too soon. The
        trajectory, or None for a move without a duration (it goes on along its plan, time
        stretched: already as fast as the limits allow) or a line (its path is the point)."""
        req = rec.request
        if rec.path != "joint" or getattr(req, "duration", None) is None or self._cmd is None:
            return None
        q = self._cmd[0]
        rest = (q, np.zeros_like(q), np.zeros_like(q))
        for duration in ((remaining,) if remaining > 0 else ()) + (None,):
            ask = SimpleNamespace(duration=duration, speed=req.speed)
            try:
                return self._plan_joint_from(rest, rec.target, ask, True).traj
            except InvalidRequest:  # sooner than the limits allow: as soon as they do
                continue
        return None

    def _time_rate(self, rate: float, qd: np.ndarray, qdd: np.ndarray, h: float) -> float:
        """The next time rate after `h` s: up towards 1 as fast as the acceleration limits
        allow. Commanded velocity is rate * qd and acceleration rate^2 * qdd + rate' * qd, so
        rate' may use what the planned acceleration leaves of each joint's limit."""
        if rate >= 1.0:
            return 1.0
        amax = self.model.amax
        spare = np.maximum(amax - rate * rate * np.abs(qdd), 0.1 * amax)
        speed = np.abs(qd)
        moving = speed > 1e-9
        up = float(np.min(spare[moving] / speed[moving])) if np.any(moving) else np.inf
        return min(1.0, rate + up * h)

    async def _brake(self) -> None:
        """Decelerate from the commanded state to rest under the acceleration and jerk limits
        (time stretched after a late tick, as in `_stream`)."""
        if self._cmd is None or not np.any(self._cmd[1]):
            return
        q, qd, qdd = self._cmd
        m = self.model
        traj = trajectory.plan_stop(q, qd, qdd, m.amax, m.jmax, m.vmax)
        loop = asyncio.get_running_loop()
        dt = 1.0 / self.svc.profile.link.control_hz
        t = 0.0
        last = loop.time()
        while not self._halt:
            now = loop.time()
            t = min(t + min(now - last, MAX_STEP_S), float(traj.duration))
            last = now
            qs = self._within_limits(traj.sample(t)[0])
            try:
                await self.svc.driver.command_joints(qs)  # type: ignore[attr-defined]
            except ArmError:
                break
            self._cmd = (qs, np.zeros_like(qs), np.zeros_like(qs))
            if t >= traj.duration:
                break
            await asyncio.sleep(max(0.0, last + dt - loop.time()))

    async def _settle(self, rec: MotionRecord) -> None:
        """`done` only when every joint is within its settle tolerance of where it was sent
        and its actuator holds torque and says it has arrived (where it tells: Dynamixel
        Moving / Moving Status); a joint without torque fails the motion at once."""
        loop = asyncio.get_running_loop()
        deadline = loop.time() + SETTLE_TIMEOUT_S
        tol = self.tolerance()
        err = np.full(self.model.n, np.inf)
        moving = await self._arrived(rec)  # a joint without torque fails at once
        if moving is None:
            return
        while loop.time() < deadline:
            if self._halt or rec.done.is_set():
                return
            fault = self._device_fault()
            if fault is not None:  # silent device or lost link: say so, not "did not settle"
                await self._watchdog(rec, fault)
                return
            q = self.svc.driver.positions
            if q is not None and not self.svc.driver.stale:
                err = np.abs(q - rec.target)
                if np.all(err <= tol):
                    verdict = await self._arrived(rec)
                    if verdict is None:
                        return  # failed
                    moving = verdict
                    if not moving:
                        self._finish(rec, "done", None)
                        return
            await asyncio.sleep(0.01)
        if moving and np.all(err <= tol):
            names = ", ".join(self.model.names[k] for k in moving)
            reason = f"{names} within tolerance but its servo still reports moving"
        else:
            worst = int(np.argmax(err / tol))
            reason = (f"{self.model.names[worst]} is {err[worst]:.6f} off (tolerance "
                      f"{tol[worst]:.6f})")
        self._finish(rec, "failed", f"did not settle at the target within {SETTLE_TIMEOUT_S} s: "
                     f"{reason}", "not_settled")

    async def _arrived(self, rec: MotionRecord) -> tuple[int, ...] | None:
        """The joints whose actuator still says it is moving; None after failing `rec`
        (a hardware fault, or a joint whose servo holds no torque: it can never be done)."""
        svc = self.svc
        if svc.driver.faults:
            f = svc.driver.faults[0]
            await self._watchdog(rec, ArmError(
                f"servo {f['servo']} ({f['joint']}) reports a hardware fault: "
                f"{', '.join(f['bits']) or 'alert'}; {f['advice']}", code="fault"))
            return None
        try:
            st = await svc.driver.settle_state()
        except ArmError:
            return tuple(range(self.model.n))  # not known now: ask again on the next round
        if st.torque_off:
            names = ", ".join(self.model.names[k] for k in st.torque_off)
            await self._watchdog(rec, ArmError(
                f"{names}: the servo holds no torque (torque off after a reboot or a fault, or "
                f"switched off), so the joint cannot be at its target; enable torque or reboot "
                f"it with POST /api/v1/arms/{svc.name}/dynamixel/{{id}}/reboot",
                code="torque_off"))
            return None
        return st.moving

    def _device_fault(self) -> ArmError | None:
        drv = self.svc.driver
        if drv.link.state is not LinkState.UP:
            return LinkDown(f"{self.svc.name} link lost: {drv.link.last_error or 'down'}")
        return drv.stale_error

    def tolerance(self) -> np.ndarray:
        """Per joint (rad or m): the profile's `settle_tolerance`, else 8 encoder ticks."""
        tr = self.model.transmission
        ticks = np.abs(8.0 / tr.ticks_per_unit)
        return np.array([j.settle_tolerance if j.settle_tolerance is not None else ticks[k]
                         for k, j in enumerate(self.svc.profile.joints)], dtype=float)

    async def _watchdog(self, rec: MotionRecord, exc: ArmError) -> None:
        log.warning("%s: motion %s failed: %s", self.svc.name, rec.id, exc.detail)
        self._finish(rec, "failed", exc.detail, exc.code)
        self.svc.hub.event("watchdog", id=rec.id, code=exc.code, reason=exc.detail)
        await self._hold()

    async def _hold(self, commanded: bool = False) -> None:
        """Command the arm to hold, where the link still allows: at the last commanded setpoint
        if `commanded` and there is one, else at its measured position; within the limits."""
        q = self._cmd[0] if commanded and self._cmd is not None else self.svc.driver.positions
        if q is None:
            self._cmd = None
            return
        q = self._within_limits(q)
        try:
            await self.svc.driver.command_joints(q)  # type: ignore[attr-defined]
            self._cmd = (q.copy(), np.zeros_like(q), np.zeros_like(q))
        except ArmError as exc:
            log.warning("%s: could not command a hold: %s", self.svc.name, exc.detail)
            self._cmd = None

    def _within_limits(self, q: np.ndarray) -> np.ndarray:
        """Every position the executor commands (setpoint, brake, hold) is clipped to the joint
        limits: a plan or a measurement a hair outside must not become a command outside."""
        return np.clip(np.asarray(q, dtype=float), self.model.lower, self.model.upper)

    def _finish(self, rec: MotionRecord, status: Status, reason: str | None,
                code: str | None = None) -> None:
        if rec.done.is_set():
            return
        rec.status, rec.reason, rec.code, rec.ended = status, reason, code, time.time()
        rec.planner = None  # the history keeps what happened, not how to plan it
        if status == "done":
            rec.progress = 1.0
        q = self.svc.driver.positions
        if q is not None:
            rec.final_positions = [float(v) for v in q]
            rec.final_tip = _vec(self.model.fk(q))
        rec.done.set()
        if rec.started is not None or status != "stopped":
            self.svc.hub.event("motion_ended", id=rec.id, status=status, reason=reason, code=code)


def _utc(t: float) -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(t))


def _vec(v: np.ndarray) -> dict[str, float]:
    return {"x": float(v[0]), "y": float(v[1]), "z": float(v[2])}
