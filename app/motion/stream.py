"""Streaming one arm's motions to its device: the task that takes the queue's next motion,
plans it again from the commanded state, sends its setpoints at the control rate (time stretched,
never skipped, after a late tick), brakes a stopped motion under the limits, and ends it `done`
only when the joints settle (app/motion/settle.py); a device that stops answering fails it with
the device's error code (the watchdog), and the arm is told to hold.
"""

from __future__ import annotations

import asyncio
import itertools
import logging
import time
from collections import deque
from types import SimpleNamespace
from typing import Any, Protocol

import numpy as np

from app.arms.model import KinematicsModel
from app.config import CartesianLimits
from app.device.actuator import Actuator
from app.errors import ArmError, InvalidRequest, LinkDown
from app.motion.history import MotionHistory, MotionRecord, Status
from app.motion.planner import Planner
from app.motion.settle import Settle
from app.runtime.tasks import cancel_and_wait
from app.safety.guard import SafetyGuard
from kinematics import trajectory

log = logging.getLogger(__name__)

#: Consecutive failed setpoints before a motion fails (3 control periods: a single dropped or
#: corrupt reply is ridden through, a device that stopped answering is not).
MAX_SETPOINT_FAILURES = 3
#: Trajectory time one tick may advance at most, s: a late tick stretches time (the step stays
#: within the velocity limit over the time it covers) instead of jumping ahead; no setpoint
#: step is more than the velocity limit times this. Three control periods at 100 Hz: 0.05 s
#: let the rbe3001's measured speed reach 1.1 x its limit on a loaded host (the PID chasing a
#: setpoint jump); 0.02 s made a move on a lossy link (tests/test_soak.py: 5 % drops, each a
#: reply timeout that holds the tick up) so slow that every move met the next link cut.
MAX_STEP_S = 0.03
#: A tick later than this, s, is reported (log and a `motion_held_up` event).
HELD_UP_S = 0.1
#: A hold keeps a joint's last command when the joint is within the settle tolerance of it, or
#: at rest within HOLD_NEAR_S of motion at its velocity limit of it; else the hold is where
#: the joint is measured (`hold_point`).
HOLD_NEAR_S = 0.03
#: A joint whose measured speed is over AT_REST of its velocity limit is moving (a tightened
#: envelope waits for the arm to stop: app/service.py `apply_safety`; a hold does not keep a
#: moving joint's command).
AT_REST = 0.05


class Events(Protocol):
    """Where the executor reports (the arm's telemetry hub)."""

    def event(self, name: str, **data: Any) -> Any: ...


class MotionStream:
    """The execution half of an arm's motion executor (app/motion/executor.py adds the requests).
    It asks
    `guard` whether a motion may start, moves `device` (the actuator) at `control_hz` and
    reports to `events`; it knows nothing of the service that hosts it."""

    def __init__(self, name: str, model: KinematicsModel, guard: SafetyGuard, device: Actuator,
                 events: Events, *, control_hz: float, cartesian: CartesianLimits) -> None:
        self.name = name
        self.model = model
        self.guard = guard
        self.device = device
        self.events = events
        self.control_hz = control_hz
        self.planner = Planner(name, model, guard, cartesian, control_hz)
        self.records = MotionHistory(name)
        self._settler = Settle(name, model.names, device)
        self._queue: deque[MotionRecord] = deque()
        self._wake = asyncio.Event()
        self._task: asyncio.Task[None] | None = None
        self.current: MotionRecord | None = None
        self.last: MotionRecord | None = None
        #: Commanded state (q, qd, qdd) of the last setpoint this executor sent, for blending;
        #: it is the arm's commanded state only while the device's `command_seq` is still
        #: `_cmd_seq` (no pass-through command, homing or set-up came after it).
        self._cmd: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        self._cmd_seq = -1
        #: When the tick that sent `_cmd` began (`time.monotonic()`): a setpoint older than
        #: HELD_UP_S is one the arm has come to rest at, whatever velocity it was sent with
        #: (`_commanded`).
        self._cmd_at = 0.0
        self._halt = False
        self._ids = itertools.count(1)
        self.home_loop: asyncio.AbstractEventLoop | None = None

    def start(self) -> None:
        if self._task is None:
            self.home_loop = asyncio.get_running_loop()
            self._task = asyncio.create_task(self._run(), name=f"motion:{self.name}")

    async def close(self) -> None:
        await cancel_and_wait(self._task)
        self._task = None
        for rec in [*self._queue, *( [self.current] if self.current else [])]:
            self._finish(rec, "stopped", "server shutting down")

    def _commanded(self) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """The arm's commanded state: the executor's last setpoint while it still is (None
        once a pass-through command, homing or set-up came after it). A setpoint sent more than
        HELD_UP_S ago (the control loop held up since) is where the arm has come to rest: at
        rest there, not at the velocity it was sent with (a motion or a brake from that
        velocity would move an arm that stands still as if it were moving)."""
        if self._cmd is None or self._cmd_seq != self.device.command_seq:
            return None
        sent, qd, _ = self._cmd
        if np.any(qd) and time.monotonic() - self._cmd_at > HELD_UP_S:
            return sent, np.zeros_like(sent), np.zeros_like(sent)
        return self._cmd

    def _start_state(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Where a motion starts: the arm's commanded state (`_commanded`), else where the arm
        is (at rest): never a stale setpoint."""
        commanded = self._commanded()
        if commanded is not None:
            return commanded
        q = self.device.positions
        if q is None:
            raise LinkDown(f"{self.name}: no joint positions from the device yet")
        z = np.zeros_like(q)
        return q.copy(), z, z.copy()

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
                log.exception("%s: motion %s crashed", self.name, rec.id)
                self._finish(rec, "failed", f"internal error: {type(exc).__name__}", "internal")
            finally:
                self.last = rec
                self.current = None

    async def _execute(self, rec: MotionRecord) -> None:
        self.guard.require_motion_allowed()
        self.guard.require_no_fault()
        self.guard.require_torque()  # (switched off while it was queued)
        start = self._start_state()
        at_rest = not np.any(start[1]) or rec.path == "line"
        if rec.path == "line" and np.any(start[1]):
            await self._brake()
            start = self._start_state()
        plan = rec.planner(start, rec.goal, rec.request, at_rest)
        rec.target, rec.target_tip = plan.target, self.model.tip(plan.target)
        rec.planned_duration = float(plan.traj.duration)
        rec.status, rec.started = "running", time.time()
        self.events.event("motion_started", id=rec.id, duration=rec.planned_duration)
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
        the same path from the last setpoint, never faster than planned and without a jump;
        after a hold-up of more than HELD_UP_S, from rest (its time rate from 0).
        A joint move asked to last `duration` is planned again instead, after a hold-up, to
        end when it was asked to (`_replan_on_time`)."""
        loop = asyncio.get_running_loop()
        dt = 1.0 / self.control_hz
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
            tick_at = time.monotonic()
            late, last = now - last, now
            if late > HELD_UP_S and 0.0 < t < duration:
                log.warning("%s: motion %s: control held up %.0f ms; going on from the last "
                            "setpoint", self.name, rec.id, late * 1e3)
                self.events.event("motion_held_up", id=rec.id, held_up_s=round(late, 4))
                fresh = self._replan_on_time(rec, due - now)
                if fresh is not None:
                    done_before += (1.0 - done_before) * t / duration
                    traj, duration, t, rate = fresh, float(fresh.duration), 0.0, 1.0
                    qd = qdd = np.zeros(self.model.n)
                    rec.planned_duration = now - begun + duration
                    self.events.event("motion_replanned", id=rec.id,
                                      remaining_s=round(duration, 4),
                                      duration=round(rec.planned_duration, 4),
                                      late_s=round(max(0.0, now + duration - due), 4))
                else:
                    # The arm has come to rest at the last setpoint meanwhile: the motion picks
                    # up from rest, its time rate from 0 under the acceleration limits, not at
                    # the planned speed (a step of MAX_STEP_S at once had the rbe3001's PID
                    # chase it at 1.1 x its velocity limit, tests/test_tracking.py). Its clock
                    # starts again now, after the warning and the event: time they took before
                    # this setpoint goes out would count as the next tick's lateness, a rate
                    # from 0 to a third of the plan's in one tick (tests/test_control.py).
                    rate, late = 0.0, dt
                    last = loop.time()
            step = min(self._time_rate(rate, qd, qdd, late) * late, MAX_STEP_S)
            if late > 0.0:
                rate = step / late
            t = min(t + step, duration)
            q, qd, qdd = (np.asarray(v, dtype=float) for v in traj.sample(t))
            q = self._within_limits(q)
            try:
                await self.device.command_joints(q)
                # A setpoint that needs no reply (Dynamixel SYNC_WRITE) goes through even when
                # the device is silent: failing polls count as failed setpoints too.
                err = self.device.stale_error
            except ArmError as exc:
                err = exc
            limp = self.guard.torque_refusal()  # a pass-through Torque Enable 0 while it runs
            if limp is not None:
                await self._watchdog(rec, limp)
                return "halt"
            failures = failures + 1 if err is not None else 0
            if err is not None and (err.code == "link_down" or failures >= MAX_SETPOINT_FAILURES):
                await self._watchdog(rec, err)
                return "halt"
            if self._halt:
                return "halt"
            self._cmd, self._cmd_seq = (q, qd * rate, qdd * rate * rate), self.device.command_seq
            self._cmd_at = tick_at  # (its tick's start: a hold-up while it was being sent
            # leaves the arm at rest as much as one before the tick)
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
                return self.planner.joint(rest, rec.target, ask, True).traj
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
        (time stretched after a late tick, as in `_stream`). Nothing to do where the arm rests
        at the last setpoint already: none was sent for more than HELD_UP_S (`_commanded`),
        before the brake or during it (the rest of the stop would move it on from there)."""
        commanded = self._commanded()
        if commanded is None:
            return
        q, qd, qdd = self._cmd = commanded
        if not np.any(qd):
            return
        m = self.model
        traj = trajectory.plan_stop(q, qd, qdd, m.amax, m.jmax, m.vmax)
        loop = asyncio.get_running_loop()
        dt = 1.0 / self.control_hz
        t = 0.0
        last = loop.time()
        while not self._halt:
            now = loop.time()
            if now - last > HELD_UP_S:  # the arm has stopped at the last setpoint meanwhile
                log.warning("%s: control held up %.0f ms while braking; the arm rests at the "
                            "last setpoint", self.name, (now - last) * 1e3)
                break
            t = min(t + min(now - last, MAX_STEP_S), float(traj.duration))
            last = now
            qs = self._within_limits(traj.sample(t)[0])
            try:
                await self.device.command_joints(qs)
            except ArmError:
                break
            self._cmd = (qs, np.zeros_like(qs), np.zeros_like(qs))
            self._cmd_seq = self.device.command_seq
            if t >= traj.duration:
                break
            await asyncio.sleep(max(0.0, last + dt - loop.time()))

    async def _settle(self, rec: MotionRecord) -> None:
        """`done` when the joints settle at the target (app/motion/settle.py)."""
        verdict, err = await self._settler.wait(
            rec.target, self.tolerance(), lambda: self._halt or rec.done.is_set())
        if verdict == "done":
            self._finish(rec, "done", None)
        elif verdict == "watchdog" and err is not None:
            await self._watchdog(rec, err)
        elif verdict == "failed" and err is not None:
            self._finish(rec, "failed", err.detail, err.code)

    def tolerance(self) -> np.ndarray:
        """Per joint (rad or m): the settle tolerance (the guard's)."""
        return self.guard.tolerance()

    async def _watchdog(self, rec: MotionRecord, exc: ArmError) -> None:
        log.warning("%s: motion %s failed: %s", self.name, rec.id, exc.detail)
        self._finish(rec, "failed", exc.detail, exc.code)
        self.events.event("watchdog", id=rec.id, code=exc.code, reason=exc.detail)
        await self._hold()

    async def _hold(self) -> None:
        """Command the arm to hold where it is (`hold_point`), where the link still allows: the
        estop's hold (not gated by the latch) and the watchdog's."""
        q = self.hold_point()
        if q is None:
            self._cmd = None
            return
        try:
            await self.device.command_joints(q, hold=True)
            self._cmd = (q.copy(), np.zeros_like(q), np.zeros_like(q))
            self._cmd_seq = self.device.command_seq
        except ArmError as exc:
            log.warning("%s: could not command a hold: %s", self.name, exc.detail)
            self._cmd = None

    def hold_point(self) -> np.ndarray | None:
        """Where the arm is: its measured position, except a joint that has arrived at its
        last command, which holds at that command (a joint sagging under gravity is not
        walked down a little further at each hold): one within the settle tolerance of it,
        or at rest (its speed under AT_REST of its limit) within one step (HOLD_NEAR_S of
        motion at its limit) of it. A joint still running towards its command (a servo
        heading for a goal) holds where it is. Never an older setpoint: the arm does not
        move to hold. Not clipped to the joint limits (an arm outside them, with raw access,
        holds where it is). None before any reading. (The tolerance case does not ask the
        speed: the rbe3001 firmware's velocity is a windowed difference that lags the
        position by up to a window, and read 0.5 rad/s at a settled arm.)"""
        q = self.device.positions
        if q is None:
            return None
        q = np.array(q, dtype=float)
        cmd = self.device.commanded
        if cmd is None:
            return q
        m = self.model
        off = np.abs(cmd - q)
        qd = self.device.velocities
        still = (np.zeros(m.n, dtype=bool) if qd is None
                 else np.abs(np.asarray(qd, dtype=float)) <= m.vmax * AT_REST)
        keep = (off <= self.tolerance()) | ((off <= m.vmax * HOLD_NEAR_S) & still)
        return np.where(np.isfinite(cmd) & keep, cmd, q)

    def _within_limits(self, q: np.ndarray) -> np.ndarray:
        """Every position the executor commands (setpoint, brake, hold) is clipped to the joint
        limits: a plan or a measurement a hair outside must not become a command outside."""
        clipped: np.ndarray = np.clip(np.asarray(q, dtype=float), self.model.lower,
                                      self.model.upper)
        return clipped

    def _finish(self, rec: MotionRecord, status: Status, reason: str | None,
                code: str | None = None) -> None:
        if rec.done.is_set():
            return
        rec.status, rec.reason, rec.code, rec.ended = status, reason, code, time.time()
        rec.planner = None  # the history keeps what happened, not how to plan it
        if status == "done":
            rec.progress = 1.0
        q = self.device.positions
        if q is not None:
            rec.final_positions = [float(v) for v in q]
            rec.final_tip = self.model.tip(q)
        rec.done.set()
        if rec.started is not None or status != "stopped":
            self.events.event("motion_ended", id=rec.id, status=status, reason=reason, code=code)


