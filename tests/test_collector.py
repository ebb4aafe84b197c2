"""app/runtime/gc_policy.py: while a server runs, the start-up objects are frozen, automatic full
collections are rare, and the full collections it runs itself wait for no arm to be moving
(a full collection stops every thread: 140-180 ms with 700 hostile clients connected)."""

from __future__ import annotations

import asyncio
import gc
import weakref
from typing import Any

import pytest
from _wait import wait_for

from app import schemas as s
from app.arms.loading import load_profile
from app.config import homed_at_start
from app.runtime import gc_policy as c
from app.runtime.gc_policy import Collector, moving
from app.service import ArmService


async def test_frozen_rare_and_restored() -> None:
    # (an app another test left running in this worker would hold the settings: then they
    # stay as that app set them)
    others = c._active
    before, frozen = gc.get_threshold(), gc.get_freeze_count()
    col = Collector(lambda: False, every_s=3600.0)
    col.start()
    try:
        assert gc.get_threshold()[2] == c.GEN2_THRESHOLD
        assert gc.get_threshold()[:2] == before[:2]
        assert gc.get_freeze_count() > 1000  # the modules and classes loaded so far
    finally:
        await col.close()
    assert gc.get_threshold() == before
    assert gc.get_freeze_count() == (0 if others == 0 else frozen)


class _Cycle:
    def __init__(self) -> None:
        self.me = self


@pytest.mark.parametrize("collect", [True, False])
async def test_start_frees_the_garbage_before_it_freezes_unless_told_not_to(
        collect: bool, monkeypatch: pytest.MonkeyPatch) -> None:
    """`start(collect=False)` (Settings.warm_start off) freezes start-up's garbage with the
    rest; stopping unfreezes it, and the next collection frees it."""
    monkeypatch.setattr(c, "_active", 0)  # this collector is the process's first
    monkeypatch.setattr(c, "_saved", None)
    gc.collect()
    garbage = _Cycle()
    gone = weakref.ref(garbage)
    del garbage  # a cycle: only a collection frees it
    col = Collector(lambda: False, every_s=3600.0)
    col.start(collect=collect)
    try:
        gc.collect()  # frozen objects are not walked
        assert (gone() is None) is collect
    finally:
        await col.close()
    gc.collect()
    assert gone() is None


async def test_two_servers_in_one_process_restore_once_the_last_ends(
        monkeypatch: pytest.MonkeyPatch) -> None:
    # The process's count of collectors and gc settings are this test's own for its length (an
    # app another test left running in this worker would hold them: it neither skips nor
    # passes vacuously then), and both are put back after.
    monkeypatch.setattr(c, "_active", 0)
    monkeypatch.setattr(c, "_saved", None)
    outer = gc.get_threshold()
    gc.set_threshold(700, 10, 10)
    try:
        a, b = Collector(lambda: False, 3600.0), Collector(lambda: False, 3600.0)
        a.start()
        b.start()
        await a.close()
        assert gc.get_threshold() == (700, 10, c.GEN2_THRESHOLD)  # b still runs
        await b.close()
        assert gc.get_threshold() == (700, 10, 10)
    finally:
        gc.set_threshold(*outer)


async def test_a_due_collection_waits_for_the_arms_to_stop_and_frees_cycles() -> None:
    moving_now = [True]
    col = Collector(lambda: moving_now[0], every_s=0.05, defer_max_s=60.0)
    col.start()
    try:
        await asyncio.sleep(0.6)  # under test: for 0.6 s, nothing (due, but an arm is moving)
        assert col.full_collections == 0  # due since 0.05 s, deferred: an arm is moving

        class Node:
            other: Any = None
        x, y = Node(), Node()
        x.other, y.other = y, x  # a cycle only the cyclic collector frees
        del x, y
        moving_now[0] = False
        await wait_for(lambda: col.full_collections, what="a full collection")
        assert col.full_collections >= 1 and col.longest_s > 0.0
        assert not [o for o in gc.get_objects() if type(o).__name__ == "Node"]
    finally:
        await col.close()


async def test_a_collection_deferred_too_long_runs_anyway() -> None:
    col = Collector(lambda: True, every_s=0.05, defer_max_s=0.5)
    col.start()
    try:
        await wait_for(lambda: col.full_collections >= 1, what="the collection deferred too long")
    finally:
        await col.close()


async def test_moving_is_true_while_an_arm_executes_a_motion_until_it_is_at_rest() -> None:
    svc = ArmService(homed_at_start(load_profile("rbe3001")))
    await svc.start()
    try:
        assert await svc.driver.wait_connected(5.0)
        busy = moving({"rbe3001": svc})
        assert not busy()
        rec = await svc.motion.move_joints(s.MoveJoints(positions=[0.3, 0.6, 0.3]))
        seen = False
        while not rec.done.is_set():
            seen = seen or busy()
            await asyncio.sleep(0.01)
        assert seen and rec.status == "done", rec.reason
        # (the joints' last readings may still move a little as the motion ends: busy till then)
        await wait_for(lambda: not busy(), what="the arm at rest after its motion")
    finally:
        await svc.close()
