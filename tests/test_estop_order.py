"""The estop's order on the arm's control loop (issue 27): the latch, the sample that shows it,
the hold written to the device; the log line and the `estop` event only once the hold has
ended. They came between the hold's start and its write, and kept the control thread (and the
GIL) from the hold and the HTTP thread from sending the sample that shows the latch.

The rbe3001's simulated firmware answers every request 25 ms late here (half its timeout), so
that "before the hold's reply" and "after it" are far apart."""

from __future__ import annotations

import asyncio

from _wait import wait_for
from conftest import make_settings, running_client

from app.sim.faults import FaultConfig

API = "/api/v1/arms/rbe3001"
LATE_S = 0.025


async def test_the_estop_event_comes_once_the_hold_was_answered_and_the_sample_before() -> None:
    async with running_client(make_settings(control_thread=False)) as (app, client):
        svc = app.state.services["rbe3001"]
        await wait_for(lambda: svc.positions is not None, what="the rbe3001's first reading")
        svc.driver.link.set_faults(FaultConfig(latency_s=LATE_S))
        sub = svc.subscribe()
        try:
            replies = svc.driver.stats["replies"]
            press = asyncio.create_task(client.post(f"{API}/estop"))
            latched_seen = False
            events: list[str] = []
            async with asyncio.timeout(10):  # (a bound: the event comes within 0.1 s)
                while not events:
                    await sub.wait(1.0)
                    msg = sub.take_message()
                    latched_seen = latched_seen or (msg is not None and '"estop":true' in msg)
                    events = [e for e in sub.take_events() if '"event":"estop"' in e]
                    assert not press.done() or events, "answered before the event"
            # the event: after the hold's reply (its request answered), the sample before it
            assert svc.driver.stats["replies"] > replies
            assert latched_seen
            r = await press
            assert r.status_code == 200 and r.json() == {"estop": True}
            # a press on a latched estop changes nothing: no second event
            assert (await client.post(f"{API}/estop")).status_code == 200
            assert not [e for e in sub.take_events() if '"event":"estop"' in e]
        finally:
            sub.close()
            svc.driver.link.set_faults(FaultConfig())
            await client.delete(f"{API}/estop")
