"""app/runtime/gc_policy.py, issue 23: no garbage collection falls inside a pass-through goal.

A collection stops every thread. CPython starts a young one at the allocation that crosses
generation 0's threshold, and a goal's own path (HTTP, validation, the check, the write)
allocates, so that is where they fell: in a traced run (bench/goal_trace.py) 94 of 400 goals
met one, and generation-1 collections were in every one of the slowest four, which set the
goal's p99. Now a goal holds automatic collections off from the facade's call until its effect
can have been seen (`hold`), the policy runs the young collections itself on a timer between
commands (`collect_young`), and a due full collection waits while a goal holds them off or the
joints move. These tests use the real app over the simulated angler.
"""

from __future__ import annotations

import asyncio
import gc
from collections import deque
from typing import Any

import pytest
from _wait import wait_for
from conftest import make_settings, running_client

from app.runtime import gc_policy

GOAL = "/api/v1/arms/angler/dynamixel/3/registers/goal_position"
#: theta3's joint index
K = 2


class Node:
    """A container the cyclic collector tracks."""

    other: Any = None


def collections() -> tuple[list[int], Any]:
    """A list that gets each collection's generation as it starts, and the callback (removed
    by the caller)."""
    seen: list[int] = []

    def cb(phase: str, info: dict[str, Any]) -> None:
        if phase == "start":
            seen.append(int(info["generation"]))
    gc.callbacks.append(cb)
    return seen, cb


def allocate(n: int) -> list[Node]:
    """`n` live tracked containers: each counts towards generation 0's threshold."""
    return [Node() for _ in range(n)]


async def test_no_collection_runs_inside_a_passthrough_goal() -> None:
    async with running_client(make_settings(control_thread=False)) as (app, _):
        svc = app.state.services["angler"]
        await wait_for(lambda: svc.driver.told() is not None and not svc.driver.stale,
                       what="the angler's first reading")
        ticks = float(svc.model.transmission.to_ticks(svc.driver.told())[K])
        threshold = max(1, gc.get_threshold()[0])
        during: list[int] = []
        kept: list[list[Node]] = []
        seen, cb = collections()
        try:
            async def send() -> bool:
                n0 = len(seen)
                # ten young generations' worth: without the hold, CPython collects ten times
                kept.append(allocate(10 * threshold))
                during.extend(seen[n0:])
                return gc.isenabled()

            enabled = await svc.command_passthrough({K: ticks}, send)
            assert not enabled, "automatic collections were on while the goal was sent"
            assert during == [], f"collections of generations {during} inside the goal"
            # the collection the goal's allocations made due runs once the hold ends
            n1 = len(seen)
            await wait_for(lambda: gc.isenabled(), what="collections back after the hold")
            kept.append(allocate(threshold))
            await wait_for(lambda: len(seen) > n1, what="the due collection after the goal")
        finally:
            gc.callbacks.remove(cb)


async def test_goals_back_to_back_do_not_put_collections_off_for_good() -> None:
    async with running_client(make_settings(control_thread=False)):
        threshold = max(1, gc.get_threshold()[0])
        refused = gc_policy.holds["refused"]
        kept = []
        seen, cb = collections()
        try:
            for _ in range(3 * gc_policy.HOLD_MAX_PENDING):  # a goal every young generation
                gc_policy.hold()
                kept.append(allocate(threshold))
            assert gc_policy.holds["refused"] > refused
            assert seen, "no collection while goals came back to back"
        finally:
            gc.callbacks.remove(cb)
        await wait_for(lambda: gc.isenabled() and not gc_policy.held(),
                       what="collections back once the goals stop")


async def test_the_policy_runs_young_collections_between_commands_not_inside_them() -> None:
    async with running_client(make_settings(control_thread=False)) as (app, _):
        col = app.state.collector
        t0 = max(1, gc.get_threshold()[0])
        seen, cb = collections()
        try:
            # under CPython's line: only the policy's timer collects it
            gc.collect(0)
            before = col.young_collections
            kept = allocate(t0 // 4)
            await wait_for(lambda: col.young_collections > before,
                           what="a young collection run by the policy's timer")
            assert seen and gc.get_count()[0] < t0
            # while a goal holds collections off, the timer runs none either
            assert gc_policy.hold(seconds=60.0)
            try:
                n0 = len(seen)
                kept += allocate(t0)
                assert col.collect_young() is None and len(seen) == n0
            finally:
                with gc_policy._hold_lock:
                    gc_policy._let_go()
            del kept
        finally:
            gc.callbacks.remove(cb)


async def test_the_policy_collects_a_young_generation_that_churn_hides_from_the_count() -> None:
    """Issue 27: CPython's count of generation 0 is its allocations less the deallocations of
    any generation, so a log that frees its oldest entry as it takes a new one (the telemetry
    logs) keeps it near zero while generation 0 fills up: a lab worker's young collection came
    after 64,000 samples' containers and took 20-30 ms. The policy's tick collects it anyway."""
    async with running_client(make_settings(control_thread=False)) as (app, _):
        col = app.state.collector
        ring = deque(allocate(2000), maxlen=2000)
        gc.collect(0)
        for _ in range(6000):  # a new entry in, the oldest out
            ring.append(Node())
        assert gc.get_count()[0] < gc.get_threshold()[0] // 2  # CPython sees nothing due
        young = sum(isinstance(o, Node) for o in gc.get_objects(0))
        assert young >= 1000, young
        assert col.collect_young() is not None
        assert sum(isinstance(o, Node) for o in gc.get_objects(0)) == 0
        del ring


async def test_a_due_full_collection_waits_while_a_goal_holds_collections_off() -> None:
    async with running_client(make_settings(control_thread=False)):
        col = gc_policy.Collector(lambda: False, every_s=0.05, defer_max_s=60.0)
        col.start()
        try:
            assert gc_policy.hold(seconds=0.8)  # a goal in flight for 0.8 s
            await asyncio.sleep(0.6)  # under test: for 0.6 s, nothing (due, but held off)
            assert gc_policy.held()
            assert col.full_collections == 0  # due since 0.05 s, deferred: a goal in flight
            await wait_for(lambda: col.full_collections >= 1,
                           what="the full collection once no goal holds")
        finally:
            await col.close()


async def test_an_arm_is_busy_for_the_policy_while_a_passthrough_goal_moves_it() -> None:
    async with running_client(make_settings(control_thread=False)) as (app, client):
        busy = app.state.collector.busy
        await wait_for(lambda: not busy(), what="the arms at rest")
        granted = gc_policy.holds["granted"] + gc_policy.holds["refused"]
        r = await client.get("/api/v1/arms/angler/dynamixel/3/registers/present_position")
        raw = r.json()["raw"]
        r = await client.put(GOAL, json={"raw": raw + 60 if raw < 2048 else raw - 60})
        assert r.status_code == 200, r.text
        assert gc_policy.holds["granted"] + gc_policy.holds["refused"] == granted + 1
        await wait_for(busy, what="the joints moving after the goal")
        await wait_for(lambda: not busy(), what="the joints at rest again")


@pytest.fixture(autouse=True)
def _no_hold_left() -> Any:
    yield
    with gc_policy._hold_lock:
        gc_policy._let_go()
    assert gc.isenabled()


async def test_a_busy_check_that_fails_does_not_end_the_policy() -> None:
    calls = [0]

    def busy() -> bool:
        calls[0] += 1
        raise ValueError("an arm's reading of another shape")
    col = gc_policy.Collector(busy, every_s=0.05)
    col.start()
    try:
        await wait_for(lambda: col.full_collections >= 2, what="collections run as due")
        assert calls[0] >= 2
    finally:
        await col.close()


async def test_a_due_young_collection_runs_at_a_wake_up_the_loop_makes_anyway() -> None:
    """Issue 27, session 41: the policy's timer woke an idle control loop 20 times a second for
    its young collections. `young_if_due` runs a due one at a wake-up the loop makes anyway
    (an arm's hand-over of replies, a poll's sample), none sooner than `YOUNG_EVERY_S` after
    the last; the timer waits `YOUNG_TIMER_S` from the last one (bench/sample_cost.py
    measures the wake-ups saved)."""
    async with running_client(make_settings(control_thread=False)) as (app, _):
        col = app.state.collector
        seen, cb = collections()
        try:
            gc_policy.young_if_due()  # (due or not: the clock starts at the policy's last)
            n0 = col.young_collections
            gc_policy.young_if_due()  # just run: not due
            assert col.young_collections == n0
            await asyncio.sleep(gc_policy.YOUNG_EVERY_S)  # (the arms' polls may run it first)
            gc_policy.young_if_due()
            assert col.young_collections >= n0 + 1 and seen
            assert gc_policy._last_young > 0.0
        finally:
            gc.callbacks.remove(cb)
