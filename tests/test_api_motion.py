"""Moves, plans, motion status and cancel, stop, emergency stop and gripper, through the API
over the simulated arms (the motion executor and drivers are the real ones)."""

from __future__ import annotations

import asyncio
import time

import httpx
import numpy as np
from fastapi import FastAPI

from app.schemas import Motion, Sample

API = "/api/v1"
JOINT_TOL = 0.02  # rad
PRISMATIC_TOL = 0.002  # m


async def _state(client: httpx.AsyncClient, arm: str) -> Sample:
    r = await client.get(f"{API}/arms/{arm}/state")
    assert r.status_code == 200
    return Sample.model_validate(r.json())


async def _settled_state(client: httpx.AsyncClient, arm: str) -> Sample:
    """A sample published after this call (so after the motion that was answered ended):
    waited for, bounded, not slept for."""
    first = await _state(client, arm)
    deadline = time.monotonic() + 5.0
    while True:
        s = await _state(client, arm)
        if s.seq > first.seq:
            return s
        assert time.monotonic() < deadline, f"no new {arm} sample in 5 s after seq {first.seq}"
        await asyncio.sleep(0.005)


async def test_move_joints_wait_ends_done_at_the_target(app_client: httpx.AsyncClient) -> None:
    target = [0.3, 0.6, 0.4]
    r = await app_client.post(f"{API}/arms/rbe3001/move/joints",
                              json={"positions": target, "wait": True})
    assert r.status_code == 200, r.text
    m = Motion.model_validate(r.json())
    assert m.status == "done" and m.progress == 1.0 and m.kind == "joints"
    assert m.target_positions == target
    s = await _settled_state(app_client, "rbe3001")
    assert np.allclose(s.positions, target, atol=JOINT_TOL), s.positions
    assert s.motion is not None and s.motion.id == m.id


async def test_move_joints_angler_mixed_units(app_client: httpx.AsyncClient) -> None:
    detail = (await app_client.get(f"{API}/arms/angler")).json()
    target = [(j["min"] + j["max"]) / 2 + 0.1 * (j["max"] - j["min"]) for j in detail["joints"]]
    r = await app_client.post(f"{API}/arms/angler/move/joints",
                              json={"positions": target, "wait": True})
    assert r.status_code == 200, r.text
    assert r.json()["status"] == "done"
    s = await _settled_state(app_client, "angler")
    for j, want, got in zip(detail["joints"], target, s.positions, strict=True):
        tol = PRISMATIC_TOL if j["kind"] == "prismatic" else JOINT_TOL
        assert abs(want - got) <= tol, (j["name"], want, got)


async def test_move_without_wait_is_202_then_queryable(app_client: httpx.AsyncClient) -> None:
    r = await app_client.post(f"{API}/arms/rbe3001/move/joints",
                              json={"positions": [-0.4, 0.5, 0.5], "duration": 1.0})
    assert r.status_code == 202
    m = Motion.model_validate(r.json())
    assert m.status in ("queued", "running") and m.planned_duration >= 1.0 - 1e-9
    r = await app_client.get(f"{API}/arms/rbe3001/motions/{m.id}")
    assert r.status_code == 200 and r.json()["id"] == m.id
    r = await app_client.delete(f"{API}/arms/rbe3001/motions/{m.id}")
    assert r.status_code == 200
    assert r.json()["status"] in ("stopped", "done")
    r = await app_client.get(f"{API}/arms/rbe3001/motions/no-such-id")
    assert r.status_code == 404 and r.json()["code"] == "unknown_motion"


async def test_move_pose_reaches_the_tip(app_client: httpx.AsyncClient) -> None:
    target = {"x": 0.2, "y": 0.05, "z": 0.15}
    r = await app_client.post(f"{API}/arms/rbe3001/move/pose",
                              json={**target, "path": "line", "wait": True})
    assert r.status_code == 200, r.text
    m = Motion.model_validate(r.json())
    assert m.status == "done" and m.path == "line" and m.kind == "pose"
    s = await _settled_state(app_client, "rbe3001")
    assert np.allclose([s.tip.x, s.tip.y, s.tip.z], [0.2, 0.05, 0.15], atol=0.004)


async def test_refusals_are_422_with_reasons(app_client: httpx.AsyncClient) -> None:
    r = await app_client.post(f"{API}/arms/rbe3001/move/joints", json={"positions": [0, 3.0, 0]})
    assert r.status_code == 422 and r.json()["code"] == "joint_limit"
    assert "shoulder" in r.json()["detail"]
    r = await app_client.post(f"{API}/arms/rbe3001/move/pose", json={"x": 2, "y": 0, "z": 0})
    assert r.status_code == 422 and r.json()["code"] == "unreachable"
    r = await app_client.post(f"{API}/arms/rbe3001/move/joints", json={"positions": [0, 0]})
    assert r.status_code == 422 and r.json()["code"] == "invalid_request"


async def test_plan_previews_without_moving(app_client: httpx.AsyncClient) -> None:
    before = await _state(app_client, "rbe3001")
    r = await app_client.post(f"{API}/arms/rbe3001/plan/pose",
                              json={"x": 0.2, "y": 0.0, "z": 0.15, "path": "line"})
    assert r.status_code == 200, r.text
    m = Motion.model_validate(r.json())
    assert m.status == "queued" and 2 <= len(m.planned_path) <= 50
    end = m.planned_path[-1]
    assert abs(end.x - 0.2) < 1e-3 and abs(end.z - 0.15) < 1e-3
    r = await app_client.post(f"{API}/arms/rbe3001/plan/joints",
                              json={"positions": [0.1, 0.5, 0.3]})
    assert r.status_code == 200 and r.json()["planned_duration"] > 0
    await asyncio.sleep(0.2)
    after = await _state(app_client, "rbe3001")
    assert np.allclose(after.positions, before.positions, atol=0.01)
    assert after.motion is None or after.motion.id != m.id


async def test_estop_latches_and_refuses_moves(app_client: httpx.AsyncClient) -> None:
    r = await app_client.post(f"{API}/arms/rbe3001/move/joints",
                              json={"positions": [0.8, 0.8, 0.8], "duration": 3.0})
    assert r.status_code == 202
    mid = r.json()["id"]
    await asyncio.sleep(0.2)
    r = await app_client.post(f"{API}/arms/rbe3001/estop")
    assert r.status_code == 200 and r.json() == {"estop": True}
    assert (await app_client.get(f"{API}/arms/rbe3001/motions/{mid}")).json()["status"] == "stopped"
    assert (await app_client.get(f"{API}/arms/rbe3001")).json()["estop"] is True
    for path, body in [("move/joints", {"positions": [0, 0.5, 0.3]}),
                       ("move/pose", {"x": 0.2, "y": 0, "z": 0.15}),
                       ("gripper", {"value": 0.5}), ("rbe3001/set-claw", {"value": 0.5})]:
        r = await app_client.post(f"{API}/arms/rbe3001/{path}", json=body)
        assert r.status_code == 409 and r.json()["code"] == "estop_latched", path
    s = await _settled_state(app_client, "rbe3001")
    assert s.estop is True
    r = await app_client.delete(f"{API}/arms/rbe3001/estop")
    assert r.status_code == 200 and r.json() == {"estop": False}
    r = await app_client.post(f"{API}/arms/rbe3001/move/joints",
                              json={"positions": [0, 0.5, 0.3], "wait": True})
    assert r.status_code == 200 and r.json()["status"] == "done"


async def test_stop_clears_the_queue(app_client: httpx.AsyncClient) -> None:
    ids = []
    for q in ([0.5, 0.5, 0.5], [-0.5, 0.6, 0.4], [0.2, 0.7, 0.2]):
        r = await app_client.post(f"{API}/arms/rbe3001/move/joints",
                                  json={"positions": q, "duration": 2.0})
        assert r.status_code == 202
        ids.append(r.json()["id"])
    await asyncio.sleep(0.1)
    r = await app_client.post(f"{API}/arms/rbe3001/stop")
    assert r.status_code == 200
    assert set(r.json()["stopped"]) == set(ids) and r.json()["estop"] is False
    for mid in ids:
        r = await app_client.get(f"{API}/arms/rbe3001/motions/{mid}")
        assert r.json()["status"] == "stopped"


async def test_gripper(app_and_client: tuple[FastAPI, httpx.AsyncClient]) -> None:
    app, client = app_and_client
    r = await client.post(f"{API}/arms/rbe3001/gripper", json={"value": 0.75})
    assert r.status_code == 200 and r.json() == {"value": 0.75}
    assert app.state.services["rbe3001"].driver.gripper == 0.75
    s = await _settled_state(client, "rbe3001")
    assert s.gripper == 0.75
    r = await client.post(f"{API}/arms/angler/gripper", json={"value": 0.5})
    assert r.status_code == 409 and r.json()["code"] == "no_gripper"
