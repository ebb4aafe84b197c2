"""The angler as documented: the design's IK cases and automatic choice, its motor wiring
(MATLAB: ID 1 from -y, ID 2 from -x, ID 3 theta3, ID 4 z) and speeds an MX-28 can reach."""

from __future__ import annotations

import httpx
import numpy as np
import pytest
from _wait import wait_for
from fastapi import FastAPI

from app.arms.loading import load_profile
from protocol import mx28

API = "/api/v1/arms/angler"
PROFILE = load_profile("angler")


def test_profile_wiring_is_the_design_matlab() -> None:
    wiring = {j.name: (j.motor_id, j.sign) for j in PROFILE.joints}
    assert wiring == {"x": (2, -1), "y": (1, -1), "theta3": (3, 1), "z": (4, 1)}
    # theta3 too (issue 24): 0 at tick 0 as the MATLAB, in extended position mode, whose
    # count restarts within one turn at power-up
    assert [j.name for j in PROFILE.joints if j.needs_homing] == ["x", "y", "theta3", "z"]
    assert [j.name for j in PROFILE.joints if not j.zero_known] == ["theta3"]


def test_joint_speeds_are_within_what_an_mx28_turns() -> None:
    rpm_12v = mx28.no_load_rpm(12.0)  # 55 rpm, e-manual
    for j in PROFILE.joints:
        per_rev = j.lead_m if j.lead_m else 2 * np.pi
        rpm = j.max_velocity / per_rev * 60.0
        assert rpm * 1.2 <= rpm_12v, f"{j.name} asks {rpm:.0f} rpm (+20 % headroom)"
    assert PROFILE.cartesian.max_velocity <= min(j.max_velocity for j in PROFILE.joints[:2])


async def test_a_move_in_x_turns_servo_2_backwards_and_leaves_servo_1(
        app_and_client: tuple[FastAPI, httpx.AsyncClient]) -> None:
    app, c = app_and_client
    bus = app.state.services["angler"].driver.link.device
    q = app.state.services["angler"].driver.positions.copy()
    before = {s.id: s.get("present_position") for s in bus.servos}
    q[0] += 0.002
    r = await c.post(f"{API}/move/joints", json={"positions": q.tolist(), "wait": True})
    assert r.status_code == 200 and r.json()["status"] == "done", r.text
    after = {s.id: s.get("present_position") for s in bus.servos}
    # x + 2 mm on an 8 mm lead = a quarter turn of ID 2, negated: -1024 ticks
    assert after[2] - before[2] == pytest.approx(-1024, abs=3)
    assert after[1] == pytest.approx(before[1], abs=3)


async def test_the_documented_point_is_reached_in_case_two(
        app_and_client: tuple[FastAPI, httpx.AsyncClient]) -> None:
    app, c = app_and_client
    p = {"x": 0.12, "y": 0.04, "z": -0.02}
    r = await c.post(f"{API}/kinematics/inverse", json=p)
    assert r.status_code == 200, r.text
    sols = r.json()["solutions"]
    assert len(sols) == 1 and sols[0]["positions"][2] == pytest.approx(-np.pi / 2)
    # no case named: the server chooses the design's (|px| > r: case two)
    r = await c.post(f"{API}/move/pose", json={**p, "wait": True})
    assert r.status_code == 200 and r.json()["status"] == "done", r.text
    hub = app.state.services["angler"].hub

    def at_the_point() -> bool:
        tip = hub.latest["tip"]
        assert [tip["x"], tip["y"], tip["z"]] == pytest.approx([0.12, 0.04, -0.02], abs=2e-4)
        return True

    await wait_for(at_the_point, what="the measured tip at the documented point")


async def test_the_ik_route_lists_every_solution_without_a_case(
        app_client: httpx.AsyncClient) -> None:
    r = await app_client.post(f"{API}/kinematics/inverse",
                              json={"x": 0.03, "y": 0.05, "z": 0.01})
    assert r.status_code == 200, r.text
    sols = [s["positions"] for s in r.json()["solutions"]]
    assert len(sols) == 3
    assert sols[0][0] == 0.0 and sols[1][0] == 0.0  # dx = 0, the design's choice here
    assert sols[2][2] == pytest.approx(-np.pi / 2)
