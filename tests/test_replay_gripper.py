"""A recorded OpenManipulator-X episode with the gripper closed and opened during it replays
with the gripper following (issue 26): each frame's gripper action is sent through the arm's
facade as the replay reaches the frame, so the gripper the replay measured at a frame's time
is the gripper the recording measured there (within the lag of one frame), and the tip path
stays within the issue's 2 mm; a replay stopped before the gripper's frames leaves the
gripper where it was."""

from __future__ import annotations

from collections.abc import AsyncIterator
from pathlib import Path

import httpx
import numpy as np
import orjson
import pytest
from _wait import held_still, wait_for
from fastapi import FastAPI

from app.errors import ArmError
from app.service import ArmService
from tests.conftest import make_settings, running_client
from tests.test_replay import dense, path_distance

API = "/api/v1"
CONFIG = Path(__file__).resolve().parents[1] / "config" / "teleop_omx.toml"
TOL = 8 * 2 * np.pi / 4096
JOINTS = ("waist", "shoulder", "elbow", "wrist")
FPS = 30


async def move(c: httpx.AsyncClient, q: list[float]) -> None:
    r = await c.post(f"{API}/arms/leader/move/joints", json={"positions": q, "wait": True})
    assert r.status_code == 200 and r.json()["status"] == "done", r.text


async def grip(c: httpx.AsyncClient, arm: ArmService, value: float) -> None:
    r = await c.post(f"{API}/arms/leader/gripper", json={"value": value})
    assert r.status_code == 200, r.text
    await wait_for(lambda: abs(float(arm.state().get("gripper") or -1.0) - value) < 0.01,
                   what=f"the gripper at {value}")


@pytest.fixture()
async def recorded() -> AsyncIterator[tuple[FastAPI, httpx.AsyncClient]]:
    """Recording `grip` with one episode of `leader`: move, close the gripper, move, open it
    half, move."""
    async with running_client(make_settings(config=str(CONFIG))) as (app, c):
        leader: ArmService = app.state.services["leader"]
        await move(c, [0.0, -0.4, 0.3, 0.6])
        await grip(c, leader, 0.0)
        r = await c.post(f"{API}/recordings", json={"name": "grip", "arms": ["leader"],
                                                    "cameras": [], "fps": FPS})
        assert r.status_code == 201, r.text
        assert (await c.post(f"{API}/recordings/grip/episodes", json={})).status_code == 201
        await move(c, [0.5, -0.2, 0.1, 0.8])
        await grip(c, leader, 1.0)
        await move(c, [-0.3, 0.1, -0.2, 0.4])
        await grip(c, leader, 0.4)
        await move(c, [0.1, -0.3, 0.2, 0.5])
        await held_still(lambda: leader.positions, TOL)
        r = await c.post(f"{API}/recordings/grip/episodes/stop")
        assert r.status_code == 200 and r.json()["episodes"] == 1, r.text
        yield app, c


def episode(app: FastAPI) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(joint states, joint actions, gripper states, gripper actions) of the episode."""
    ep = app.state.recordings.get("grip").dataset.load_episode(0)
    cols = [ep.names.index(f"leader.{j}.pos") for j in JOINTS]
    g = ep.names.index("leader.gripper.pos")
    return ep.states[:, cols], ep.actions[:, cols], ep.states[:, g], ep.actions[:, g]


async def test_the_gripper_replays_with_the_joints(
        recorded: tuple[FastAPI, httpx.AsyncClient]) -> None:
    app, c = recorded
    leader: ArmService = app.state.services["leader"]
    states, actions, g_states, g_actions = episode(app)
    assert g_actions.max() == pytest.approx(1.0) and 0.0 in g_actions.tolist()
    # start elsewhere, the gripper open: the replay closes and half opens it again
    await move(c, [0.3, 0.2, -0.4, 0.2])
    await grip(c, leader, 0.0)
    sub = leader.subscribe(4000)
    try:
        r = await c.post(f"{API}/arms/leader/replay", json={"recording": "grip", "episode": 0,
                                                            "wait": True})
        assert r.status_code == 200, r.text
        motion = r.json()
        assert motion["status"] == "done"
        await wait_for(lambda: abs(float(leader.state()["gripper"]) - g_actions[-1]) < 0.01,
                       what="the gripper at the episode's last action")
        samples = [orjson.loads(x) for x in sub.take()[0]]
    finally:
        sub.close()
    mine = [smp for smp in samples if (smp.get("motion") or {}).get("id") == motion["id"]]
    # each sample's time in the episode: the motion's progress through its plan, less the
    # soft start (the plan's duration less the frames' (T - 1) / fps)
    duration = float(motion["planned_duration"])
    frames_s = (len(actions) - 1) / FPS
    t = np.array([float(smp["motion"]["progress"]) * duration - (duration - frames_s)
                  for smp in mine])
    g = np.array([float(smp["gripper"]) for smp in mine])
    played = t >= 0.0
    assert played.sum() > 3 * FPS
    grid = np.arange(len(g_states)) / FPS
    # the recording's gripper over the last 0.1 s before each played sample's episode time
    # (the replay sends a frame's action when it reaches the frame, up to a frame after the
    # recording's command, and the look at the motion every 10 ms) and a poll after it
    off = []
    for tk, gk in zip(t[played], g[played], strict=True):
        window = np.linspace(tk - 0.1, tk + 0.02, 25)
        off.append(float(np.min(np.abs(np.interp(window, grid, g_states) - gk))))
    assert max(off) < 0.03, f"the replay's gripper {max(off):.3f} off the recording's"
    assert g[played].max() > 0.98 and abs(g[-1] - g_states[-1]) < 0.02
    # the tip path: the existing test's measure (tests/test_replay_recording.py)
    q = np.array([smp["positions"] for smp in mine], dtype=float)
    tips = np.asarray(leader.model.fk(q), dtype=float)
    path = np.asarray(leader.model.fk(dense(states)), dtype=float)
    first = np.asarray(leader.model.fk(actions[0]), dtype=float)
    reached = int(np.argmax(np.linalg.norm(tips - first, axis=1) < 0.0005))
    off_mm = path_distance(tips[reached:], path)
    assert float(np.max(off_mm)) < 0.002, f"replay {np.max(off_mm) * 1e3:.2f} mm off"


async def test_a_stopped_replay_sends_no_more_gripper_actions(
        recorded: tuple[FastAPI, httpx.AsyncClient]) -> None:
    app, c = recorded
    leader: ArmService = app.state.services["leader"]
    await move(c, [0.3, 0.2, -0.4, 0.2])
    await grip(c, leader, 0.2)
    r = await c.post(f"{API}/arms/leader/replay", json={"recording": "grip", "episode": 0})
    assert r.status_code == 202, r.text
    mid = r.json()["id"]
    await wait_for(lambda: leader.state()["motion"] is not None
                   and leader.state()["motion"]["id"] == mid, what="the replay running")
    r = await c.post(f"{API}/arms/leader/stop")
    assert r.status_code == 200, r.text
    r = await c.get(f"{API}/arms/leader/motions/{mid}")
    assert r.json()["status"] == "stopped", r.text
    # stopped during the soft start: the first frame's action (open) never went out
    await held_still(lambda: leader.positions, TOL)
    assert abs(float(leader.state()["gripper"]) - 0.2) < 0.01
    assert leader.gripper_setpoint() == pytest.approx(0.2)


async def test_gripper_actions_not_one_per_frame_in_0_to_1_are_refused_whole(
        recorded: tuple[FastAPI, httpx.AsyncClient]) -> None:
    app, _c = recorded
    leader: ArmService = app.state.services["leader"]
    _s, actions, _gs, g_actions = episode(app)
    for bad in (g_actions[:-1], np.where(np.arange(len(g_actions)) == 3, 1.5, g_actions)):
        with pytest.raises(ArmError) as info:
            await leader.replay(actions, FPS, bad)
        assert info.value.code == "invalid_request"
    assert not leader.moving
