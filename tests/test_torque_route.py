"""`PUT /api/v1/arms/{arm}/torque` (an addition to API.md): the joints' torque off, the arm free
to be moved by hand, or on again holding where the hand left it. Through the real app over the
simulated arms, judged on the device's side of the link (the simulated servos' Torque Enable,
Goal Position and Present Position) and by the answers' codes. Refusals change nothing: a
joint that falls without torque (the angler's z winch) unless the body says its load is held,
a device without a torque switch (the rbe3001), an arm in a teleoperation session, another
client's lease, a body that is not one."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from _wait import held_still, wait_for

from app.service import ArmService
from tests._lerobot import check_dataset
from tests.conftest import make_settings, running_client
from tests.test_recording_api import frames_at_least

API = "/api/v1"
CONFIG = Path(__file__).resolve().parents[1] / "config" / "teleop_omx.toml"


def servos(arm: ArmService) -> list[Any]:
    """The simulated joint servos behind the arm's link (the device side)."""
    bus = arm.driver.link.device
    return [bus.servo(j.motor_id) for j in arm.profile.joints]


async def test_torque_off_refused_while_the_winch_would_fall_then_off_and_on_holding() -> None:
    async with running_client(make_settings()) as (app, c):
        angler: ArmService = app.state.services["angler"]
        events: list[dict[str, Any]] = []
        sub = angler.hub.subscribe()
        try:
            r = await c.put(f"{API}/arms/angler/torque", json={"on": False})
            assert r.status_code == 409 and r.json()["code"] == "in_use", r.text
            assert "z falls without torque" in r.json()["detail"], r.text
            assert all(sv.torque for sv in servos(angler))  # nothing switched

            r = await c.put(f"{API}/arms/angler/torque",
                            json={"on": False, "load_supported": True})
            assert r.status_code == 200, r.text
            assert r.json() == {"arm": "angler", "on": False}
            assert not any(sv.torque for sv in servos(angler))
            # the winch's load, held by nobody in the simulator, goes down as a real one does
            z = angler.profile.joints.index(next(j for j in angler.profile.joints
                                                if j.falls_without_torque))
            before = servos(angler)[z].pos
            await wait_for(lambda: abs(servos(angler)[z].pos - before) > 10,
                           what="the free winch paying out")

            r = await c.put(f"{API}/arms/angler/torque", json={"on": True})
            assert r.status_code == 200 and r.json() == {"arm": "angler", "on": True}, r.text
            assert all(sv.torque for sv in servos(angler))
            # each servo holds where it was left: its goal is its present position
            for sv in servos(angler):
                assert abs(sv.get("goal_position") - sv.get("present_position")) <= 1
            here = [sv.pos for sv in servos(angler)]
            await wait_for(lambda: angler.hub.published > 20, what="samples")
            assert np.allclose([sv.pos for sv in servos(angler)], here, atol=1.0)
            _samples, got, _dropped = sub.take()
            events = [e for e in map(_json, got) if e.get("event") == "torque"]
        finally:
            sub.close()
        assert [e["data"] for e in events] == [{"on": False}, {"on": True}]


def _json(raw: str) -> dict[str, Any]:
    import orjson

    out: dict[str, Any] = orjson.loads(raw)
    return out


async def test_the_refusals_change_nothing() -> None:
    async with running_client(make_settings()) as (app, c):
        angler: ArmService = app.state.services["angler"]
        r = await c.put(f"{API}/arms/rbe3001/torque", json={"on": False})
        assert r.status_code == 409 and r.json()["code"] == "not_supported", r.text
        r = await c.put(f"{API}/arms/nope/torque", json={"on": False})
        assert r.status_code == 404 and r.json()["code"] == "unknown_arm", r.text
        for body in ({"on": "no"}, {}, {"on": False, "load_supported": 1}, [False]):
            r = await c.put(f"{API}/arms/angler/torque", json=body)
            assert r.status_code == 422, (body, r.text)
        r = await c.put(f"{API}/arms/angler/torque", content=b"{not json",
                        headers={"content-type": "application/json"})
        assert r.status_code == 422 and r.json()["code"] == "invalid_json", r.text
        # another client's lease
        r = await c.post(f"{API}/arms/angler/lease")
        assert r.status_code in (200, 201), r.text
        r = await c.put(f"{API}/arms/angler/torque", json={"on": False, "load_supported": True})
        assert r.status_code == 409 and r.json()["code"] == "leased", r.text
        assert all(sv.torque for sv in servos(angler))
        # torque on (holding where it is) is open to every operator, like the estop's hold
        r = await c.put(f"{API}/arms/angler/torque", json={"on": True})
        assert r.status_code == 200, r.text
        assert all(sv.torque for sv in servos(angler))


async def test_the_estop_latch_lets_torque_off_and_on_through() -> None:
    """Torque off is the safe write and torque on moves nothing: neither waits for a release."""
    async with running_client(make_settings()) as (app, c):
        angler: ArmService = app.state.services["angler"]
        assert (await c.post(f"{API}/arms/angler/estop")).status_code == 200
        r = await c.put(f"{API}/arms/angler/torque", json={"on": False, "load_supported": True})
        assert r.status_code == 200, r.text
        assert not any(sv.torque for sv in servos(angler))
        r = await c.put(f"{API}/arms/angler/torque", json={"on": True})
        assert r.status_code == 200, r.text
        assert all(sv.torque for sv in servos(angler))
        assert angler.estop  # still latched


async def test_an_arm_in_a_teleoperation_session_is_busy() -> None:
    async with running_client(make_settings(config=str(CONFIG))) as (app, c):
        r = await c.post(f"{API}/teleop", json={"leader": "leader", "follower": "follower",
                                                "rate_hz": 50})
        assert r.status_code == 201, r.text
        sid = r.json()["id"]
        for arm in ("leader", "follower"):
            r = await c.put(f"{API}/arms/{arm}/torque", json={"on": False,
                                                              "load_supported": True})
            assert r.status_code == 409 and r.json()["code"] == "busy", r.text
            assert sid in r.json()["detail"]
            assert all(sv.torque for sv in servos(app.state.services[arm]))
        assert (await c.delete(f"{API}/teleop/{sid}")).status_code == 200
        r = await c.put(f"{API}/arms/follower/torque", json={"on": False, "load_supported": True})
        assert r.status_code == 200, r.text


async def test_a_demonstration_by_hand_records_where_the_hand_took_the_arm() -> None:
    """Torque off, an arm moved by hand while a recording runs (the simulated world's hand on
    an OpenManipulator-X): its episode's action is where the hand has the arm, as its state
    is, not the goal the servos held before the torque went off (the commanded state is
    forgotten with the torque); the dataset is read as LeRobot's."""
    async with running_client(make_settings(config=str(CONFIG))) as (app, c):
        arm: ArmService = app.state.services["leader"]
        n = len(arm.profile.joints)
        tol = 8 * 2 * np.pi / 4096  # the XM430's settle tolerance (8 ticks), rad
        # a move first: the servos' goal, the arm's commanded state, is then this pose
        start = [0.1, -0.2, 0.1, 0.2]
        r = await c.post(f"{API}/arms/leader/move/joints", json={"positions": start,
                                                                 "wait": True})
        assert r.status_code == 200 and r.json()["status"] == "done", r.text
        np.testing.assert_allclose(await held_still(lambda: arm.positions, tol), start,
                                   atol=2 * tol)
        path = [[0.4, -0.3, 0.2, 0.5], [-0.2, -0.1, 0.1, 0.3]]
        r = await c.put(f"{API}/arms/leader/world/hand", json={"wait": True})  # held first
        assert r.status_code == 200, r.text
        r = await c.put(f"{API}/arms/leader/torque", json={"on": False, "load_supported": True})
        assert r.status_code == 200, r.text
        r = await c.post(f"{API}/recordings", json={"name": "shown", "arms": ["leader"],
                                                     "fps": 25, "task": "shown by hand"})
        assert r.status_code == 201, r.text
        assert (await c.post(f"{API}/recordings/shown/episodes")).status_code == 201
        for q in path:
            r = await c.put(f"{API}/arms/leader/world/hand",
                            json={"positions": q, "speed": 0.8, "wait": True})
            assert r.status_code == 200, r.text
            await wait_for(lambda q=q: np.allclose(arm.positions, q, atol=tol),
                           what=f"the arm's samples at {q}")
        there = (await c.get(f"{API}/recordings/shown")).json()["current"]["frames"]
        await frames_at_least(c, "shown", there + 3)  # three more frames
        r = await c.post(f"{API}/recordings/shown/episodes/stop")
        assert r.status_code == 200, r.text
        read = check_dataset(Path(r.json()["path"]))
        action = read.frames["action"][:, :n].astype(float)
        state = read.frames["observation.state"][:, :n].astype(float)
        # the hand's way, in the state and in the action alike, ending where it let the arm
        np.testing.assert_allclose(state[-1], path[-1], atol=tol)
        np.testing.assert_allclose(action[-1], path[-1], atol=tol)
        assert float(np.max(np.abs(action - state))) < 0.8 / 25 + 2 * tol
        assert float(np.max(np.abs(action[-1] - start))) > 0.25  # not the goal held before
        r = await c.put(f"{API}/arms/leader/torque", json={"on": True})
        assert r.status_code == 200, r.text
        assert (await c.delete(f"{API}/arms/leader/world/hand")).status_code == 204
        np.testing.assert_allclose(await held_still(lambda: arm.positions, tol), path[-1],
                                   atol=2 * tol)  # holding where the hand left it
