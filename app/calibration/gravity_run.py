"""The gravity calibration's motion: to each pose through the planner like any joint move,
wait there until the arm is at rest, average the raw joint torques over a few samples, then
fit (app/calibration/gravity.py) and hand the fit back. Runs as a task on the control loop;
`GravityRun` is its state, as GET /calibration shows it."""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np

from app.calibration.gravity import GravityFit, fit

log = logging.getLogger(__name__)

#: Raw torque samples averaged at each pose (the rbe3001 polls at 500 Hz: 40 ms).
SAMPLES = 20
#: Longest wait for the arm to come to rest at a pose and give its samples, s.
REST_TIMEOUT_S = 10.0

#: Moves the arm to joint values q (a planned joint move) and answers when it has ended,
#: with its status and reason.
Move = Callable[[list[float]], Awaitable[tuple[str, str, str | None]]]
#: Waits (at most `timeout` s) for `SAMPLES` readings at rest and answers their mean joint
#: values and raw torques, or None.
Rest = Callable[[int, float], Awaitable[tuple[np.ndarray, np.ndarray] | None]]


@dataclass
class GravityRun:
    poses: list[list[float]]
    status: Literal["running", "done", "failed"] = "running"
    done: int = 0
    motions: list[str] = field(default_factory=list)
    reason: str | None = None
    started: float = field(default_factory=time.time)
    ended: float | None = None
    task: asyncio.Task[None] | None = field(default=None, repr=False)

    def fail(self, reason: str) -> None:
        self.status, self.reason, self.ended = "failed", reason, time.time()
        log.warning("gravity calibration failed: %s", reason)


async def run(state: GravityRun, model: Any, move: Move, rest: Rest,
              done: Callable[[GravityFit], Awaitable[None]]) -> None:
    """Visit every pose of `state`, measure, fit, and give the fit to `done`."""
    qs: list[np.ndarray] = []
    taus: list[np.ndarray] = []
    for pose in state.poses:
        mid, status, reason = await move(pose)
        state.motions.append(mid)
        if status != "done":
            state.fail(f"motion {mid} to {pose} {status}: {reason or 'no reason given'}")
            return
        got = await rest(SAMPLES, REST_TIMEOUT_S)
        if got is None:
            state.fail(f"the arm did not come to rest at {pose} with torque readings within "
                       f"{REST_TIMEOUT_S:g} s")
            return
        qs.append(got[0])
        taus.append(got[1])
        state.done += 1
    result = fit(model, np.array(qs), np.array(taus))
    await done(result)
    state.status, state.ended = "done", time.time()
    log.info("gravity calibration: %d poses, residual rms %.4f, worst %.4f", len(qs),
             result.rms, result.worst)
