"""A plain lease (taken while nobody queued) and the classroom queue's slot (issue 22, item 11),
end to end over the HTTP API (httpx over ASGI, the real app and its simulated arms).

The rule (app/classroom/queue.py, README "Running a lab session"): once someone waits, a plain
lease ends at most one slot (`ARMSERVER_SLOT_S`) after the moment the queue went from nobody
waiting to someone waiting, renewed or not; then the arm is handed off to the head of the
queue as between two queue slots. If nobody waits any more before then, the slot is lifted.

Before this, renewals kept a plain lease past the slot for as long as its holder liked; only an
instructor's revoke ended it.
"""

from __future__ import annotations

import asyncio
import json
import time
from typing import Any

import httpx
import numpy as np

from app.classroom.queue import home_pose
from tests.conftest import running_client
from tests.test_classroom import ALICE, BOB, CAROL, TEACH, VIEW, class_settings, until

ARM = "rbe3001"
SLOT_S = 1.5
#: Renewal period of the holder: well inside the ttl below.
RENEW_S = 0.1
#: How long past its slot a lease may live before the test calls it escaped (a busy machine's
#: slack: the watcher wakes at the slot's end, the renewal that sees it comes RENEW_S later).
LATE_S = 3.0


def H(token: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {token}"}


def settings(**over: Any) -> Any:
    """The classroom tests' settings, with this file's slot and a claim and ttl long enough
    for a loaded machine."""
    return class_settings(**{"claim_s": 5.0, "slot_s": SLOT_S, "lease_ttl_s": 3.0, **over})


async def queue(c: httpx.AsyncClient) -> dict[str, Any]:
    r = await c.get(f"/api/v1/arms/{ARM}/queue", headers=H(VIEW))
    assert r.status_code == 200, r.text
    return r.json()  # type: ignore[no-any-return]


async def entry(c: httpx.AsyncClient, eid: str, token: str) -> dict[str, Any]:
    r = await c.get(f"/api/v1/arms/{ARM}/queue/{eid}", headers=H(token))
    assert r.status_code == 200, r.text
    return r.json()  # type: ignore[no-any-return]


async def renew(c: httpx.AsyncClient, lease: str, token: str = CAROL) -> httpx.Response:
    return await c.put(f"/api/v1/arms/{ARM}/lease/{lease}", headers=H(token))


async def renew_for(c: httpx.AsyncClient, lease: str, seconds: float) -> None:
    """Renew every RENEW_S for `seconds`; every renewal must be answered 200."""
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        r = await renew(c, lease)
        assert r.status_code == 200, r.text
        await asyncio.sleep(RENEW_S)


def event_names(events: list[str]) -> list[str]:
    return [json.loads(e)["event"] for e in events]


async def test_a_plain_lease_ends_one_slot_after_someone_joins_then_hands_off() -> None:
    async with running_client(settings()) as (app, c):
        svc = app.state.services[ARM]
        sub = svc.hub.subscribe()
        r = await c.post(f"/api/v1/arms/{ARM}/lease", headers=H(CAROL))
        assert r.status_code == 201, r.text
        lease = r.json()["id"]
        # alone, the plain lease has no slot: renewals keep it past a slot's length
        await renew_for(c, lease, SLOT_S + 0.5)
        q = await queue(c)
        assert q["holder"] == "(a lease outside the queue)" and q["slot_left"] is None
        # carol moves the arm away from home: the hand-off must bring it back
        move = {"positions": [0.3, 0.4, 0.2], "speed": 1.0, "wait": True}
        r = await c.post(f"/api/v1/arms/{ARM}/move/joints", json=move,
                         headers={**H(CAROL), "X-Arm-Lease": lease})
        assert r.status_code == 200 and r.json()["status"] == "done", r.text

        t_join = time.monotonic()
        r = await c.post(f"/api/v1/arms/{ARM}/queue", headers=H(ALICE))
        # the server joined alice before now: her slot ends SLOT_S after at the latest (the
        # join's own time, taken before the request, was 81 ms early once on a loaded machine)
        wall_joined = time.time()
        assert r.status_code == 201, r.text
        alice = r.json()
        assert alice["status"] == "waiting" and alice["position"] == 1
        q = await queue(c)
        assert q["holder"] == "(a lease outside the queue)"
        assert q["slot_left"] is not None and 0 < q["slot_left"] <= SLOT_S
        # nobody else takes a plain lease meanwhile
        r = await c.post(f"/api/v1/arms/{ARM}/lease", headers=H(BOB))
        assert r.status_code == 409 and r.json()["code"] == "leased"

        # carol renews as often as she likes: the lease still ends one slot after the join
        while True:
            r = await renew(c, lease)
            if r.status_code != 200:
                break
            assert r.json()["expires"] <= wall_joined + SLOT_S + 0.01, \
                "a renewal reached past the slot's end"
            assert time.monotonic() - t_join < SLOT_S + LATE_S, \
                "the plain lease was renewed past its slot after someone joined"
            await asyncio.sleep(RENEW_S)
        ended = time.monotonic() - t_join
        assert r.status_code == 404 and r.json()["code"] == "unknown_lease", r.text
        assert SLOT_S - 0.05 <= ended <= SLOT_S + LATE_S, ended
        r = await c.post(f"/api/v1/arms/{ARM}/move/joints", json=move,
                         headers={**H(CAROL), "X-Arm-Lease": lease})
        assert r.status_code == 409 and r.json()["code"] == "leased"

        # the hand-off as between two queue slots: home, then alice is offered
        async def offered() -> dict[str, Any] | None:
            e = await entry(c, alice["id"], ALICE)
            return e if e["status"] == "offered" else None
        alice = await until(offered, what="alice's offer")
        assert np.allclose(svc.driver.positions, home_pose(svc), atol=0.03)
        q = await queue(c)
        assert q["last_handoff"]["ok"] is True and q["blocked"] is None
        r = await renew(c, alice["lease_id"], ALICE)
        assert r.status_code == 200, r.text
        q = await queue(c)
        assert q["holder"] == "alice" and 0 < q["slot_left"] <= SLOT_S

        _, events, _ = sub.take()
        sub.close()
        names = event_names(events)
        expired = [json.loads(e)["data"] for e in events
                   if json.loads(e)["event"] == "lease_expired"]
        assert expired and expired[0]["lease"] == lease and expired[0]["reason"] == "slot_over"
        assert names.index("lease_expired") < names.index("handoff") \
            < names.index("lease_offered") < names.index("lease_granted"), names


async def test_the_slot_is_lifted_when_nobody_waits_any_more() -> None:
    async with running_client(settings()) as (_, c):
        r = await c.post(f"/api/v1/arms/{ARM}/lease", headers=H(CAROL))
        lease = r.json()["id"]
        alice = (await c.post(f"/api/v1/arms/{ARM}/queue", headers=H(ALICE))).json()
        assert (await queue(c))["slot_left"] is not None
        r = await c.delete(f"/api/v1/arms/{ARM}/queue/{alice['id']}", headers=H(ALICE))
        assert r.status_code == 200 and r.json()["status"] == "done"
        assert (await queue(c))["slot_left"] is None
        # nobody waits: the lease outlives the slot alice's join started
        await renew_for(c, lease, SLOT_S + 1.0)
        # someone waits again: a new slot, from this join
        t_join = time.monotonic()
        await c.post(f"/api/v1/arms/{ARM}/queue", headers=H(BOB))
        q = await queue(c)
        assert q["slot_left"] is not None and q["slot_left"] <= SLOT_S
        while (r := await renew(c, lease)).status_code == 200:
            assert time.monotonic() - t_join < SLOT_S + LATE_S, "renewed past the new slot"
            await asyncio.sleep(RENEW_S)
        assert r.json()["code"] == "unknown_lease"
        assert time.monotonic() - t_join >= SLOT_S - 0.05


async def test_an_instructor_clearing_the_queue_lifts_the_slot_too() -> None:
    async with running_client(settings()) as (_, c):
        lease = (await c.post(f"/api/v1/arms/{ARM}/lease", headers=H(CAROL))).json()["id"]
        await c.post(f"/api/v1/arms/{ARM}/queue", headers=H(ALICE))
        await c.post(f"/api/v1/arms/{ARM}/queue", headers=H(BOB))
        assert (await queue(c))["slot_left"] is not None
        r = await c.delete(f"/api/v1/arms/{ARM}/queue", headers=H(TEACH))
        assert r.status_code == 200 and r.json()["entries"] == []
        assert r.json()["slot_left"] is None
        await renew_for(c, lease, SLOT_S + 1.0)


async def test_a_second_join_does_not_restart_the_slot() -> None:
    async with running_client(settings()) as (_, c):
        lease = (await c.post(f"/api/v1/arms/{ARM}/lease", headers=H(CAROL))).json()["id"]
        t_join = time.monotonic()
        await c.post(f"/api/v1/arms/{ARM}/queue", headers=H(ALICE))
        await renew_for(c, lease, SLOT_S / 2)
        left_before = (await queue(c))["slot_left"]
        await c.post(f"/api/v1/arms/{ARM}/queue", headers=H(BOB))
        left_after = (await queue(c))["slot_left"]
        assert left_after <= left_before <= SLOT_S / 2 + 0.1, (left_before, left_after)
        while (r := await renew(c, lease)).status_code == 200:
            assert time.monotonic() - t_join < SLOT_S + LATE_S, "renewed past the slot"
            await asyncio.sleep(RENEW_S)
        assert r.json()["code"] == "unknown_lease"


async def test_a_queue_holders_slot_is_not_moved_by_joins() -> None:
    async with running_client(settings(slot_s=30.0)) as (_, c):
        a = (await c.post(f"/api/v1/arms/{ARM}/queue", headers=H(ALICE))).json()

        async def offered() -> dict[str, Any] | None:
            e = await entry(c, a["id"], ALICE)
            return e if e["status"] == "offered" else None
        a = await until(offered, what="alice's offer")
        assert (await renew(c, a["lease_id"], ALICE)).status_code == 200
        slot_end = (await entry(c, a["id"], ALICE))["slot_end"]
        left = (await queue(c))["slot_left"]
        await c.post(f"/api/v1/arms/{ARM}/queue", headers=H(BOB))
        await c.post(f"/api/v1/arms/{ARM}/queue", headers=H(CAROL))
        assert (await entry(c, a["id"], ALICE))["slot_end"] == slot_end
        q = await queue(c)
        assert q["holder"] == "alice" and q["slot_left"] <= left
