"""A real leader (not simulated: a serial link, here `socket://` to a simulated
OpenManipulator-X bus, the bytes a U2D2 would carry) is moved by hand: the session switches
its servos' torque off (`ArmService.set_torque`), the follower follows where the hand puts
it, and when the session ends the leader's torque is on again with each goal at its present
position, so it holds where the hand left it. An arm whose device cannot switch its torque off
(the rbe3001) is refused as a real leader."""

from __future__ import annotations

from collections.abc import AsyncIterator
from typing import Any

import httpx
import numpy as np
import pytest
from _wait import held_still, wait_for
from fastapi import FastAPI

from app.arms import arm_type
from app.arms.loading import load_profile
from app.config import ArmProfile
from app.service import ArmService
from app.sim.servers import TcpServer, serve_tcp
from tests.conftest import make_settings, running_client

API = "/api/v1"
TOL = 8 * 2 * np.pi / 4096
START = {"leader": "leader", "follower": "follower", "rate_hz": 50, "load_supported": True}


def named(profile: ArmProfile, name: str, **link: Any) -> ArmProfile:
    return profile.model_copy(update={"name": name,
                                      "link": profile.link.model_copy(update=link)})


@pytest.fixture()
async def real_leader() -> AsyncIterator[tuple[FastAPI, httpx.AsyncClient, Any]]:
    omx = load_profile("openmanipulator_x")
    bus = arm_type("openmanipulator_x").simulator(omx)
    srv: TcpServer = await serve_tcp(bus)
    try:
        leader = named(omx, "leader", kind="serial",
                       address=f"socket://127.0.0.1:{srv.port}")
        follower = named(omx, "follower")
        async with running_client(make_settings(), profiles=[leader, follower]) as (app, c):
            yield app, c, bus
    finally:
        await srv.close()


def joint_servos(bus: Any, arm: ArmService) -> list[Any]:
    ids = [j.motor_id for j in arm.profile.joints]
    return [next(sv for sv in bus.servos if sv.id == i) for i in ids]


async def test_a_real_leader_is_moved_by_hand(
        real_leader: tuple[FastAPI, httpx.AsyncClient, Any]) -> None:
    app, c, bus = real_leader
    leader: ArmService = app.state.services["leader"]
    follower: ArmService = app.state.services["follower"]
    servos = joint_servos(bus, leader)
    assert leader.link_status().kind == "serial" and all(sv.torque for sv in servos)
    # its shoulder, elbow and wrist fall without torque: freed only when said to be held
    unsaid = {k: v for k, v in START.items() if k != "load_supported"}
    for body in (unsaid, {**unsaid, "load_supported": False}):
        r = await c.post(f"{API}/teleop", json=body)
        assert r.status_code == 409 and r.json()["code"] == "in_use", r.text
        assert "shoulder, elbow, wrist fall without torque" in r.json()["detail"]
    assert all(sv.torque for sv in servos), "a refused session switched the leader's torque"
    assert (await c.get(f"{API}/teleop")).json() == []
    r = await c.post(f"{API}/teleop", json=START)
    assert r.status_code == 201, r.text
    sid = r.json()["id"]
    assert not any(sv.torque for sv in servos), "the leader's torque is still on"
    # the hand: each servo put at the pose, and held there (torque off, its shoulder, elbow
    # and wrist would fall on the simulated bus as on an arm: app/arms/dynamixel/sim_gravity.py)
    bus.gravity.held = True
    hand = np.array([0.4, -0.3, 0.2, 0.5])
    for sv, ticks in zip(servos, leader.model.transmission.to_ticks(hand), strict=True):
        sv.pos = float(ticks)
    await wait_for(lambda: np.allclose(leader.positions, hand, atol=TOL),
                   what="the leader's samples where the hand put it")
    await wait_for(lambda: np.allclose(follower.positions, hand, atol=TOL),
                   what="the follower where the hand put the leader")
    r = await c.delete(f"{API}/teleop/{sid}")
    assert r.status_code == 200, r.text
    # torque on again (the simulated bus takes the bytes on its own loop), each goal at its
    # present position: the leader holds where it is
    await wait_for(lambda: all(sv.torque for sv in servos), what="the leader's torque on")
    assert [sv.get("goal_position") for sv in servos] == [
        sv.get("present_position") for sv in servos]
    np.testing.assert_allclose(await held_still(lambda: leader.positions, TOL), hand, atol=TOL)


async def test_a_real_leader_held_by_a_lease_needs_that_lease(
        real_leader: tuple[FastAPI, httpx.AsyncClient, Any]) -> None:
    """Switching a real leader's torque off makes it limp: a command to it. While its lease is
    held, a session needs that lease (X-Leader-Lease) as a move would, and a refusal leaves
    its torque on."""
    app, c, bus = real_leader
    leader: ArmService = app.state.services["leader"]
    servos = joint_servos(bus, leader)
    r = await c.post(f"{API}/arms/leader/lease")
    assert r.status_code in (200, 201), r.text
    lease = r.json()["id"]
    r = await c.post(f"{API}/teleop", json=START)
    assert r.status_code == 409 and r.json()["code"] == "leased", r.text
    r = await c.post(f"{API}/teleop", json=START, headers={"X-Leader-Lease": "not-it"})
    assert r.status_code == 409 and r.json()["code"] == "leased", r.text
    assert all(sv.torque for sv in servos), "a refused session switched the leader's torque"
    assert (await c.get(f"{API}/teleop")).json() == []
    r = await c.post(f"{API}/teleop", json=START, headers={"X-Leader-Lease": lease})
    assert r.status_code == 201, r.text
    assert not any(sv.torque for sv in servos)
    assert (await c.delete(f"{API}/teleop/{r.json()['id']}")).status_code == 200
    await wait_for(lambda: all(sv.torque for sv in servos), what="the leader's torque on")


async def test_estop_on_a_real_leader_gives_it_its_torque_back(
        real_leader: tuple[FastAPI, httpx.AsyncClient, Any]) -> None:
    app, c, bus = real_leader
    leader: ArmService = app.state.services["leader"]
    servos = joint_servos(bus, leader)
    r = await c.post(f"{API}/teleop", json=START)
    assert r.status_code == 201, r.text
    sid = r.json()["id"]
    assert not any(sv.torque for sv in servos)
    assert (await c.post(f"{API}/arms/leader/estop")).status_code == 200

    async def ended() -> bool:
        t = [x for x in (await c.get(f"{API}/teleop")).json() if x["id"] == sid][0]
        return bool(t["status"] == "ended")
    await wait_for(ended, what="the session ended by the leader's estop")
    await wait_for(lambda: all(sv.torque for sv in servos), what="the leader's torque on")
    assert (await c.delete(f"{API}/arms/leader/estop")).status_code == 200


async def test_a_real_leader_that_cannot_free_its_joints_is_refused() -> None:
    rbe = load_profile("rbe3001")
    arm = arm_type("rbe3001")
    srv = await serve_tcp(arm.simulator(rbe))
    try:
        leader = named(rbe, "leader", kind="serial", address=f"socket://127.0.0.1:{srv.port}")
        follower = named(load_profile("openmanipulator_x"), "follower")
        async with running_client(make_settings(), profiles=[leader, follower]) as (app, c):
            r = await c.post(f"{API}/teleop", json={**START, "mapping": "tip"})
            assert r.status_code == 409 and r.json()["code"] == "not_supported", r.text
            assert (await c.get(f"{API}/teleop")).json() == []
    finally:
        await srv.close()
