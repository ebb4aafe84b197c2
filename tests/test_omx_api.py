"""A server config with all three arm types side by side (the rbe3001, the angler and the
OpenManipulator-X, each on its simulator), through the HTTP API: the listing, moves on each,
the OMX's joint and straight-line moves with pitch, its gripper, its pass-through, and the
422s of an unreachable pose or pitch."""

from __future__ import annotations

import asyncio
import math
from collections.abc import AsyncIterator
from pathlib import Path

import httpx
import numpy as np
import pytest
from _wait import fresh_state
from fastapi import FastAPI

from app.schemas import Motion, Sample
from kinematics import omx
from tests.conftest import make_settings, running_client

API = "/api/v1"
OMX = f"{API}/arms/omx"
JOINT_TOL = 8 * 2 * math.pi / 4096  # rad: the default settle tolerance, 8 encoder ticks

#: The README's example: the three arm types, each simulated.
CONFIG = Path(__file__).resolve().parents[1] / "config" / "three-arms.example.toml"


@pytest.fixture()
async def three() -> AsyncIterator[tuple[FastAPI, httpx.AsyncClient]]:
    async with running_client(make_settings(config=str(CONFIG))) as pair:
        yield pair


async def _state(client: httpx.AsyncClient, arm: str = "omx") -> Sample:
    """A sample taken after the call (after the motion the caller waited for ended)."""
    return Sample.model_validate(await fresh_state(client, arm))


async def test_three_arm_types_serve_side_by_side(
        three: tuple[FastAPI, httpx.AsyncClient]) -> None:
    _, c = three
    arms = (await c.get(f"{API}/arms")).json()
    assert [(a["name"], a["model"]) for a in arms] == [
        ("rbe3001", "rbe3001"), ("angler", "angler"), ("omx", "openmanipulator_x")]
    detail = (await c.get(OMX)).json()
    assert detail["capabilities"]["pitch"] is True
    assert detail["capabilities"]["gripper"] is True
    assert detail["capabilities"]["protocol"] == "dynamixel"
    assert detail["chain"]["points"] == list(omx.POINTS)
    assert [j["name"] for j in detail["joints"]] == ["waist", "shoulder", "elbow", "wrist"]
    # a move on each arm, at the same time
    moves = {"rbe3001": [0.2, 0.3, 0.2], "omx": [0.3, -0.4, 0.3, 0.5]}
    ang = (await c.get(f"{API}/arms/angler")).json()["joints"]
    moves["angler"] = [(j["min"] + j["max"]) / 2 for j in ang]
    rs = await asyncio.gather(*(c.post(f"{API}/arms/{arm}/move/joints",
                                       json={"positions": q, "wait": True})
                                for arm, q in moves.items()))
    for r in rs:
        assert r.status_code == 200 and r.json()["status"] == "done", r.text
    s = await _state(c)
    assert np.allclose(s.positions, moves["omx"], atol=JOINT_TOL), s.positions


async def test_joint_move_reports_tip_and_pitch(three: tuple[FastAPI, httpx.AsyncClient]) -> None:
    _, c = three
    q = [-0.5, 0.2, -0.3, 0.6]
    r = await c.post(f"{OMX}/move/joints", json={"positions": q, "wait": True})
    assert r.status_code == 200, r.text
    m = Motion.model_validate(r.json())
    assert m.status == "done"
    s = await _state(c)
    want = omx.fk(s.positions)
    assert s.tip.pitch is not None
    assert [s.tip.x, s.tip.y, s.tip.z, s.tip.pitch] == pytest.approx(want.tolist(), abs=1e-9)
    assert s.tip.pitch == pytest.approx(-(0.2 - 0.3 + 0.6), abs=JOINT_TOL)
    # the forward kinematics route gives the pitch and the 4x4 Jacobian
    r = await c.post(f"{OMX}/kinematics/forward", json={"positions": q})
    body = r.json()
    assert body["tip"]["pitch"] == pytest.approx(-0.5, abs=1e-12)
    assert np.allclose(body["jacobian"], omx.jacobian(q), atol=1e-12)


async def test_line_move_with_pitch_ends_done_within_tolerance(
        three: tuple[FastAPI, httpx.AsyncClient]) -> None:
    _, c = three
    target = {"x": 0.22, "y": 0.06, "z": 0.12, "pitch": -0.7}
    r = await c.post(f"{OMX}/move/pose", json={**target, "path": "line", "wait": True})
    assert r.status_code == 200, r.text
    m = Motion.model_validate(r.json())
    assert m.status == "done" and m.path == "line", m
    # the motion reports its tips with the pitch too (API.md "Wrist pitch")
    assert m.target_tip.pitch == pytest.approx(-0.7, abs=1e-6)
    assert m.final_tip is not None and m.final_tip.pitch == pytest.approx(-0.7, abs=0.03)
    s = await _state(c)
    assert [s.tip.x, s.tip.y, s.tip.z] == pytest.approx([0.22, 0.06, 0.12], abs=0.004)
    assert s.tip.pitch == pytest.approx(-0.7, abs=0.03)
    # a joint-path pose move without a pitch: the arm chooses one, the tip still arrives
    r = await c.post(f"{OMX}/move/pose", json={"x": 0.18, "y": -0.08, "z": 0.2, "wait": True})
    assert r.status_code == 200 and r.json()["status"] == "done", r.text
    s = await _state(c)
    assert [s.tip.x, s.tip.y, s.tip.z] == pytest.approx([0.18, -0.08, 0.2], abs=0.004)


async def test_inverse_kinematics_route_with_pitch(
        three: tuple[FastAPI, httpx.AsyncClient]) -> None:
    _, c = three
    q = np.array([0.4, -0.6, 0.5, 0.3])
    x, y, z, pitch = omx.fk(q).tolist()
    r = await c.post(f"{OMX}/kinematics/inverse", json={"x": x, "y": y, "z": z, "pitch": pitch})
    assert r.status_code == 200, r.text
    sols = r.json()["solutions"]
    assert any(np.allclose(s["positions"], q, atol=1e-7) for s in sols)
    for s in sols:
        assert np.allclose(omx.fk(s["positions"]), [x, y, z, pitch], atol=1e-9)


async def test_unreachable_pose_or_pitch_is_422_and_nothing_moves(
        three: tuple[FastAPI, httpx.AsyncClient]) -> None:
    _, c = three
    before = (await _state(c)).positions
    for body in ({"x": 0.6, "y": 0.0, "z": 0.1},              # beyond the reach
                 {"x": 0.38, "y": 0.0, "z": 0.08, "pitch": 1.5}):  # not at that pitch
        r = await c.post(f"{OMX}/move/pose", json=body)
        assert r.status_code == 422 and r.json()["code"] == "unreachable", r.text
        r = await c.post(f"{OMX}/kinematics/inverse", json=body)
        assert r.status_code == 422 and r.json()["code"] == "unreachable", r.text
    # a pitch given to an arm without a wrist
    r = await c.post(f"{API}/arms/rbe3001/move/pose",
                     json={"x": 0.2, "y": 0.0, "z": 0.15, "pitch": 0.1})
    assert r.status_code == 422 and r.json()["code"] == "unreachable", r.text
    assert np.allclose((await _state(c)).positions, before, atol=1e-9)


async def test_gripper_route_moves_the_gripper_servo(
        three: tuple[FastAPI, httpx.AsyncClient]) -> None:
    app, c = three
    bus = app.state.services["omx"].driver.link.device
    r = await c.post(f"{OMX}/gripper", json={"value": 1.0})
    assert r.status_code == 200 and r.json()["value"] == 1.0, r.text
    assert bus.servo(15).get("goal_position") == 2483  # -0.010 m: +0.667 rad
    for _ in range(200):
        s = await _state(c)
        if s.gripper is not None and abs(s.gripper - 1.0) < 0.01:
            break
    assert s.gripper == pytest.approx(1.0, abs=0.01)
    r = await c.post(f"{OMX}/gripper", json={"value": 1.5})
    assert r.status_code == 422
    assert bus.servo(15).get("goal_position") == 2483


async def test_passthrough_ping_and_register_read(
        three: tuple[FastAPI, httpx.AsyncClient]) -> None:
    _, c = three
    r = await c.post(f"{OMX}/dynamixel/ping", json={"id": 11})
    assert r.status_code == 200, r.text
    assert r.json()["devices"] == [{"id": 11, "model_number": 1020, "firmware_version": 46}]
    r = await c.get(f"{OMX}/dynamixel/15/registers/operating_mode")
    assert r.status_code == 200 and r.json()["raw"] == 5, r.text
    r = await c.get(f"{OMX}/dynamixel/12/registers/present_position")
    body = r.json()
    assert r.status_code == 200 and body["unit"] == "deg"
    s = await _state(c)
    assert body["raw"] == pytest.approx(2048 + s.positions[1] * 4096 / (2 * math.pi), abs=3)
    r = await c.get(f"{OMX}/dynamixel/12/registers/no_such_item")
    assert r.status_code == 422 and r.json()["code"] == "unknown_register"
    # the XM430's table, not the MX-28's: Present Current at 126, no Present Load
    r = await c.get(f"{OMX}/dynamixel/12/registers/present_current")
    assert r.status_code == 200 and r.json()["address"] == 126 and r.json()["unit"] == "mA"
    r = await c.get(f"{OMX}/dynamixel/12/registers/present_load")
    assert r.status_code == 422 and r.json()["code"] == "unknown_register"
    r = await c.get(f"{API}/arms/angler/dynamixel/1/registers/present_load")
    assert r.status_code == 200 and r.json()["address"] == 126


async def test_passthrough_protects_the_gripper_servo_settings(
        three: tuple[FastAPI, httpx.AsyncClient]) -> None:
    """The gripper's servo is the arm's own: its operating mode (current-based position, which
    the gripper needs) is the driver's, as the joints' are (409 `in_use`, nothing written)."""
    app, c = three
    bus = app.state.services["omx"].driver.link.device
    r = await c.put(f"{OMX}/dynamixel/15/registers/operating_mode", json={"raw": 3})
    assert r.status_code == 409 and r.json()["code"] == "in_use", r.text
    assert bus.servo(15).get("operating_mode") == 5
    r = await c.put(f"{OMX}/dynamixel/15/registers/led", json={"raw": 1})
    assert r.status_code == 200 and bus.servo(15).get("led") == 1


async def test_the_joints_that_fold_under_the_arm_keep_their_torque(
        three: tuple[FastAPI, httpx.AsyncClient]) -> None:
    """Shoulder, elbow and wrist fall without torque (the profile's `falls_without_torque`):
    torque off to their servos is 409 `in_use`, nothing written; the waist's and the gripper's
    go off as before."""
    app, c = three
    bus = app.state.services["omx"].driver.link.device
    for dxl_id, joint in ((12, "shoulder"), (13, "elbow"), (14, "wrist")):
        r = await c.put(f"{OMX}/dynamixel/{dxl_id}/registers/torque_enable", json={"raw": 0})
        assert r.status_code == 409 and r.json()["code"] == "in_use", r.text
        assert f"let {joint} fall" in r.json()["detail"] and bus.servo(dxl_id).torque
    for dxl_id in (11, 15):
        r = await c.put(f"{OMX}/dynamixel/{dxl_id}/registers/torque_enable", json={"raw": 0})
        assert r.status_code == 200 and not bus.servo(dxl_id).torque, r.text


async def test_a_servo_fault_refuses_moves_until_its_reboot(
        three: tuple[FastAPI, httpx.AsyncClient]) -> None:
    app, c = three
    svc = app.state.services["omx"]
    svc.driver.link.device.inject_hardware_error(13, "overheating")  # the elbow's servo
    for _ in range(250):
        if svc.driver.faults:
            break
        await asyncio.sleep(0.02)
    detail = (await c.get(OMX)).json()
    assert [(f["servo"], f["joint"], f["bits"]) for f in detail["faults"]] == [
        (13, "elbow", ["overheating"])]
    r = await c.post(f"{OMX}/move/joints", json={"positions": [0.1, 0.0, 0.0, 0.0]})
    assert r.status_code == 409 and r.json()["code"] == "fault"
    assert "/dynamixel/13/reboot" in r.json()["detail"]
    r = await c.post(f"{OMX}/dynamixel/13/reboot")
    assert r.status_code == 200, r.text
    for _ in range(250):
        if not svc.driver.faults:
            break
        await asyncio.sleep(0.02)
    detail = (await c.get(OMX)).json()
    assert detail["faults"] == [] and detail["homed"] == [True] * 4  # absolute encoders
    r = await c.post(f"{OMX}/move/joints", json={"positions": [0.1, 0.0, 0.0, 0.0], "wait": True})
    assert r.status_code == 200 and r.json()["status"] == "done", r.text
