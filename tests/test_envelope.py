"""The safety envelope through the real app over the simulated arms (API.md "Safety envelope"):

- GET for any viewer, PUT for an instructor only (403 for an operator on a token-protected
  server; an open server lets anyone change it), kept across a restart in the data dir;
- a planned move (joint or line, move or plan route) whose path takes any body point (the tip
  or a joint origin: the elbow counts) into a zone or below the floor is refused with 422
  `keep_out` naming the zone and the body point, and nothing moves;
- pass-through position commands (rbe3001 SET_PID, Dynamixel goal_position) are checked on
  their straight joint-space path: 422 `keep_out` and the device never sees them;
- a zone around where the arm is now is refused (no motion could leave it); bad input is 422
  and changes nothing;
- a locked database: the change applies, the answer says `persisted: false`, health says why,
  and the write lands once the lock goes.
"""

from __future__ import annotations

import asyncio
import contextlib
import sqlite3
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
from conftest import make_settings, wait_ready
from fastapi import FastAPI

from app import schemas as s
from app.config import Settings
from app.store import DB_NAME
from app.web.factory import create_app

API = "/api/v1"
RB = f"{API}/arms/rbe3001"
AN = f"{API}/arms/angler"
INSTRUCTOR, OPERATOR, VIEWER = "instr-tok-1", "op-tok-1", "view-tok-1"


@contextlib.asynccontextmanager
async def served(settings: Settings | None = None, headers: dict[str, str] | None = None
                 ) -> AsyncIterator[tuple[FastAPI, httpx.AsyncClient]]:
    app = create_app(settings or make_settings())
    async with app.router.lifespan_context(app):
        await wait_ready(app)
        async with httpx.AsyncClient(transport=httpx.ASGITransport(app=app), headers=headers,
                                     base_url="http://armserver.test", timeout=30.0) as client:
            yield app, client
    assert app.state.internal_errors == 0


def box(name: str, centre: Any, half: float | list[float]) -> dict[str, Any]:
    c, h = np.asarray(centre, dtype=float), np.broadcast_to(np.asarray(half, dtype=float), (3,))
    lo, hi = c - h, c + h
    return {"name": name, "min": dict(zip("xyz", lo.tolist(), strict=True)),
            "max": dict(zip("xyz", hi.tolist(), strict=True))}


def q_now(app: FastAPI, arm: str) -> np.ndarray:
    return np.asarray(app.state.services[arm].driver.positions, dtype=float).copy()


def points(app: FastAPI, arm: str, q: Any) -> np.ndarray:
    return app.state.services[arm].safety.points(np.asarray(q, dtype=float))


def idle(app: FastAPI) -> bool:
    return all(s.motion.current is None and not s.motion._queue
               for s in app.state.services.values())


async def test_get_answers_the_profile_settings_for_any_viewer() -> None:
    async with served() as (_app, client):
        r = await client.get(f"{RB}/safety")
        assert r.status_code == 200, r.text
        body = r.json()
        assert body["zones"] == [] and body["floor_z"] is None and body["speed_override"] == 1.0
        assert body["tool_margin"] == 0.02 and body["source"] == "profile"
        assert body["body_points"] == ["base", "shoulder", "elbow", "tip"]
        assert body["editable"] is True  # an open server: everyone is an instructor
        r = await client.get(f"{AN}/safety")
        assert r.json()["body_points"] == ["base", "x_carriage", "column", "arm_end", "tip"]


async def test_only_an_instructor_may_change_it_on_a_protected_server() -> None:
    settings = make_settings(instructor_tokens=INSTRUCTOR, operator_tokens=OPERATOR,
                             viewer_tokens=VIEWER)
    async with served(settings) as (app, client):
        def auth(tok: str) -> dict[str, str]:
            return {"Authorization": f"Bearer {tok}"}

        r = await client.get(f"{RB}/safety", headers=auth(VIEWER))
        assert r.status_code == 200 and r.json()["editable"] is False
        body = {"speed_override": 0.5}
        for tok in (VIEWER, OPERATOR):
            r = await client.put(f"{RB}/safety", json=body, headers=auth(tok))
            assert r.status_code == 403 and r.json()["code"] == "forbidden", r.text
            assert "instructor" in r.json()["detail"]
        r = await client.put(f"{RB}/safety", json=body)
        assert r.status_code == 401
        assert app.state.services["rbe3001"].safety.speed_override == 1.0
        r = await client.put(f"{RB}/safety", json=body, headers=auth(INSTRUCTOR))
        assert r.status_code == 200 and r.json()["speed_override"] == 0.5, r.text
        assert r.json()["editable"] is True
        # an instructor may move the arm like an operator
        r = await client.post(f"{RB}/plan/joints", json={"positions": [0.1, 0.2, 0.3]},
                              headers=auth(INSTRUCTOR))
        assert r.status_code == 200, r.text
        r = await client.post(f"{RB}/move/joints", json={"positions": [0.0, 0.1, 0.1]},
                              headers=auth(INSTRUCTOR))
        assert r.status_code == 202, r.text


async def test_a_joint_move_sweeping_the_elbow_through_a_zone_is_refused() -> None:
    async with served() as (app, client):
        q0 = q_now(app, "rbe3001")
        q1 = q0 + np.array([1.0, 0.0, 0.0])  # turn the base: the elbow sweeps an arc
        mid = q0 + np.array([0.5, 0.0, 0.0])
        elbow, tip = points(app, "rbe3001", mid)[2], points(app, "rbe3001", mid)[3]
        assert abs(elbow[2] - tip[2]) > 0.1  # the zone below holds the elbow, not the tip
        zone = box("camera", elbow, 0.03)
        r = await client.put(f"{RB}/safety", json={"zones": [zone]})
        assert r.status_code == 200 and r.json()["source"] == "stored", r.text
        for route in ("plan/joints", "move/joints"):
            r = await client.post(f"{RB}/{route}", json={"positions": q1.tolist()})
            assert r.status_code == 422, r.text
            body = r.json()
            assert body["code"] == "keep_out", body
            assert "'camera'" in body["detail"] and "elbow" in body["detail"], body
            assert "s into the motion" in body["detail"]
        assert idle(app)
        await asyncio.sleep(0.1)
        np.testing.assert_allclose(q_now(app, "rbe3001"), q0, atol=0.02)  # nothing moved
        # the way back round the other side is clear: accepted, and it runs to the end
        q2 = q0 + np.array([-0.4, 0.0, 0.0])
        r = await client.post(f"{RB}/move/joints", json={"positions": q2.tolist(), "wait": True})
        assert r.status_code == 200 and r.json()["status"] == "done", r.text


async def test_a_line_move_into_a_zone_and_a_move_below_the_floor_are_refused() -> None:
    async with served() as (app, client):
        q0 = q_now(app, "rbe3001")
        tip0 = points(app, "rbe3001", q0)[3]
        goal = tip0 + np.array([0.0, 0.08, 0.06])
        zone = box("fixture", tip0 + np.array([0.0, 0.04, 0.03]), [0.05, 0.01, 0.05])
        r = await client.put(f"{RB}/safety", json={"zones": [zone]})
        assert r.status_code == 200, r.text
        pose = {"x": goal[0], "y": goal[1], "z": goal[2], "path": "line"}
        r = await client.post(f"{RB}/plan/pose", json=pose)
        assert r.status_code == 422 and r.json()["code"] == "keep_out", r.text
        assert "'fixture'" in r.json()["detail"] and "tip" in r.json()["detail"]
        # the floor: a move that takes the tip (with the tool's margin) under it
        r = await client.put(f"{RB}/safety", json={"zones": [], "floor_z": tip0[2] - 0.05})
        assert r.status_code == 200, r.text
        down = {"x": tip0[0], "y": tip0[1], "z": tip0[2] - 0.04, "path": "line"}
        r = await client.post(f"{RB}/move/pose", json=down)
        assert r.status_code == 422 and r.json()["code"] == "keep_out", r.text
        assert "floor" in r.json()["detail"] and "tip" in r.json()["detail"]
        assert "0.02 m margin" in r.json()["detail"]
        up = {"x": tip0[0], "y": tip0[1], "z": tip0[2] + 0.03, "path": "line", "wait": True}
        r = await client.post(f"{RB}/move/pose", json=up)
        assert r.status_code == 200 and r.json()["status"] == "done", r.text
        r = await client.put(f"{RB}/safety", json={"floor_z": None})
        assert r.status_code == 200 and r.json()["floor_z"] is None


async def test_angler_zone_on_the_column_path() -> None:
    async with served() as (app, client):
        q0 = q_now(app, "angler")
        q1 = q0 + np.array([0.04, 0.0, 0.0, 0.0])
        col = points(app, "angler", q0 + np.array([0.02, 0.0, 0.0, 0.0]))[2]  # the column foot
        r = await client.put(f"{AN}/safety", json={"zones": [box("clamp", col, 0.005)]})
        assert r.status_code == 200, r.text
        r = await client.post(f"{AN}/plan/joints", json={"positions": q1.tolist()})
        assert r.status_code == 422 and r.json()["code"] == "keep_out", r.text
        detail = r.json()["detail"]
        # the column foot and the x carriage both sit at z = 0: either is a right answer
        assert "'clamp'" in detail and ("column" in detail or "x_carriage" in detail), detail


async def test_pass_through_positions_are_checked_on_their_path() -> None:
    async with served() as (app, client):
        svc = app.state.services["rbe3001"]
        q0 = q_now(app, "rbe3001")
        q1 = q0 + np.array([0.8, 0.0, 0.0])
        elbow = points(app, "rbe3001", q0 + np.array([0.4, 0.0, 0.0]))[2]
        r = await client.put(f"{RB}/safety", json={"zones": [box("hand", elbow, 0.02)]})
        assert r.status_code == 200, r.text
        before = list(svc.driver.link.device.setpoint)
        ticks = svc.model.transmission.to_ticks(q1).tolist()
        body = {"joints": [{"position_ticks": t, "velocity_ticks_s": 0.0} for t in ticks]}
        r = await client.post(f"{RB}/rbe3001/set-pid", json=body)
        assert r.status_code == 422 and r.json()["code"] == "keep_out", r.text
        assert "'hand'" in r.json()["detail"] and "of the way along" in r.json()["detail"]
        await asyncio.sleep(0.05)
        assert list(svc.driver.link.device.setpoint) == before  # the firmware never saw it
        # angler: a goal_position register write whose path crosses a zone
        an = app.state.services["angler"]
        qa = q_now(app, "angler")
        qb = qa.copy()
        qb[2] = qa[2] + 0.6
        arm_end = points(app, "angler", qa + np.array([0.0, 0.0, 0.3, 0.0]))[3]
        r = await client.put(f"{AN}/safety", json={"zones": [box("lamp", arm_end, 0.01)]})
        assert r.status_code == 200, r.text
        goal_before = an.driver.link.device.servo(3).get("goal_position")
        raw = int(round(an.model.transmission.to_ticks(qb)[2]))
        r = await client.put(f"{AN}/dynamixel/3/registers/goal_position", json={"raw": raw})
        assert r.status_code == 422 and r.json()["code"] == "keep_out", r.text
        assert "'lamp'" in r.json()["detail"]
        assert an.driver.link.device.servo(3).get("goal_position") == goal_before


async def test_a_zone_around_the_arm_now_and_bad_input_change_nothing() -> None:
    async with served() as (app, client):
        q0 = q_now(app, "rbe3001")
        here = points(app, "rbe3001", q0)[2]
        r = await client.put(f"{RB}/safety", json={"zones": [box("trap", here, 0.02)]})
        assert r.status_code == 422 and r.json()["code"] == "keep_out", r.text
        assert "now" in r.json()["detail"]
        bad = [
            {"zones": [{"name": "flat", "min": {"x": 0, "y": 0, "z": 0},
                        "max": {"x": 1, "y": 1, "z": 0}}]},
            {"zones": [box("a", [1, 1, 1], 0.1), box("a", [2, 2, 2], 0.1)]},
            {"speed_override": 0.01}, {"speed_override": 1.5}, {"speed_override": None},
            {"floor_z": "low"}, {"zones": [box("x", [1, 1, 1], 0.1) | {"extra": 1}]},
            {"zones": [{"name": "", "min": {"x": 0, "y": 0, "z": 0},
                        "max": {"x": 1, "y": 1, "z": 1}}]},
            {"unknown": 1},
        ]
        for body in bad:
            r = await client.put(f"{RB}/safety", json=body)
            if body == {"speed_override": None}:  # null is "keep it": accepted, no change
                assert r.status_code == 200 and r.json()["speed_override"] == 1.0
                continue
            assert r.status_code == 422, (body, r.text)
            assert r.json()["code"] in ("invalid_request", "invalid_json"), r.text
        r = await client.get(f"{RB}/safety")
        assert r.json()["zones"] == [] and r.json()["speed_override"] == 1.0


async def test_settings_survive_a_restart(tmp_path: Path) -> None:
    settings = make_settings(data_dir=str(tmp_path))
    zone = box("camera", [0.5, 0.5, 0.5], 0.05)
    async with served(settings) as (_app, client):
        r = await client.put(f"{AN}/safety", json={"zones": [zone], "floor_z": -0.2,
                                                   "speed_override": 0.3})
        assert r.status_code == 200 and r.json()["persisted"] is True, r.text
    assert (tmp_path / DB_NAME).is_file()
    async with served(settings) as (app, client):
        body = (await client.get(f"{AN}/safety")).json()
        assert body["source"] == "stored" and body["zones"] == [zone]
        assert body["floor_z"] == -0.2 and body["speed_override"] == 0.3
        assert (await client.get(f"{RB}/safety")).json()["source"] == "profile"
        assert app.state.services["angler"].safety.speed_override == 0.3


async def test_a_locked_database_is_an_error_in_health_not_a_lost_change(tmp_path: Path) -> None:
    settings = make_settings(data_dir=str(tmp_path))
    async with served(settings) as (app, client):
        assert (await client.get(f"{API}/health")).json()["store"]["ok"] is True
        other = sqlite3.connect(tmp_path / DB_NAME, isolation_level=None)
        other.execute("BEGIN EXCLUSIVE")
        try:
            r = await client.put(f"{RB}/safety", json={"speed_override": 0.4})
            assert r.status_code == 200, r.text
            assert r.json()["persisted"] is False and "locked" in r.json()["store_error"]
            assert app.state.services["rbe3001"].safety.speed_override == 0.4  # applied
            h = (await client.get(f"{API}/health")).json()
            assert h["status"] == "degraded" and h["store"]["ok"] is False
            # the setting, and the audit record of the PUT (app/classroom/audit.py): both kept,
            # unsaved
            assert h["store"]["pending"] == 2 and "locked" in h["store"]["error"]
        finally:
            other.execute("ROLLBACK")
            other.close()
        app.state.store._retry_s = 0.05  # retry soon rather than in RETRY_S
        r = await client.put(f"{AN}/safety", json={"speed_override": 0.9})  # flushes both
        assert r.status_code == 200 and r.json()["persisted"] is True, r.text
        # the audit records (this PUT's among them) go through the store's writer thread,
        # after the response: wait for it (bounded) rather than race it
        for _ in range(250):
            h = (await client.get(f"{API}/health")).json()
            if h["store"]["pending"] == 0:
                break
            await asyncio.sleep(0.02)
        assert h["store"]["ok"] is True and h["store"]["pending"] == 0
    rows = dict(sqlite3.connect(tmp_path / DB_NAME).execute(
        "SELECT scope, value FROM settings").fetchall())
    assert '"speed_override":0.4' in rows["arm:rbe3001"]
    assert '"speed_override":0.9' in rows["arm:angler"]


@pytest.mark.parametrize("override", [0.25, 0.6])
async def test_speed_override_scales_every_planned_limit(override: float) -> None:
    async with served() as (app, client):
        svc = app.state.services["rbe3001"]
        m = svc.model
        q0 = q_now(app, "rbe3001")
        q1 = (q0 + np.array([1.0, 0.5, 0.5])).tolist()
        fast = (await client.post(f"{RB}/plan/joints", json={"positions": q1})).json()
        r = await client.put(f"{RB}/safety", json={"speed_override": override})
        assert r.status_code == 200
        slow = (await client.post(f"{RB}/plan/joints", json={"positions": q1})).json()
        assert slow["planned_duration"] > fast["planned_duration"] * 1.2
        # the plan the executor would run: its peak v, a, j within k times the profile's
        req = s.MoveJoints(positions=q1)
        for at_rest in (True, False):
            plan = svc.motion._plan_joint_from(svc.motion._tail_state("queue")[0],
                                               np.array(q1), req, at_rest)
            t = np.linspace(0.0, plan.traj.duration, 2001)
            _q, qd, qdd = plan.traj.sample(t)
            assert np.all(np.abs(qd).max(axis=0) <= override * m.vmax * (1 + 1e-6))
            assert np.all(np.abs(qdd).max(axis=0) <= override * m.amax * (1 + 1e-6))
            jerk = np.diff(qdd, axis=0) / np.diff(t)[:, None]
            assert np.all(np.abs(jerk).max(axis=0) <= override * m.jmax * (1 + 1e-3))
            # and it hits the slower limit: not merely slower for some other reason
            assert np.abs(qd).max() >= 0.9 * override * m.vmax.max()
        # a line move: the Cartesian limits are scaled too
        tip = points(app, "rbe3001", q0)[3]
        line = {"x": tip[0], "y": tip[1] + 0.1, "z": tip[2] + 0.05, "path": "line"}
        r = await client.post(f"{RB}/plan/pose", json=line)
        assert r.status_code == 200, r.text
        plan = svc.motion._plan_pose_from(svc.motion._tail_state("queue")[0],
                                          np.array([line["x"], line["y"], line["z"]]),
                                          s.MovePose(**line), True)
        t = np.linspace(0.0, plan.traj.duration, 2001)
        q = plan.traj.sample(t)[0]
        tip_v = np.linalg.norm(np.diff(m.fk(q), axis=0), axis=-1) / np.diff(t)
        assert tip_v.max() <= override * svc.profile.cartesian.max_velocity * 1.02


async def test_the_client_reads_and_changes_the_envelope() -> None:
    from app.client import ArmServerError, AsyncArmClient

    async with served() as (app, _client):
        transport = httpx.ASGITransport(app=app)
        async with AsyncArmClient("http://armserver.test", transport=transport) as c:
            got = await c.set_safety("angler", zones=[box("cam", [0.5, 0.5, 0.5], 0.05)],
                                     floor_z=-0.2)
            assert [z.name for z in got.zones] == ["cam"] and got.floor_z == -0.2
            got = await c.set_safety("angler", speed_override=0.5)  # the rest is kept
            assert got.floor_z == -0.2 and got.speed_override == 0.5 and len(got.zones) == 1
            got = await c.set_safety("angler", floor_z=None)  # None given: no floor
            assert got.floor_z is None and len(got.zones) == 1
            assert (await c.safety("angler")).speed_override == 0.5
            here = points(app, "angler", q_now(app, "angler"))[-1]
            with pytest.raises(ArmServerError) as info:
                await c.set_safety("angler", zones=[box("trap", here, 0.01)])
            assert info.value.code == "keep_out" and info.value.status == 422


async def test_zones_from_the_server_config(tmp_path: Path) -> None:
    cfg = tmp_path / "lab.toml"
    cfg.write_text('''
[[arms]]
profile = "rbe3001"
name = "left"

[arms.safety]
floor_z = -0.1
speed_override = 0.5
tool_margin = 0.03

[[arms.safety.zones]]
name = "camera"
min = { x = 0.3, y = 0.3, z = 0.3 }
max = { x = 0.4, y = 0.4, z = 0.4 }
''')
    async with served(make_settings(config=str(cfg))) as (app, client):
        body = (await client.get(f"{API}/arms/left/safety")).json()
        assert body["source"] == "profile" and body["zones"][0]["name"] == "camera"
        assert body["floor_z"] == -0.1 and body["speed_override"] == 0.5
        assert body["tool_margin"] == 0.03
        assert app.state.services["left"].safety.margins[-1] == 0.03
    bad = tmp_path / "bad.toml"
    bad.write_text(cfg.read_text().replace("speed_override = 0.5", "speed_override = 2.0"))
    with pytest.raises(ValueError, match="speed_override"):
        from app.arms.loading import load_arms
        load_arms(bad)
