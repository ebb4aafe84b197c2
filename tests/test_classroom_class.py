"""A class of fifty: students with their own tokens join both arms' queues at once, claim (or
let the offer pass), move and let their slots end, with accelerated claim and slot times; the
server is restarted in the middle.

Checked: never two holders of one arm (the lease events alternate granted / ended, and every
hand-off lies between), never a move from someone who does not hold the arm (every accepted
move lies inside its sender's slot; every move from a waiting student is refused 409), every
hand-off ends at the home pose with no fault, every change is in the audit log, and the restart
keeps the queues and the log.
"""

from __future__ import annotations

import asyncio
import json
import time
from collections import Counter
from pathlib import Path
from typing import Any

import httpx
import numpy as np

from app.classroom.queue import home_pose
from tests.conftest import make_settings, running_client

STUDENTS = 50
ARMS = ("rbe3001", "angler")
TEACH = "class-teach"
#: joint offsets from home each student moves by (small: the test is about turns, not travel)
NUDGE = {"rbe3001": [0.05, 0.0, 0.0], "angler": [0.002, 0.0, 0.0, 0.0]}


def token(i: int) -> str:
    return f"student-token-{i:02d}"


def name(i: int) -> str:
    return f"s{i:02d}"


def settings_for(data_dir: Path) -> Any:
    return make_settings(operator_tokens=",".join(f"{name(i)}:{token(i)}"
                                                  for i in range(STUDENTS)),
                         instructor_tokens=f"teach:{TEACH}", claim_s=1.5, slot_s=0.8,
                         lease_ttl_s=0.6, data_dir=str(data_dir))


class Class:
    def __init__(self) -> None:
        self.entries: dict[int, tuple[str, str]] = {}  # student -> (arm, entry id)
        self.sent: Counter[str] = Counter()  # changing requests sent, per name
        self.moves: list[tuple[int, float, float]] = []  # accepted: student, sent, answered
        self.finished: set[int] = set()
        self.stopping = False  # the server is about to restart: students return, unfinished

    async def req(self, c: httpx.AsyncClient, i: int, method: str, url: str,
                  **kw: Any) -> httpx.Response:
        headers = {"Authorization": f"Bearer {token(i)}", **kw.pop("headers", {})}
        if method != "GET":
            self.sent[name(i)] += 1
        return await c.request(method, url, headers=headers, **kw)

    async def student(self, c: httpx.AsyncClient, i: int) -> None:
        arm = ARMS[i % 2]
        if i not in self.entries:
            r = await self.req(c, i, "POST", f"/api/v1/arms/{arm}/queue")
            assert r.status_code == 201, r.text
            self.entries[i] = (arm, r.json()["id"])
        _, eid = self.entries[i]
        home = [float(v) for v in self.home[arm]]
        target = [h + d for h, d in zip(home, NUDGE[arm], strict=True)]
        tried_early = False
        while True:
            if self.stopping:
                return
            e = (await self.req(c, i, "GET", f"/api/v1/arms/{arm}/queue/{eid}")).json()
            if e["status"] in ("done", "expired"):
                self.finished.add(i)
                return
            if e["status"] == "offered" and e["lease_id"]:
                break
            if not tried_early:  # a move while waiting is refused, with or without a guess
                tried_early = True
                r = await self.req(c, i, "POST", f"/api/v1/arms/{arm}/move/joints",
                                   json={"positions": target},
                                   headers={"X-Arm-Lease": "guessed-lease"})
                assert r.status_code == 409 and r.json()["code"] == "leased", r.text
            await asyncio.sleep(0.2)
        lease = e["lease_id"]
        if i % 5 == 0:  # lets the offer pass
            await asyncio.sleep(1.6)
        else:
            r = await self.req(c, i, "PUT", f"/api/v1/arms/{arm}/lease/{lease}")
            if r.status_code == 200:
                t0 = time.time()
                r = await self.req(c, i, "POST", f"/api/v1/arms/{arm}/move/joints",
                                   json={"positions": target, "wait": True},
                                   headers={"X-Arm-Lease": lease})
                if r.status_code == 200:
                    self.moves.append((i, t0, time.time()))
                if i % 5 == 4:  # leaves early
                    await self.req(c, i, "DELETE", f"/api/v1/arms/{arm}/lease/{lease}")
                else:  # renews until the slot ends
                    while (await self.req(c, i, "PUT",
                                          f"/api/v1/arms/{arm}/lease/{lease}")).status_code == 200:
                        if self.stopping:
                            return
                        await asyncio.sleep(0.2)
        while True:  # until the entry has ended
            if self.stopping:
                return
            e = (await self.req(c, i, "GET", f"/api/v1/arms/{arm}/queue/{eid}")).json()
            if e["status"] in ("done", "expired"):
                self.finished.add(i)
                return
            await asyncio.sleep(0.2)


def check_events(events: list[dict[str, Any]], home: np.ndarray,
                 at_start: tuple[str | None, str | None]) -> int:
    """Granted/ended alternate; an offer only after a successful hand-off (or at start).
    `at_start`: the (offered, holding) names when the events began to be watched."""
    offered, holder = at_start
    handoffs = 0
    clear_to_offer = offered is None and holder is None
    for ev in events:
        kind, data = ev["event"], ev["data"]
        if kind == "lease_offered":
            assert holder is None and offered is None and clear_to_offer, ev
            offered, clear_to_offer = data["who"], False
        elif kind == "lease_granted":
            assert holder is None and offered == data["who"], ev
            holder, offered = data["who"], None
        elif kind == "lease_ended":
            assert data["who"] in (holder, offered), ev
            holder = offered = None
        elif kind == "handoff":
            assert holder is None and offered is None, ev
            assert data["ok"] is True, ev
            assert np.allclose(data["positions"], home, atol=0.03), ev
            handoffs += 1
            clear_to_offer = True
    return handoffs


async def run_phase(room: Class, settings: Any, stop_after_turns: int | None) -> dict[str, Any]:
    first_move = len(room.moves)  # this phase's moves (a restart may grant an entry again)
    async with running_client(settings) as (app, c):
        room.home = {a: home_pose(app.state.services[a]) for a in ARMS}
        subs = {a: app.state.services[a].hub.subscribe() for a in ARMS}
        at_start = {}
        for a in ARMS:  # (no await since subscribing: no event can slip in between)
            cur = app.state.classroom.queue(a).current()
            at_start[a] = (cur.name if cur is not None and cur.status == "offered" else None,
                           cur.name if cur is not None and cur.status == "holding" else None)
        tasks = [asyncio.create_task(room.student(c, i)) for i in range(STUDENTS)
                 if i not in room.finished]
        ended = 0
        events: dict[str, list[dict[str, Any]]] = {a: [] for a in ARMS}
        deadline = time.monotonic() + 400.0
        while not all(t.done() for t in tasks) and not room.stopping:
            assert time.monotonic() < deadline, "the class did not finish"
            await asyncio.sleep(0.1)
            for a in ARMS:
                _, evs, _ = subs[a].take()
                for raw in evs:
                    ev = json.loads(raw)
                    events[a].append(ev)
                    ended += ev["event"] == "lease_ended"
            if stop_after_turns is not None and ended >= stop_after_turns:
                room.stopping = True
        for t in tasks:
            await asyncio.wait_for(t, 30.0)  # a student's failed assertion fails the test
        room.stopping = False
        for a in ARMS:
            _, evs, _ = subs[a].take()
            events[a] += [json.loads(raw) for raw in evs]
            subs[a].close()
        handoffs = sum(check_events(events[a], room.home[a], at_start[a]) for a in ARMS)
        teach = {"Authorization": f"Bearer {TEACH}"}
        queues = {a: (await c.get(f"/api/v1/arms/{a}/queue", headers=teach)).json()
                  for a in ARMS}
        log = (await c.get("/api/v1/audit", params={"limit": 10000}, headers=teach)).json()
        # every accepted move of this phase lies inside its sender's holding time (an entry
        # held across the restart is granted again after it: its earlier moves were checked
        # against its earlier holding time at the end of the first phase)
        for i, t0, t1 in room.moves[first_move:]:
            arm, eid = room.entries[i]
            e = (await c.get(f"/api/v1/arms/{arm}/queue/{eid}", headers=teach)).json()
            if e["started"] is not None:
                assert e["started"] <= t0 and (e["ended"] is None or t1 <= e["ended"] + 0.05), e
        return {"queues": queues, "log": log, "handoffs": handoffs, "events": events}


async def test_fifty_students_two_arms_restart_in_the_middle(tmp_path: Path) -> None:
    settings = settings_for(tmp_path)
    room = Class()
    first = await run_phase(room, settings, stop_after_turns=8)
    waiting_before = {a: [e["id"] for e in first["queues"][a]["entries"]] for a in ARMS}
    assert sum(len(v) for v in waiting_before.values()) > 20  # most still queued
    second_settings = settings_for(tmp_path)
    async with running_client(second_settings) as (_, c):  # the restart keeps queue and log
        teach = {"Authorization": f"Bearer {TEACH}"}
        for a in ARMS:
            q = (await c.get(f"/api/v1/arms/{a}/queue", headers=teach)).json()
            restored = [e["id"] for e in q["entries"]]
            # the same queue; its head may have moved on in the moment between the last look
            # and the shutdown (a slot ended, a hand-off ran, the next was offered)
            k = len(waiting_before[a]) - len(restored)
            assert 0 <= k <= 2 and restored == waiting_before[a][k:], (restored, waiting_before)
        log = (await c.get("/api/v1/audit", params={"limit": 10000}, headers=teach)).json()
        assert log[-len(first["log"]):] == first["log"]
    second = await run_phase(room, settings_for(tmp_path), stop_after_turns=None)
    assert room.finished == set(range(STUDENTS))
    for a in ARMS:
        assert second["queues"][a]["entries"] == [] and second["queues"][a]["blocked"] is None
    assert len(room.moves) >= STUDENTS // 2  # most students moved in their slot
    assert first["handoffs"] + second["handoffs"] >= STUDENTS - 2
    # every change the students sent is in the log, under their name
    logged = Counter(r["name"] for r in second["log"] if r["name"].startswith("s"))
    assert logged == room.sent
    assert not any(token(i) in json.dumps(second["log"]) for i in range(STUDENTS))
