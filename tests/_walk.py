"""Walking an rbe3001 with pass-through SET_PID steps, each within what the guard accepts (at
most 0.03 s of motion at the joint's velocity limit from where the joint is, and from the last
command: app/safety/guard.py `check_passthrough`), waiting (bounded) for the arm to follow each
step."""

from __future__ import annotations

import asyncio
import time
from typing import Any

import httpx
import numpy as np

from app.safety.guard import PASSTHROUGH_STEP_S

#: Fraction of the accepted step each walking step takes.
STEP_FRACTION = 0.6


async def pid_walk(client: httpx.AsyncClient, svc: Any, target: Any, *, url: str | None = None,
                   timeout: float = 30.0, headers: dict[str, str] | None = None) -> None:
    """SET_PID steps from where the arm is to `target` (rad), each answered 200; returns when
    every joint is within a step of the target; fails after `timeout` s."""
    url = url or f"/api/v1/arms/{svc.name}/rbe3001/set-pid"
    target = np.asarray(target, dtype=float)
    cap = svc.model.vmax * PASSTHROUGH_STEP_S * STEP_FRACTION
    deadline = time.monotonic() + timeout
    while True:
        # from where the arm was last told to go (the arm is within half a step of it)
        here = np.asarray(svc.driver.told(), dtype=float)
        if np.all(np.abs(target - here) <= cap):
            nxt = target
        else:
            nxt = here + np.clip(target - here, -cap, cap)
        # the setpoint may move from the last command only as fast as the joint may: a full
        # step needs PASSTHROUGH_STEP_S since that command
        while time.monotonic() - svc.driver.commanded_at < PASSTHROUGH_STEP_S:
            await asyncio.sleep(0.002)
        ticks = svc.model.transmission.to_ticks(nxt)
        r = await client.post(url, json={"joints": [{"position_ticks": float(t)} for t in ticks]},
                              headers=headers)
        assert r.status_code == 200, r.text
        # wait for the arm to follow (bounded), then take the next step from where it is
        while np.any(np.abs(np.asarray(svc.driver.positions) - nxt) > cap / 2):
            assert time.monotonic() < deadline, (f"the arm did not follow SET_PID to {nxt} "
                                                 f"(at {svc.driver.positions})")
            await asyncio.sleep(0.005)
        if nxt is target:
            return
