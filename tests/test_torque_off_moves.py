"""Nothing is commanded to a joint whose torque is off. Before, a planned move was accepted with
the angler's torque switched off (`PUT .../torque`): the executor streamed its goals for the
whole plan (20 s) to servos that could not follow, each goal waiting in its servo for the
torque to come back, and only the settle check at the end failed it. Now every command that
moves an arm (a planned move, a pass-through goal, a teleoperation follower's start) is 409
`torque_off` while a joint's torque is off through this server, and nothing is written; a
motion that runs when a pass-through write switches a joint off fails at its next setpoint
(the watchdog), not at its end. Judged on the device's side (the simulated servos' Goal
Position and Torque Enable) and by the answers' codes."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np
import orjson
from _bus_watch import watch_writes
from _wait import held_still, wait_for

from app.arms.loading import load_profile
from app.config import homed_at_start
from app.service import ArmService
from tests.conftest import make_settings, running_client

API = "/api/v1"
DX = f"{API}/arms/angler/dynamixel"
CONFIG = Path(__file__).resolve().parents[1] / "config" / "teleop_omx.toml"


def goals(arm: ArmService) -> list[int]:
    bus = arm.driver.link.device
    return [bus.servo(j.motor_id).get("goal_position") for j in arm.profile.joints]


async def test_moves_and_goals_are_refused_while_the_torque_is_off_then_run_once_it_is_on(
        ) -> None:
    async with running_client(make_settings()) as (app, c):
        angler: ArmService = app.state.services["angler"]
        assert (await c.get(f"{API}/arms/angler")).json()["torque"] == [True] * 4
        r = await c.put(f"{API}/arms/angler/torque", json={"on": False, "load_supported": True})
        assert r.status_code == 200, r.text
        assert (await c.get(f"{API}/arms/angler")).json()["torque"] == [False] * 4
        q = await held_still(lambda: angler.positions, 1e-4)  # (the winch has paid out)
        before = goals(angler)
        target = [q[0] + 0.01, q[1], q[2], max(q[3], 0.02)]
        refused = [
            await c.post(f"{API}/arms/angler/move/joints", json={"positions": target}),
            await c.post(f"{API}/arms/angler/move/pose",
                         json={"x": 0.0, "y": 0.1, "z": 0.0}),
            await c.put(f"{DX}/2/registers/goal_position", json={"raw": before[0] + 40}),
            await c.post(f"{DX}/sync-write", json={"name": "goal_position",
                                                   "values": {"2": before[0] + 40}}),
        ]
        for r in refused:
            assert r.status_code == 409 and r.json()["code"] == "torque_off", r.text
            detail = r.json()["detail"]
            assert "x, y, theta3, z" in detail and "/arms/angler/torque" in detail, detail
        assert goals(angler) == before  # nothing written
        assert angler.motion.current is None and not angler.motion.queued()

        r = await c.put(f"{API}/arms/angler/torque", json={"on": True})
        assert r.status_code == 200, r.text
        r = await c.post(f"{API}/arms/angler/move/joints",
                         json={"positions": target, "wait": True})
        assert r.status_code == 200 and r.json()["status"] == "done", r.text
        np.testing.assert_allclose(await held_still(lambda: angler.positions, 1e-4), target,
                                   atol=2e-3)


async def test_one_joint_off_through_passthrough_refuses_moves_until_its_reboot() -> None:
    async with running_client(make_settings()) as (app, c):
        angler: ArmService = app.state.services["angler"]
        bus = angler.driver.link.device
        q = await held_still(lambda: angler.positions, 1e-4)
        sub = angler.hub.subscribe()
        try:
            r = await c.put(f"{DX}/3/registers/torque_enable", json={"raw": 0})  # theta3
            assert r.status_code == 200, r.text
            events: list[dict[str, Any]] = []

            def torque_event() -> bool:  # (as the torque route's, with the joints switched)
                events.extend(orjson.loads(e) for e in sub.take()[1])
                return any(e.get("event") == "torque" for e in events)

            await wait_for(torque_event, what="the torque event")
            assert [e["data"] for e in events if e.get("event") == "torque"] == [
                {"on": False, "joints": ["theta3"]}], events
        finally:
            sub.close()
        detail = (await c.get(f"{API}/arms/angler")).json()
        assert detail["torque"] == [True, True, False, True], detail["torque"]
        target = [q[0] + 0.01, q[1], q[2], q[3]]  # theta3 not among the joints moved
        r = await c.post(f"{API}/arms/angler/move/joints", json={"positions": target})
        assert r.status_code == 409 and r.json()["code"] == "torque_off", r.text
        assert "torque of theta3 is off" in r.json()["detail"], r.text
        assert bus.servo(2).get("goal_position") == bus.servo(2).get("present_position") or \
            abs(bus.servo(2).get("goal_position") - bus.servo(2).get("present_position")) <= 1
        r = await c.post(f"{DX}/3/reboot")  # set up again: goal = present, torque on
        assert r.status_code == 200, r.text
        assert bus.servo(3).torque
        assert (await c.get(f"{API}/arms/angler")).json()["torque"] == [True] * 4
        r = await c.post(f"{API}/arms/angler/move/joints",
                         json={"positions": target, "wait": True})
        assert r.status_code == 200 and r.json()["status"] == "done", r.text


async def test_a_running_motion_fails_at_once_when_a_joint_goes_limp() -> None:
    async with running_client(make_settings()) as (app, c):
        angler: ArmService = app.state.services["angler"]
        sub = angler.hub.subscribe()
        try:
            q = await held_still(lambda: angler.positions, 1e-4)
            r = await c.post(f"{API}/arms/angler/move/joints",
                             json={"positions": [q[0] + 0.03, q[1], q[2], q[3]],
                                   "duration": 10.0})
            assert r.status_code == 202, r.text
            mid = r.json()["id"]
            await wait_for(lambda: angler.motion.current is not None
                           and angler.motion.current.status == "running", what="running")
            t0 = time.monotonic()
            r = await c.put(f"{DX}/3/registers/torque_enable", json={"raw": 0})
            assert r.status_code == 200, r.text

            async def ended() -> dict[str, Any] | None:
                got = (await c.get(f"{API}/arms/angler/motions/{mid}")).json()
                return got if got["status"] != "running" else None

            m = await wait_for(ended, what="the motion's end")
            took = time.monotonic() - t0
            assert m["status"] == "failed" and m["code"] == "torque_off", m
            assert "theta3" in m["reason"], m
            assert took < 2.0, took  # at its next setpoint, not at the plan's end and settle
            events: list[dict[str, Any]] = []

            def watchdog() -> bool:
                events.extend(orjson.loads(e) for e in sub.take()[1])
                return any(e.get("event") == "watchdog" and e["data"]["code"] == "torque_off"
                           for e in events)

            await wait_for(watchdog, what="the watchdog event, code torque_off")
        finally:
            sub.close()


async def test_a_follower_with_its_torque_off_cannot_start_a_session() -> None:
    async with running_client(make_settings(config=str(CONFIG))) as (app, c):
        follower: ArmService = app.state.services["follower"]
        bus = follower.driver.link.device
        r = await c.put(f"{API}/arms/follower/world/hand", json={})  # the hand holds it first
        assert r.status_code == 200, r.text
        r = await c.put(f"{API}/arms/follower/torque", json={"on": False, "load_supported": True})
        assert r.status_code == 200, r.text
        r = await c.post(f"{API}/teleop", json={"leader": "leader", "follower": "follower",
                                                "rate_hz": 50})
        assert r.status_code == 409 and r.json()["code"] == "torque_off", r.text
        assert (await c.get(f"{API}/teleop")).json() == []
        assert not any(bus.servo(j.motor_id).torque for j in follower.profile.joints)
        r = await c.put(f"{API}/arms/follower/torque", json={"on": True})
        assert r.status_code == 200, r.text
        r = await c.post(f"{API}/teleop", json={"leader": "leader", "follower": "follower",
                                                "rate_hz": 50})
        assert r.status_code == 201, r.text
        r = await c.delete(f"{API}/teleop/{r.json()['id']}")
        assert r.status_code == 200, r.text


async def test_raw_access_torque_on_writes_the_present_position_as_the_goal_first() -> None:
    """With raw access a pass-through Torque Enable 1 to a joint's servo is allowed. A servo
    whose torque comes on may drive to its Goal Position: the goal from before its torque went
    off, where a hand has since moved the joint away from, a move no check has seen (the
    envelope holds with raw access too). The e-manual does not say what the MX-28 (2.0) does
    with that older goal (the simulated servo holds where it stands); the server does not rely
    on it: as the torque route does, it writes each servo's present position as its goal
    first, then the Torque Enable, and the arm's record says the joint holds there."""
    raw = homed_at_start(load_profile("angler")).model_copy(update={"raw_access": True})
    async with running_client(profiles=[raw]) as (app, c):
        angler: ArmService = app.state.services["angler"]
        bus = angler.driver.link.device
        q0 = await held_still(lambda: angler.positions, 1e-4)
        r = await c.put(f"{DX}/3/registers/torque_enable", json={"raw": 0})  # theta3
        assert r.status_code == 200, r.text
        moved = [q0[0], q0[1], q0[2] + 0.4, q0[3]]
        r = await c.put(f"{API}/arms/angler/world/hand",
                        json={"positions": moved, "speed": 0.5, "wait": True})
        assert r.status_code == 200, r.text
        r = await c.delete(f"{API}/arms/angler/world/hand")
        assert r.status_code == 204, r.text
        here = await held_still(lambda: angler.positions, 1e-4)
        np.testing.assert_allclose(here, moved, atol=2e-3)
        stale = bus.servo(3).get("goal_position")
        present = bus.servo(3).get("present_position")
        assert abs(stale - present) > 100  # the goal register still holds the older goal
        writes: list[tuple[str, dict[int, int]]] = []
        watch_writes(bus, lambda name, values: writes.append((name, values)))
        r = await c.put(f"{DX}/3/registers/torque_enable", json={"raw": 1})
        assert r.status_code == 200, r.text
        assert [w for w in writes if w[0] in ("goal_position", "torque_enable")] == [
            ("goal_position", {3: present}), ("torque_enable", {3: 1})], writes
        assert bus.servo(3).torque
        told = angler.setpoint()
        assert told is not None
        np.testing.assert_allclose(told, here, atol=2e-3)  # the record: where it holds
        assert (await c.get(f"{API}/arms/angler")).json()["torque"] == [True] * 4
        # while a planned motion runs it is busy, as the torque route is
        r = await c.post(f"{API}/arms/angler/move/joints",
                         json={"positions": [here[0] + 0.03, here[1], here[2], here[3]],
                               "duration": 10.0})
        assert r.status_code == 202, r.text
        await wait_for(lambda: angler.motion.current is not None, what="running")
        r = await c.put(f"{DX}/3/registers/torque_enable", json={"raw": 1})
        assert r.status_code == 409 and r.json()["code"] == "busy", r.text
        assert (await c.post(f"{API}/arms/angler/stop")).status_code == 200


async def test_a_torque_off_whose_status_is_lost_still_refuses_moves() -> None:
    """The bus loses the status of a Torque Enable 0 (the servo got it: its torque is off) and
    the write answers 504 `device_timeout`: the joint is taken as limp all the same, noted as
    the write went out, and a move is 409 `torque_off`, not streamed to a servo that cannot
    follow it."""
    async with running_client(make_settings()) as (app, c):
        angler: ArmService = app.state.services["angler"]
        link = angler.driver.link
        bus = link.device
        q = await held_still(lambda: angler.positions, 1e-4)
        link.set_faults(link.faults.model_copy(update={"drop": 1.0}))
        try:
            r = await c.put(f"{DX}/3/registers/torque_enable", json={"raw": 0})
            assert r.status_code == 504 and r.json()["code"] == "device_timeout", r.text
        finally:
            link.set_faults(link.faults.model_copy(update={"drop": 0.0}))
        assert not bus.servo(3).torque  # the servo got it
        await wait_for(lambda: not angler.driver.stale, what="polls answered again")
        r = await c.post(f"{API}/arms/angler/move/joints",
                         json={"positions": [q[0] + 0.01, q[1], q[2], q[3]]})
        assert r.status_code == 409 and r.json()["code"] == "torque_off", r.text
        assert (await c.get(f"{API}/arms/angler")).json()["torque"] == [True, True, False, True]


async def test_an_estop_hold_on_a_limp_arm_leaves_it_told_where_the_hand_has_it() -> None:
    """The estop's hold is sent to every joint servo, the limp ones too (it moves nothing
    there). It is not what those joints are told: a hand moving the arm during the latch moves
    what the arm is said to be headed for (`told`: a recording's action, a check's start)."""
    async with running_client(make_settings()) as (app, c):
        angler: ArmService = app.state.services["angler"]
        q0 = await held_still(lambda: angler.positions, 1e-4)
        r = await c.put(f"{API}/arms/angler/world/hand", json={"wait": True})  # hold where it is
        assert r.status_code == 200, r.text
        r = await c.put(f"{API}/arms/angler/torque", json={"on": False, "load_supported": True})
        assert r.status_code == 200, r.text
        assert (await c.post(f"{API}/arms/angler/estop")).status_code == 200
        moved = [q0[0] + 0.02, q0[1], q0[2], q0[3]]
        r = await c.put(f"{API}/arms/angler/world/hand",
                        json={"positions": moved, "speed": 0.1, "wait": True})
        assert r.status_code == 200, r.text
        np.testing.assert_allclose(await held_still(lambda: angler.positions, 1e-4), moved,
                                   atol=2e-3)
        told = angler.setpoint()
        assert told is not None
        np.testing.assert_allclose(told, moved, atol=2e-3)
