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
joint limits (422 `joint_limit`), no frame-to-frame step faster than the velocity limit times
the tracking margin and the speed override (422 `velocity_limit`), and every body point at
every control period of the whole trajectory against the keep-out envelope (422
`keep_out`). Acceleration between frames is not bounded here: a recording is what an arm
did, and the step speed bound is the one a replay can honour without changing its timing.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from app.errors import InvalidRequest, JointLimit, VelocityLimit
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


def frames_trajectory(targets: np.ndarray, fps: float) -> SampledTrajectory:
    """The targets (T, n) at `fps` as a sampled trajectory: velocity and acceleration by
    finite differences (what the executor's time rate reads after a late tick)."""
    times = np.arange(len(targets), dtype=np.float64) / fps
    if len(targets) == 1:
        z = np.zeros_like(targets)
        return SampledTrajectory(times, targets, z, z.copy())
    qd = np.gradient(targets, times, axis=0)
    qdd = np.gradient(qd, times, axis=0)
    return SampledTrajectory(times, targets, qd, qdd)


def check_targets(planner: Planner, targets: Any, fps: float) -> np.ndarray:
    """The targets as a (T, n) float array, checked: shape, finite, the frame rate, the joint
    limits and the frame-to-frame speed (see the module's docstring). 422 otherwise."""
    model, guard = planner.model, planner.guard
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
    for k, row in enumerate(q):
        v = model.violations(row)
        if v:
            raise JointLimit(f"replay frame {k}: " + "; ".join(v))
    if len(q) > 1:
        speed = np.abs(np.diff(q, axis=0)) * fps
        cap = np.asarray(guard.scaled(model.vmax * model.profile.tracking_margin)[0], float)
        over = speed > cap * (1 + 1e-9)
        if np.any(over):
            k, j = (int(v) for v in np.argwhere(over)[0])
            raise VelocityLimit(
                f"replay frames {k} -> {k + 1}: {model.names[j]} moves at {speed[k, j]:.3g}/s, "
                f"over its velocity limit times the tracking margin and the speed override "
                f"({cap[j]:.3g}/s); replay at a lower frame rate, or re-record slower")
    return q


def replay_planner(planner: Planner, targets: np.ndarray, fps: float
                   ) -> Callable[[State, np.ndarray, Any, bool], Plan]:
    """The executor's planner for a replay of checked `targets` at `fps` (check_targets): from
    a start state (the commanded state when it starts, the queue's end when queued), the
    soft start to the first frame and then the frames, the whole checked against the
    envelope at the control period."""
    frames = frames_trajectory(targets, fps)

    def plan(start: State, _goal: np.ndarray, req: Any, at_rest: bool) -> Plan:
        lead = planner.joint(start, targets[0], req, at_rest).traj
        traj = ReplayTrajectory(lead, frames)
        planner.guard.check_trajectory(frames, planner.dt)
        return Plan(traj, np.asarray(start[0], dtype=float), targets[-1].copy(), "joint")

    return plan
