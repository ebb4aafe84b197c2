"""Recording during teleoperation (config/teleop_omx.toml: two simulated OpenManipulator-X
arms): the follower's dataset holds the leader's joints as the action (the follower's commanded
setpoint is the leader's mapped joints) and the follower's measured joints as the state."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import orjson
from _wait import wait_for

from tests._lerobot import check_dataset
from tests.conftest import make_settings, running_client
from tests.test_recording_api import frames_at_least

API = "/api/v1"
CONFIG = Path(__file__).resolve().parents[1] / "config" / "teleop_omx.toml"
TOL = 8 * 2 * np.pi / 4096  # rad: the XM430's settle tolerance (8 ticks)
GOAL = [0.6, -0.5, 0.4, 0.7]


def path_distance(points: np.ndarray, path: np.ndarray) -> np.ndarray:
    """Each point's distance (rad) to the polyline `path`."""
    a, b = path[:-1], path[1:]
    ab = b - a
    out = []
    for p in points:
        t = np.clip(np.einsum("ij,ij->i", p - a, ab)
                    / np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-18), 0.0, 1.0)
        out.append(float(np.min(np.linalg.norm(a + t[:, None] * ab - p, axis=1))))
    return np.asarray(out)


async def test_the_action_is_the_leaders_joints_the_state_the_followers() -> None:
    async with running_client(make_settings(config=str(CONFIG))) as (app, c):
        leader, follower = app.state.services["leader"], app.state.services["follower"]
        r = await c.post(f"{API}/teleop", json={"leader": "leader", "follower": "follower",
                                                 "rate_hz": 50})
        assert r.status_code == 201, r.text
        await wait_for(lambda: np.allclose(follower.positions, leader.positions, atol=TOL),
                       what="the follower where the leader is")
        r = await c.post(f"{API}/recordings", json={"name": "tele", "arms": ["follower"],
                                                     "fps": 25, "task": "follow"})
        assert r.status_code == 201, r.text
        lsub, fsub = leader.subscribe(4000), follower.subscribe(4000)
        try:
            assert (await c.post(f"{API}/recordings/tele/episodes")).status_code == 201
            r = await c.post(f"{API}/arms/leader/move/joints", json={"positions": GOAL,
                                                                     "wait": True})
            assert r.status_code == 200, r.text
            await wait_for(lambda: np.allclose(follower.positions, GOAL, atol=TOL),
                           what="the follower at the leader's goal")
            there = (await c.get(f"{API}/recordings/tele")).json()["current"]["frames"]
            await frames_at_least(c, "tele", there + 3)  # three more frames
            r = await c.post(f"{API}/recordings/tele/episodes/stop")
            assert r.status_code == 200, r.text
            lq = np.array([orjson.loads(x)["positions"] for x in lsub.take()[0]])
            fq = np.array([orjson.loads(x)["positions"] for x in fsub.take()[0]])
        finally:
            lsub.close()
            fsub.close()
        d = r.json()
        assert d["names"][:4] == [f"follower.{j.name}.pos" for j in follower.profile.joints]
        read = check_dataset(Path(d["path"]))
        action = read.frames["action"][:, :4].astype(float)
        state = read.frames["observation.state"][:, :4].astype(float)
        # the action followed the leader's joint path (within one teleop period's motion) and
        # ended at its goal
        one_period = float(np.max(leader.model.vmax)) * leader.profile.tracking_margin / 50
        assert float(np.max(path_distance(action, lq))) < one_period
        np.testing.assert_allclose(action[-1], GOAL, atol=TOL)
        # the state is the follower as measured, resampled between its samples: on the path of
        # its telemetry (float32's rounding), and at the goal at the end
        np.testing.assert_allclose(state[-1], GOAL, atol=TOL)
        settled = state[: len(state) - 1]  # frames after the last sample are the last sample
        assert float(np.max(path_distance(settled, np.vstack([state[:1], fq])))) < 1e-5
