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
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from app.errors import InvalidRequest, JointLimit
from app.motion.history import Plan
from app.motion.planner import Planner, State
from kinematics.trajectory import SampledTrajectory, Samples, time_grid

#: Frame rates a replay accepts, Hz (LeRobot datasets are 10..100 fps in practice).
MIN_FPS, MAX_FPS = 1.0, 1000.0
#: Most frames one replay may hold: 10 min at 100 fps (the planner's longest line, too).
MAX_FRAMES = 60_000


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


def replay_planner(planner: Planner, targets: np.ndarray, fps: float
                   ) -> Callable[[State, np.ndarray, Any, bool], Plan]:
    """The executor's planner for a replay of checked `targets` at `fps` (check_targets): from
    a start state (the commanded state when it starts, the queue's end when queued), the
    soft start to the first frame and then the frames (timed under the speed override as it
    is then), the frames checked against the envelope at the control period (the soft start
    by `Planner.joint`)."""
    def plan(start: State, _goal: np.ndarray, req: Any, at_rest: bool) -> Plan:
        frames = frames_trajectory(targets, fps, step_speed(planner))  # the override now
        lead = planner.joint(start, targets[0], req, at_rest).traj
        traj = ReplayTrajectory(lead, frames)
        planner.guard.check_trajectory(frames, planner.dt)
        return Plan(traj, np.asarray(start[0], dtype=float), targets[-1].copy(), "joint")

    return plan
