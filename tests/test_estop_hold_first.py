"""After an estop latches, the next command the device gets is the hold: no poll is started
between the latch and the hold's queueing. The hold's task runs once the latch's step yields,
a few hundred microseconds later; a poll that came due meanwhile went first and held the hold
back a whole device round trip (the simulated rbe3001 answers in 1.1 ms, as the firmware
does; over USB HID a poll is a write and a read). A poll already in flight at the latch still
ends first: the link carries one exchange at a time.

The simulated firmware is watched where it receives bytes (the order and the loop time the
owner task writes them); the arm runs on this test's loop, as the control loop runs it."""

from __future__ import annotations

import asyncio
import random
from typing import Any

from _wait import wait_for

from app.arms.loading import check_profile, load_profile
from app.config import homed_at_start
from app.service import ArmService
from protocol import rbe3001 as rb

LATCHES = 40


async def test_no_poll_starts_between_the_latch_and_its_hold() -> None:
    base = load_profile("rbe3001").model_dump()
    for joint in base["joints"]:
        if "zero_known" in joint:
            joint["zero_known"] = True
    svc = ArmService(homed_at_start(check_profile(base)))
    await svc.start()
    try:
        await wait_for(lambda: svc.hub.published > 20, what="samples")
        dev = svc.driver.link.device
        got: list[tuple[float, str]] = []  # (loop time, command) of every packet received
        receive = dev.receive

        def receiving(data: bytes, now: float) -> Any:
            got.append((now, type(rb.decode_command(bytes(data))).__name__))
            return receive(data, now)

        dev.receive = receiving
        loop = asyncio.get_running_loop()
        rng = random.Random(7)
        late: list[list[str]] = []
        for _ in range(LATCHES):
            await asyncio.sleep(rng.uniform(0.004, 0.012))  # at varying offsets to the polls
            got.clear()
            latched_at = loop.time()
            await svc.latch_estop()  # answers once the hold is commanded
            after = [cmd for t, cmd in got if t >= latched_at]
            assert "SetPid" in after, got
            before_hold = after[:after.index("SetPid")]
            if before_hold:
                late.append(before_hold)
            await svc.release_estop()
        assert late == [], f"{len(late)} of {LATCHES} holds waited for a poll started after the " \
                           f"latch: {late[:5]}"
    finally:
        await svc.close()
