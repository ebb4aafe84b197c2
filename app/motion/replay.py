"""Playing a sequence of joint targets back as one motion (issue 26: replaying a recorded
episode's actions).

A replay is a motion like a move: queued, streamed, stopped, estopped and settled by the
arm's executor (app/motion/executor.py, app/motion/stream.py). Its trajectory has two parts:

1. a soft start: a planned joint move (`Planner.joint`, ruckig under the joint limits times
   the profile's tracking margin and the speed override) from the commanded state to the
   first target, at rest there;
2. the targets themselves, (T, n) rad or m, one every 1/fps s, linearly interpolated between
   frames at the executor's control rate (LeRobot frames sit on `timestamp = frame_index /
   fps`, huggingface/lerobot `src/lerobot/datasets/lerobot_dataset.py`).

Checked before anything moves (the same checks a planned move gets): every target within the
joint limits (422 `joint_limit`) and every body point at every control period of the whole
trajectory against the keep-out envelope (422 `keep_out`). Speed: a frame-to-frame step that
would go faster than the velocity limit times the tracking margin and the speed override
(a recording's grid holds the setpoint last commanded before each frame's time, so one frame
may carry a little more than a period's motion; a recording of a faster arm) takes as long as
the limit needs: the path is kept, that step alone is slower than recorded, and the motion's
`planned_duration` says so. Acceleration between frames is not bounded here: a recording is
what an arm did.

The gripper (where the episode has its column and the arm an actuated gripper) is no joint of
the trajectory: `follow_gripper` runs beside the motion on the control loop and, as the motion
reaches each frame's time (the motion's progress times the duration of the plan it runs,
`ReplayPlanner.last`), sends that frame's gripper action through the arm's facade
(`ArmService.set_gripper`: the checks of POST /gripper) when it differs from the last one
sent. It ends with the motion; a motion stopped or estopped sends no more.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from app.errors import ArmError, InvalidRequest, JointLimit
from app.motion.history import MotionRecord, Plan
from app.motion.planner import Planner, State
from kinematics.trajectory import SampledTrajectory, Samples, time_grid

#: Frame rates a replay accepts, Hz (LeRobot datasets are 10..100 fps in practice).
MIN_FPS, MAX_FPS = 1.0, 1000.0
#: Most frames one replay may hold: 10 min at 100 fps (the planner's longest line, too).
MAX_FRAMES = 60_000
#: How often the gripper's follower looks at the motion's progress, s: a period of the
#: executor's usual 100 Hz control rate (a frame at 30 fps lasts 33 ms).
GRIPPER_LOOK_S = 0.01
#: A gripper action closer than this to the last one sent is not sent again (0..1 scale).
GRIPPER_STEP = 1e-3

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ReplayAsk:
    """What the executor reads of a request (`mode`, `speed`, `duration`) for a replay: queued
    after the arm's current motion, the soft start at the planner's limits, no duration."""

    mode: str = "queue"
    speed: float = 1.0
    duration: float | None = None
    wait: bool = False


@dataclass(frozen=True, eq=False)
class ReplayTrajectory:
    """The soft start (`lead`: duration, sample) followed by the frames (`frames`); the
    surface the executor and the envelope's check need (kinematics.trajectory
    TrajectoryLike)."""

    lead: Any
    frames: SampledTrajectory

    @property
    def duration(self) -> float:
        return float(self.lead.duration) + self.frames.duration

    def sample(self, t: npt.ArrayLike) -> Samples:
        ta = np.clip(np.asarray(t, dtype=np.float64), 0.0, self.duration)
        t0 = float(self.lead.duration)
        a = self.lead.sample(np.minimum(ta, t0))
        b = self.frames.sample(np.maximum(ta - t0, 0.0))
        first = (ta < t0)[..., None]
        q, qd, qdd = (np.where(first, np.asarray(x, dtype=np.float64), np.asarray(y))
                      for x, y in zip(a, b, strict=True))
        return q, qd, qdd

    def sample_grid(self, dt: float) -> tuple[Any, Any, Any, Any]:
        t = time_grid(self.duration, dt)
        return (t, *self.sample(t))


def frames_trajectory(targets: np.ndarray, fps: float, speed: np.ndarray) -> SampledTrajectory:
    """The targets (T, n) at `fps` as a sampled trajectory, a step that would be faster than
    `speed` (per joint, rad/s or m/s) lasting as long as `speed` needs; velocity and
    acceleration by finite differences (what the executor's time rate reads after a late
    tick)."""
    if len(targets) == 1:
        z = np.zeros_like(targets)
        return SampledTrajectory(np.zeros(1), targets, z, z.copy())
    step = np.max(np.abs(np.diff(targets, axis=0)) / np.maximum(speed, 1e-12), axis=1)
    times = np.concatenate([[0.0], np.cumsum(np.maximum(step * (1 + 1e-9), 1.0 / fps))])
    qd = np.gradient(targets, times, axis=0)
    qdd = np.gradient(qd, times, axis=0)
    return SampledTrajectory(times, targets, qd, qdd)


def step_speed(planner: Planner) -> np.ndarray:
    """The fastest a replay step may go, per joint: the velocity limit times the tracking
    margin and the speed override (what the planner plans a joint move under)."""
    m = planner.model
    return np.asarray(planner.guard.scaled(m.vmax * m.profile.tracking_margin)[0], dtype=float)


def check_targets(planner: Planner, targets: Any, fps: float) -> np.ndarray:
    """The targets as a (T, n) float array, checked: shape, finite, the frame rate and the
    joint limits (see the module's docstring). 422 otherwise."""
    model = planner.model
    if not (np.isfinite(fps) and MIN_FPS <= fps <= MAX_FPS):
        raise InvalidRequest(f"replay frame rate {fps!r} is outside {MIN_FPS:g}..{MAX_FPS:g} fps")
    q = np.asarray(targets, dtype=float)
    if q.ndim != 2 or q.shape[1] != model.n or not 1 <= q.shape[0] <= MAX_FRAMES:
        raise InvalidRequest(f"{planner.name}: a replay takes 1..{MAX_FRAMES} frames of "
                             f"{model.n} joints ({', '.join(model.names)}), got shape "
                             f"{list(q.shape)}")
    if not np.all(np.isfinite(q)):
        bad = int(np.flatnonzero(~np.all(np.isfinite(q), axis=1))[0])
        raise InvalidRequest(f"replay frame {bad} is not finite: {q[bad].tolist()}")
    outside = np.any((q < model.lower) | (q > model.upper), axis=1)
    for k in np.flatnonzero(outside)[:1]:  # the first frame outside, in the model's words
        v = model.violations(q[k]) or [f"outside the joint limits: {q[k].tolist()}"]
        raise JointLimit(f"replay frame {int(k)}: " + "; ".join(v))
    return q


class ReplayPlanner:
    """The executor's planner for a replay of checked `targets` at `fps` (check_targets): from
    a start state (the commanded state when it starts, the queue's end when queued), the
    soft start to the first frame and then the frames (timed under the speed override as it
    is then), the frames checked against the envelope at the control period (the soft start
    by `Planner.joint`). `last` is the trajectory it planned last: the one the motion runs
    once it has started (the executor plans again as it starts it)."""

    def __init__(self, planner: Planner, targets: np.ndarray, fps: float) -> None:
        self.planner, self.targets, self.fps = planner, targets, fps
        self.last: ReplayTrajectory | None = None

    def __call__(self, start: State, _goal: np.ndarray, req: Any, at_rest: bool) -> Plan:
        planner, targets = self.planner, self.targets
        frames = frames_trajectory(targets, self.fps, step_speed(planner))  # the override now
        lead = planner.joint(start, targets[0], req, at_rest).traj
        traj = ReplayTrajectory(lead, frames)
        planner.guard.check_trajectory(frames, planner.dt)
        self.last = traj
        return Plan(traj, np.asarray(start[0], dtype=float), targets[-1].copy(), "joint")


def replay_planner(planner: Planner, targets: np.ndarray, fps: float) -> ReplayPlanner:
    """The executor's planner for a replay (ReplayPlanner)."""
    return ReplayPlanner(planner, targets, fps)


def frame_at(traj: ReplayTrajectory, progress: float) -> int | None:
    """The frame a motion running `traj` has reached at `progress` (0..1 of its duration):
    the last frame whose time has come, None during the soft start."""
    t = progress * traj.duration - float(traj.lead.duration)
    if t < 0.0:
        return None
    times = np.asarray(traj.frames.times, dtype=float)
    return int(np.clip(np.searchsorted(times, t + 1e-9, side="right") - 1, 0, len(times) - 1))


def check_gripper(values: Any, frames: int) -> np.ndarray:
    """A gripper action per frame (0 open .. 1 closed), checked: 422 otherwise."""
    g = np.asarray(values, dtype=float)
    if g.shape != (frames,) or not np.all(np.isfinite(g)) or np.any((g < 0.0) | (g > 1.0)):
        raise InvalidRequest(f"a replay's gripper takes one action in 0..1 per frame ({frames}),"
                             f" got shape {list(g.shape)}")
    return g


async def follow_gripper(rec: MotionRecord, plan: ReplayPlanner, gripper: np.ndarray,
                         set_gripper: Callable[[float], Awaitable[Any]]) -> None:
    """On the control loop, beside the replay `rec` planned by `plan`: each frame's gripper
    action (`gripper`, one per frame) sent by `set_gripper` as the motion reaches the frame,
    when it differs from the last one sent; the last frame's once the motion is done. Ends
    with the motion, or at the first refusal (an estop latched meanwhile: logged)."""
    sent: float | None = None

    async def send(k: int) -> bool:
        nonlocal sent
        g = float(gripper[k])
        if sent is not None and abs(g - sent) < GRIPPER_STEP:
            return True
        try:
            await set_gripper(g)
        except ArmError as exc:
            log.info("%s: replay %s: gripper action of frame %d refused (%s): no more",
                     rec.arm, rec.id, k, exc.code)
            return False
        sent = g
        return True

    while not rec.done.is_set():
        traj = plan.last
        if rec.status == "running" and traj is not None:
            k = frame_at(traj, rec.progress)
            if k is not None and not await send(k):
                return
        await asyncio.sleep(GRIPPER_LOOK_S)
    if rec.status == "done":
        await send(len(gripper) - 1)
