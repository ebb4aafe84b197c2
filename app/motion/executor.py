"""Per-arm motion queue and executor.

A move is checked and planned when it is submitted (joint limits, reachability, every point of
a line), so a bad move is refused with 422 before anything is sent. It is planned again from the
arm's commanded state when it starts, time-parameterised by ruckig under the profile's velocity,
acceleration and jerk limits, and streamed to the driver as setpoints at the profile's control
rate. It ends `done` only when the measured joints settle at the target; a device that stops
answering fails it with the device's error code (the watchdog), and the arm is told to hold.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from app import schemas as s
from app.errors import Busy
from app.motion import replay
from app.motion.history import MotionRecord, Plan
from app.motion.planner import State
from app.motion.stream import Events, MotionStream
from app.runtime.control_thread import on_home

__all__ = ["Events", "MotionExecutor", "MotionRecord", "Plan"]

MAX_QUEUED = 32
PREVIEW_POINTS = 50


class MotionExecutor(MotionStream):
    """One arm's motion queue: requests are checked and planned here, and streamed by the
    task of `MotionStream`. Built from the arm's name, model, safety guard, actuator and
    event sink, and its control rate and Cartesian limits (not from the service)."""

    # the history's bounds (how many motions, how many seconds of ended ones), settable
    @property
    def history(self) -> int:
        return self.records.history

    @history.setter
    def history(self, n: int) -> None:
        self.records.history = n

    @property
    def history_s(self) -> float:
        return self.records.history_s

    @history_s.setter
    def history_s(self, s_: float) -> None:
        self.records.history_s = s_

    # --------------------------------------------------------- requests

    def get(self, motion_id: str) -> MotionRecord:
        return self.records.get(motion_id)

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

    async def move_joints(self, req: s.MoveJoints) -> MotionRecord:
        """On the control loop: `_move_joints`."""
        return await on_home(self.home_loop, lambda: self._move_joints(req))

    async def _move_joints(self, req: s.MoveJoints) -> MotionRecord:
        q1 = self.planner.joint_vector(req.positions)
        return self._submit("joints", "joint", req, self._plan_joint_from, q1)

    async def move_pose(self, req: s.MovePose) -> MotionRecord:
        """On the control loop: `_move_pose`."""
        return await on_home(self.home_loop, lambda: self._move_pose(req))

    async def _move_pose(self, req: s.MovePose) -> MotionRecord:
        p = np.array([req.x, req.y, req.z])
        return self._submit("pose", req.path, req, self._plan_pose_from, p)

    async def replay(self, targets: np.ndarray, fps: float) -> MotionRecord:
        """On the control loop: `_replay`."""
        return await on_home(self.home_loop, lambda: self._replay(targets, fps))

    async def _replay(self, targets: np.ndarray, fps: float) -> MotionRecord:
        """Queue a replay of joint targets (T, n) at `fps` (app/motion/replay.py): checked
        now, planned again from the commanded state when it starts, like a joint move."""
        q = replay.check_targets(self.planner, targets, fps)
        plan = replay.replay_planner(self.planner, q, fps)
        return self._submit("joints", "joint", replay.ReplayAsk(), plan, q[-1])

    def preview_joints(self, req: s.MoveJoints) -> s.Motion:
        q1 = self.planner.joint_vector(req.positions)
        return self._preview("joints", "joint", req, self._plan_joint_from, q1)

    def preview_pose(self, req: s.MovePose) -> s.Motion:
        p = np.array([req.x, req.y, req.z])
        return self._preview("pose", req.path, req, self._plan_pose_from, p)

    async def cancel(self, motion_id: str, reason: str = "cancelled") -> MotionRecord:
        """Runs `_cancel` on the arm's control loop (its state changes only there)."""
        return await on_home(self.home_loop, lambda: self._cancel(motion_id, reason))

    async def _cancel(self, motion_id: str, reason: str = "cancelled") -> MotionRecord:
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

    async def stop_all(self, reason: str) -> list[str]:
        """On the control loop: `_stop_all`."""
        return await on_home(self.home_loop, lambda: self._stop_all(reason))

    async def _stop_all(self, reason: str) -> list[str]:
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

    async def emergency_stop(self) -> None:
        """Runs `_emergency_stop` on the arm's control loop (its state changes only there)."""
        return await on_home(self.home_loop, lambda: self._emergency_stop())

    async def _emergency_stop(self) -> None:
        """Stop streaming now, clear the queue and command a hold where the arm is
        (`hold_point`: its measured position, or its last command if it rests there), never
        where an older plan left it. The caller commands it once per latch, not per press."""
        self._halt = True
        while self._queue:
            self._finish(self._queue.popleft(), "stopped", "emergency stop")
        cur = self.current
        if cur is not None and not cur.done.is_set():
            self._finish(cur, "stopped", "emergency stop")
        await self._hold()
        self._halt = False

    # --------------------------------------------------------- planning

    def _plan_joint_from(self, start: State, q1: np.ndarray, req: Any, at_rest: bool) -> Plan:
        return self.planner.joint(start, q1, req, at_rest)

    def _plan_pose_from(self, start: State, p: np.ndarray, req: Any, at_rest: bool) -> Plan:
        return self.planner.pose(start, p, req, at_rest)

    def _tail_state(self, mode: str) -> tuple[State, bool]:
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
        self.guard.require_motion_allowed()
        start, at_rest = self._tail_state(req.mode)
        plan = planner(start, target, req, at_rest or path == "line")
        rec = self._record(kind, path, req, plan, "preview")
        return rec.to_schema()

    def _record(self, kind: str, path: str, req: Any, plan: Plan, mid: str) -> MotionRecord:
        return MotionRecord(id=mid, arm=self.name, kind="joints" if kind == "joints" else "pose",
                            path="line" if path == "line" else "joint",
                            request=req, target=plan.target, target_tip=self.model.tip(plan.target),
                            planned_duration=float(plan.traj.duration),
                            planned_path=self._preview_path(plan))

    def _submit(self, kind: str, path: str, req: Any, planner: Any,
                target: np.ndarray) -> MotionRecord:
        self.guard.require_motion_allowed()
        self.guard.require_no_fault()
        self.guard.require_torque()
        if req.mode == "queue" and len(self._queue) >= MAX_QUEUED:
            raise Busy(f"{self.name}: {MAX_QUEUED} motions already queued")
        start, at_rest = self._tail_state(req.mode)
        plan = planner(start, target, req, at_rest or path == "line")
        self.guard.check_homed(start[0], plan.target)
        rec = self._record(kind, path, req, plan, self.records.new_id(next(self._ids)))
        rec.planner, rec.goal = planner, target
        rec.home_loop = self.home_loop
        self.records.remember(rec)
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

