"""A simulated leader moved through its world (issue 26: "the leader is a simulated arm moved
through its world"): `PUT /arms/{arm}/world/hand` moves the simulated servos whose torque is
off, on the device's side of the link, and the server reads them as it reads hardware.
Teleoperation between two simulated OpenManipulator-X arms (config/teleop_omx.toml) with
`free_leader`: the leader's torque goes off, a hand drives it along a path, the follower
follows, and a recording made meanwhile holds the leader's joints as the action and the
follower's as the state. The hand's refusals: torque on (409 `conflict`, nothing moved), a
goal beyond the limits, a wrong width, a device without servos, a real arm."""

from __future__ import annotations

from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import orjson
import pytest
from _wait import held_still, wait_for
from fastapi import FastAPI

from app.client import AsyncArmClient
from app.service import ArmService
from tests._lerobot import check_dataset
from tests.conftest import make_settings, running_client
from tests.test_recording_api import frames_at_least
from tests.test_recording_teleop import path_distance

API = "/api/v1"
CONFIG = Path(__file__).resolve().parents[1] / "config" / "teleop_omx.toml"
TOL = 8 * 2 * np.pi / 4096  # rad: the XM430's settle tolerance (8 ticks)
START = {"leader": "leader", "follower": "follower", "rate_hz": 50, "free_leader": True,
         "load_supported": True}
PATH = [[0.4, -0.3, 0.2, 0.5], [0.6, -0.5, 0.4, 0.7], [-0.2, -0.1, 0.1, 0.3]]
SPEED = 0.8  # rad/s on the joint with the longest way


@pytest.fixture()
async def pair() -> AsyncIterator[tuple[FastAPI, httpx.AsyncClient]]:
    async with running_client(make_settings(config=str(CONFIG))) as p:
        yield p


def servos(arm: ArmService) -> list[Any]:
    """The simulated joint servos behind the arm's link (the device side)."""
    bus = arm.driver.link.device
    return [bus.servo(j.motor_id) for j in arm.profile.joints]


async def hand(c: httpx.AsyncClient, arm: str, q: list[float], **more: Any) -> httpx.Response:
    return await c.put(f"{API}/arms/{arm}/world/hand", json={"positions": q, **more})


async def test_a_torque_on_arm_resists_the_hand(pair: tuple[FastAPI, httpx.AsyncClient]) -> None:
    app, c = pair
    leader: ArmService = app.state.services["leader"]
    here = await held_still(lambda: leader.positions, TOL)
    assert all(sv.torque for sv in servos(leader))
    r = await hand(c, "leader", PATH[0])
    assert r.status_code == 409 and r.json()["code"] == "conflict", r.text
    assert "torque" in r.json()["detail"]
    np.testing.assert_allclose(await held_still(lambda: leader.positions, TOL), here, atol=TOL)
    for body, status, code in (
            ({"positions": [0.1, 0.2]}, 422, "invalid_request"),
            ({"positions": [3.5, 0.0, 0.0, 0.0]}, 422, "joint_limit"),
            ({"positions": PATH[0], "speed": 0}, 422, "invalid_request"),
            ({"positions": PATH[0], "speed": "1"}, 422, "invalid_request")):
        r = await c.put(f"{API}/arms/leader/world/hand", json=body)
        assert r.status_code == status and r.json()["code"] == code, (body, r.text)


async def test_a_leader_that_falls_without_torque_is_freed_only_when_held(
        pair: tuple[FastAPI, httpx.AsyncClient]) -> None:
    """An OpenManipulator-X's shoulder, elbow and wrist fall without torque (its profile's
    `falls_without_torque`): freeing it as a leader is 409 `in_use`, its torque left on and
    no session started, unless the body says its load is held; not freed, it leads by its
    own commands."""
    app, c = pair
    leader: ArmService = app.state.services["leader"]
    assert leader.profile.falling_joints == ["shoulder", "elbow", "wrist"]
    r = await c.post(f"{API}/teleop", json={**START, "load_supported": False})
    assert r.status_code == 409 and r.json()["code"] == "in_use", r.text
    assert '{"load_supported": true}' in r.json()["detail"]
    assert all(sv.torque for sv in servos(leader)), "a refused session freed the leader"
    assert (await c.get(f"{API}/teleop")).json() == []
    r = await c.post(f"{API}/teleop", json={**START, "free_leader": False,
                                            "load_supported": False})
    assert r.status_code == 201 and r.json()["free_leader"] is False, r.text
    assert all(sv.torque for sv in servos(leader))
    assert (await c.delete(f"{API}/teleop/{r.json()['id']}")).status_code == 200


async def test_the_follower_follows_a_leader_moved_by_hand(
        pair: tuple[FastAPI, httpx.AsyncClient]) -> None:
    app, c = pair
    leader: ArmService = app.state.services["leader"]
    follower: ArmService = app.state.services["follower"]
    here = await held_still(lambda: leader.positions, TOL)
    # the hand takes hold of the leader where it is (torque on: it moves nothing), then the
    # session frees it: its shoulder, elbow and wrist would fall on their own
    r = await c.put(f"{API}/arms/leader/world/hand", json={"wait": True})
    assert r.status_code == 200, r.text
    np.testing.assert_allclose(r.json()["positions"], here, atol=TOL)
    r = await c.post(f"{API}/teleop", json=START)
    assert r.status_code == 201, r.text
    t = r.json()
    assert t["free_leader"] is True
    assert not any(sv.torque for sv in servos(leader)), "the leader's torque is still on"
    await wait_for(lambda: np.allclose(follower.positions, leader.positions, atol=TOL),
                   what="the follower where the leader is")
    np.testing.assert_allclose(await held_still(lambda: leader.positions, TOL), here,
                               atol=TOL)  # held: it did not fall
    r = await c.post(f"{API}/recordings", json={"name": "byhand", "arms": ["follower"],
                                                "fps": 25, "task": "follow the hand"})
    assert r.status_code == 201, r.text
    lsub, fsub = leader.subscribe(4000), follower.subscribe(4000)
    try:
        assert (await c.post(f"{API}/recordings/byhand/episodes")).status_code == 201
        for q in PATH:
            r = await hand(c, "leader", q, speed=SPEED, wait=True)
            assert r.status_code == 200, r.text
            assert r.json() == {"positions": q, "speed": SPEED, "moving": False}
            # the server reads the simulated servos where the hand left them
            await wait_for(lambda q=q: np.allclose(leader.positions, q, atol=TOL),
                           what=f"the leader's samples at {q}")
            await wait_for(lambda q=q: np.allclose(follower.positions, q, atol=TOL),
                           what=f"the follower at {q}")
        there = (await c.get(f"{API}/recordings/byhand")).json()["current"]["frames"]
        await frames_at_least(c, "byhand", there + 3)  # three more frames
        r = await c.post(f"{API}/recordings/byhand/episodes/stop")
        assert r.status_code == 200, r.text
        lsamples = [orjson.loads(x) for x in lsub.take()[0]]
        fq = np.array([orjson.loads(x)["positions"] for x in fsub.take()[0]])
    finally:
        lsub.close()
        fsub.close()
    lq = np.array([smp["positions"] for smp in lsamples])
    # read as hardware is read: the hand's speed in the servos' Present Velocity
    speeds = np.max(np.abs(np.array([smp["velocities"] for smp in lsamples])), axis=1)
    assert 0.5 * SPEED < float(np.max(speeds)) <= SPEED * 1.05
    # the leader went the hand's way, and the follower the leader's: within one period's
    # motion at the hand's speed (and the follower's servos' own lag) of its joint path
    hand_path = np.array([lq[0], *PATH])
    assert float(np.max(path_distance(lq, hand_path))) < 2 * TOL
    bound = SPEED / 50 + 2 * TOL
    off = path_distance(fq, lq)
    assert float(np.max(off)) < bound, f"the follower {np.max(off):.4f} rad off the leader"
    figures = [x for x in (await c.get(f"{API}/teleop")).json() if x["id"] == t["id"]][0]
    assert figures["status"] == "running" and figures["commands"] > 50
    # the recording: the action is the leader's joints (mapped one to one), the state the
    # follower's measured joints
    d = r.json()
    assert d["names"][:4] == [f"follower.{j.name}.pos" for j in follower.profile.joints]
    read = check_dataset(Path(d["path"]))
    action = read.frames["action"][:, :4].astype(float)
    state = read.frames["observation.state"][:, :4].astype(float)
    assert float(np.max(path_distance(action, lq))) < bound
    np.testing.assert_allclose(action[-1], PATH[-1], atol=TOL)
    assert float(np.max(path_distance(state[:-1], np.vstack([state[:1], fq])))) < 1e-5
    np.testing.assert_allclose(state[-1], PATH[-1], atol=TOL)
    # the session ends: the leader's torque on again, holding where the hand left it, and the
    # hand refused from then on
    r = await c.delete(f"{API}/teleop/{t['id']}")
    assert r.status_code == 200, r.text
    await wait_for(lambda: all(sv.torque for sv in servos(leader)), what="the torque on")
    r = await hand(c, "leader", PATH[0])
    assert r.status_code == 409 and r.json()["code"] == "conflict", r.text
    np.testing.assert_allclose(await held_still(lambda: leader.positions, TOL), PATH[-1],
                               atol=2 * TOL)


async def test_a_hand_on_a_device_without_servos_or_a_real_arm() -> None:
    async with running_client(make_settings()) as (app, c):
        r = await hand(c, "rbe3001", [0.0, 0.0, 0.0])
        assert r.status_code == 409 and r.json()["code"] == "not_supported", r.text
        r = await hand(c, "nope", [0.0])
        assert r.status_code == 404 and r.json()["code"] == "unknown_arm", r.text


async def test_a_joint_whose_torque_comes_on_is_let_go(
        pair: tuple[FastAPI, httpx.AsyncClient]) -> None:
    """The session ends mid-move: the leader's torque comes on, its servos hold where they are
    (the hand does not drag them on to its goal) and the move ends."""
    app, c = pair
    leader: ArmService = app.state.services["leader"]
    r = await c.post(f"{API}/teleop", json=START)
    assert r.status_code == 201, r.text
    sid = r.json()["id"]
    start = np.array(leader.positions, dtype=float)
    goal = [0.9, -0.6, 0.5, 0.9]
    r = await hand(c, "leader", goal, speed=0.3)
    assert r.status_code == 200 and r.json()["moving"] is True, r.text
    await wait_for(lambda: np.max(np.abs(leader.positions - start)) > 0.1,
                   what="the hand under way")
    assert (await c.delete(f"{API}/teleop/{sid}")).status_code == 200
    await wait_for(lambda: all(sv.torque for sv in servos(leader)), what="the torque on")
    assert leader.hand is not None
    await wait_for(lambda: not leader.hand.active, what="the hand letting go")
    held = await held_still(lambda: leader.positions, TOL)
    assert np.max(np.abs(held - np.array(goal))) > 0.1, "the hand went on to its goal"


async def test_the_hand_on_the_anglers_prismatic_joints() -> None:
    """A simulated MX-28 bus (the angler: three lead-screw carriages and a revolute joint):
    with its torque off (the facade's set_torque, as a session does), the hand puts the joints
    where asked, metres and radians, and the server reads them there; let go, the winch's
    load goes down."""
    async with running_client(make_settings()) as (app, c):
        angler: ArmService = app.state.services["angler"]
        detail = (await c.get(f"{API}/arms/angler")).json()
        lo = np.array([j["min"] for j in detail["joints"]])
        hi = np.array([j["max"] for j in detail["joints"]])
        goal = (lo + 0.4 * (hi - lo)).tolist()
        await angler.set_torque(False)
        r = await hand(c, "angler", goal, speed=0.05, wait=True)
        assert r.status_code == 200 and r.json()["moving"] is False, r.text
        await wait_for(lambda: np.allclose(angler.positions, goal, atol=1e-3),
                       what="the angler's samples where the hand put it")
        # the client's hand lets go: the z winch's load goes down to its lower limit, the
        # carriages and theta3 stay where the hand left them; taking hold again (no
        # positions) holds it where it is, and on again it holds itself
        async with AsyncArmClient("http://armserver.test",
                                  transport=httpx.ASGITransport(app=app)) as client:
            await client.let_go_hand("angler")
            z = angler.profile.joint_names.index("z")
            down = [*goal[:z], float(lo[z]), *goal[z + 1:]]
            await wait_for(lambda: np.allclose(angler.positions, down, atol=1e-3),
                           what="the angler's load down, the rest where the hand left it")
            held = await client.move_hand("angler", wait=True)
        np.testing.assert_allclose(held.positions, down, atol=1e-3)
        await angler.set_torque(True)
        r = await hand(c, "angler", (lo + 0.5 * (hi - lo)).tolist())
        assert r.status_code == 409 and r.json()["code"] == "conflict", r.text


async def test_the_hand_is_the_lease_holders_or_an_instructors() -> None:
    """With tokens: a viewer may not move an arm by hand (403); while one operator holds the
    leader's lease another's hand is refused (409 `leased`), the holder's is let through to the
    torque check, and an instructor's too; the Python client's move_hand sends the lease."""
    settings = make_settings(config=str(CONFIG), operator_tokens="op-a, op-b",
                             instructor_tokens="teach", viewer_tokens="look")
    async with running_client(settings) as (app, c):
        def auth(token: str, lease: str | None = None) -> dict[str, str]:
            h = {"Authorization": f"Bearer {token}"}
            return {**h, "X-Arm-Lease": lease} if lease else h

        r = await c.put(f"{API}/arms/leader/world/hand", json={"positions": PATH[0]},
                        headers=auth("look"))
        assert r.status_code == 403 and r.json()["code"] == "forbidden", r.text
        r = await c.post(f"{API}/arms/leader/lease", headers=auth("op-a"))
        assert r.status_code in (200, 201), r.text
        lease = r.json()["id"]
        r = await c.put(f"{API}/arms/leader/world/hand", json={"positions": PATH[0]},
                        headers=auth("op-b"))
        assert r.status_code == 409 and r.json()["code"] == "leased", r.text
        for headers in (auth("op-a", lease), auth("teach")):  # through, to the torque check
            r = await c.put(f"{API}/arms/leader/world/hand", json={"positions": PATH[0]},
                            headers=headers)
            assert r.status_code == 409 and r.json()["code"] == "conflict", r.text
        leader: ArmService = app.state.services["leader"]
        await leader.set_torque(False)
        transport = httpx.ASGITransport(app=app)
        async with AsyncArmClient("http://armserver.test", token="op-a",
                                  transport=transport) as client:
            client.leases["leader"] = lease
            done = await client.move_hand("leader", PATH[0], speed=1.0, wait=True)
        assert done.moving is False and done.positions == PATH[0]
        await wait_for(lambda: np.allclose(leader.positions, PATH[0], atol=TOL),
                       what="the leader where the client's hand put it")
        await leader.set_torque(True)


async def test_a_freed_leader_let_go_falls_and_the_follower_follows_the_fall(
        pair: tuple[FastAPI, httpx.AsyncClient]) -> None:
    """Held, freed, let go (DELETE .../world/hand): the leader's shoulder, elbow and wrist
    fall on the simulated bus (its torque off, nothing holding it), the server reads the
    fall as it reads hardware, with the servos' own Present Velocity, the waist (turning
    about the vertical) stays, and the follower follows to where the leader came to rest."""
    app, c = pair
    leader: ArmService = app.state.services["leader"]
    follower: ArmService = app.state.services["follower"]
    here = np.asarray(await held_still(lambda: leader.positions, TOL))
    assert (await c.put(f"{API}/arms/leader/world/hand", json={})).status_code == 200
    r = await c.post(f"{API}/teleop", json=START)
    assert r.status_code == 201, r.text
    sub = leader.subscribe(4000)
    try:
        r = await c.delete(f"{API}/arms/leader/world/hand")
        assert r.status_code == 204, r.text
        rest = np.asarray(await held_still(lambda: leader.positions, TOL, window=0.3))
        samples = [orjson.loads(x) for x in sub.take()[0]]
    finally:
        sub.close()
    fell = rest - here
    assert abs(fell[0]) <= TOL, fell  # the waist
    # the shoulder came down forward onto its stop; the elbow and the wrist swung on the way
    np.testing.assert_allclose(rest[1], leader.model.upper[1], atol=TOL)
    swing = np.max(np.abs([smp["velocities"] for smp in samples]), axis=0)
    assert swing[0] == 0.0 and np.all(swing[1:] > 0.1), swing
    # lower: the summed height of the arm's body points (the model's own kinematics)
    def height(q: np.ndarray) -> float:
        return float(np.sum(np.asarray(leader.model.joint_origins(q))[1:, 2]))

    assert height(rest) < height(here) - 0.01
    # (the pair's clamp_margin, 0.05 rad in config/teleop_omx.toml, keeps the follower that
    # far inside its limits: its shoulder stops short of the stop the leader fell onto)
    m = follower.model
    want = np.clip(rest, np.asarray(m.lower) + 0.05, np.asarray(m.upper) - 0.05)
    await wait_for(lambda: np.allclose(follower.positions, want, atol=TOL),
                   what="the follower where the leader fell")
    assert (await c.delete(f"{API}/arms/leader/world/hand")).status_code == 204  # (again: 204)
    # taken hold of again where it fell: its shoulder on its stop reads half a tick beyond
    # the limit (3,072 ticks), and the hand holds it there all the same
    r = await c.put(f"{API}/arms/leader/world/hand", json={"wait": True})
    assert r.status_code == 200, r.text
    np.testing.assert_allclose(r.json()["positions"], rest, atol=TOL)
