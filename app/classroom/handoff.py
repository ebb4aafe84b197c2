"""The hand-off between two holders of an arm (API.md "Queue and hand-off"): stop, go to the
profile's home pose at reduced speed, check the arm got there with no fault."""

from __future__ import annotations

import asyncio
import time

import numpy as np

from app import schemas as s
from app.errors import ArmError
from app.service import ArmService

#: Speed fraction of the move home between two holders.
HANDOFF_SPEED = 0.5
#: How long the home move may take beyond its planned duration before the hand-off fails, s.
HANDOFF_SLACK_S = 10.0
#: How long a hand-off waits for the device's first sample (at start-up), s.
FIRST_SAMPLE_S = 10.0


def home_pose(svc: ArmService) -> np.ndarray:
    """The profile's home pose, else the middle of the joint limits."""
    if svc.profile.home is not None:
        return np.asarray(svc.profile.home, dtype=float)
    return np.asarray((svc.model.lower + svc.model.upper) / 2, dtype=float)


async def handoff(svc: ArmService) -> str | None:
    """Stop, go home at reduced speed, check it got there with no fault. None when it did, else
    why not."""
    if svc.estop:
        return "the emergency stop is latched"
    deadline = time.monotonic() + FIRST_SAMPLE_S
    while svc.positions is None and time.monotonic() < deadline:  # noqa: ASYNC110
        await asyncio.sleep(0.05)  # just started: the driver has no event for its first sample
    try:
        await svc.stop()
        home = home_pose(svc)
        rec = await svc.move_joints(s.MoveJoints(positions=[float(v) for v in home],
                                                 speed=HANDOFF_SPEED, mode="replace"))
        async with asyncio.timeout(rec.planned_duration + HANDOFF_SLACK_S):
            await rec.wait()
    except ArmError as exc:
        return f"going home was refused: {exc.detail} ({exc.code})"
    except TimeoutError:
        return "the arm did not reach home in time"
    if rec.status != "done":
        return f"the move home ended {rec.status}: {rec.reason or '-'}"
    faults = svc.faults
    if faults:
        return f"device faults after the move home: {faults}"
    q = svc.positions
    if q is None:
        return "no position reading after the move home"
    return None


def positions(svc: ArmService) -> list[float] | None:
    q = svc.positions
    return None if q is None else [round(float(v), 6) for v in q]
