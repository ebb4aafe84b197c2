"""Safety limits, enforced in one place (ArmService) for every path that moves an arm, and the
security basics, through the real app over the simulated arms.

- Planned moves outside the joint limits: 422 `joint_limit` naming the joint.
- Pass-through positions (rbe3001 SET_PID ticks, Dynamixel goal_position) outside the limits:
  422 `joint_limit` and nothing reaches the device (the simulator's own setpoint and register
  are read back); a profile with `raw_access` accepts the same commands.
- Pass-through velocities over the joint velocity limit (in ticks/s): 422 `velocity_limit`.
- The latched estop refuses every command that can move (409), whatever the profile.
- NaN and infinity anywhere: 422, nothing sent.
- No token in logs (ours and uvicorn's) or in any answer.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
from collections.abc import AsyncIterator
from typing import Any

import httpx
import numpy as np
import pytest
from _walk import pid_walk
from conftest import make_settings, running_client, serve_live
from fastapi import FastAPI
from websockets.asyncio.client import connect
from websockets.exceptions import ConnectionClosed

from app.arms.loading import load_profile
from app.config import ArmProfile, Settings, homed_at_start

API = "/api/v1"
RB = f"{API}/arms/rbe3001"
AN = f"{API}/arms/angler"


@contextlib.asynccontextmanager
async def served(profiles: list[ArmProfile] | None = None, settings: Settings | None = None,
                 headers: dict[str, str] | None = None
                 ) -> AsyncIterator[tuple[FastAPI, httpx.AsyncClient]]:
    """conftest's in-process app and client, over `profiles`."""
    async with running_client(settings, headers, profiles) as pair:
        yield pair


def raw_profiles() -> list[ArmProfile]:
    return [homed_at_start(load_profile(n)).model_copy(update={"raw_access": True})
            for n in ("rbe3001", "angler")]


def _rb_setpoint(app: FastAPI) -> list[float]:
    return list(app.state.services["rbe3001"].driver.link.device.setpoint)


def _goal(app: FastAPI, dxl_id: int) -> int:
    return app.state.services["angler"].driver.link.device.servo(dxl_id).get("goal_position")


def _ticks(app: FastAPI, arm: str, q: list[float]) -> list[float]:
    tr = app.state.services[arm].model.transmission
    return [float(t) for t in tr.to_ticks(np.array(q))]


def _set_pid_body(ticks: list[float], velocities: list[float] | None = None) -> dict[str, Any]:
    v = velocities or [0.0] * len(ticks)
    return {"joints": [{"position_ticks": t, "velocity_ticks_s": w}
                       for t, w in zip(ticks, v, strict=True)]}


def _angler_goal_ticks(app: FastAPI, dxl_id: int, offset: float) -> int:
    """goal_position for motor `dxl_id` putting its joint `offset` (rad or m) beyond its upper
    limit (or inside it, for a negative offset)."""
    svc = app.state.services["angler"]
    k = next(i for i, j in enumerate(svc.profile.joints) if j.motor_id == dxl_id)
    q = svc.driver.positions.copy()
    q[k] = svc.model.upper[k] + offset
    return int(round(svc.model.transmission.to_ticks(q)[k]))


# ---------------------------------------------------------------- joint limits


async def test_planned_moves_outside_the_limits_name_the_joint() -> None:
    async with served() as (app, client):
        for arm, url in (("rbe3001", RB), ("angler", AN)):
            model = app.state.services[arm].model
            for k, name in enumerate(model.names):
                q = [float((lo + hi) / 2) for lo, hi in zip(model.lower, model.upper, strict=True)]
                q[k] = float(model.upper[k]) + 0.1 * (model.upper[k] - model.lower[k])
                for route in ("move/joints", "plan/joints"):
                    r = await client.post(f"{url}/{route}", json={"positions": q})
                    assert r.status_code == 422, (arm, route, r.text)
                    body = r.json()
                    assert body["code"] == "joint_limit" and name in body["detail"], body
                    assert "above" in body["detail"]
        assert all(s.motion.current is None and not s.motion._queue
                   for s in app.state.services.values())


async def test_rbe3001_set_pid_outside_the_limits_never_reaches_the_device() -> None:
    async with served() as (app, client):
        svc = app.state.services["rbe3001"]
        before = _rb_setpoint(app)
        q = [float((lo + hi) / 2) for lo, hi in zip(svc.model.lower, svc.model.upper, strict=True)]
        for k, name in enumerate(svc.model.names):
            bad = list(q)
            bad[k] = float(svc.model.lower[k]) - 0.2
            r = await client.post(f"{RB}/rbe3001/set-pid", json=_set_pid_body(_ticks(app, "rbe3001",
                                                                                      bad)))
            assert r.status_code == 422 and r.json()["code"] == "joint_limit", r.text
            assert name in r.json()["detail"] and "below" in r.json()["detail"]
        await asyncio.sleep(0.05)
        assert _rb_setpoint(app) == before  # the firmware never saw them
        # within the limits it goes through, to the firmware (in steps the guard accepts)
        await pid_walk(client, svc, q)
        np.testing.assert_allclose(_rb_setpoint(app), _ticks(app, "rbe3001", q), atol=0.01)


async def test_dynamixel_goal_position_outside_the_limits_writes_nothing() -> None:
    async with served() as (app, client):
        before = {i: _goal(app, i) for i in (1, 2, 3, 4)}
        for dxl_id in (1, 2, 3, 4):
            too_far = _angler_goal_ticks(app, dxl_id, 0.05)
            r = await client.put(f"{AN}/dynamixel/{dxl_id}/registers/goal_position",
                                 json={"raw": too_far})
            assert r.status_code == 422 and r.json()["code"] == "joint_limit", r.text
            r = await client.post(f"{AN}/dynamixel/sync-write",
                                  json={"name": "goal_position", "values": {str(dxl_id): too_far}})
            assert r.status_code == 422 and r.json()["code"] == "joint_limit", r.text
        await asyncio.sleep(0.05)
        assert {i: _goal(app, i) for i in (1, 2, 3, 4)} == before


async def test_raw_access_profile_accepts_the_same_pass_through() -> None:
    async with served(profiles=raw_profiles()) as (app, client):
        svc = app.state.services["rbe3001"]
        q = [float((lo + hi) / 2) for lo, hi in zip(svc.model.lower, svc.model.upper, strict=True)]
        q[0] = float(svc.model.lower[0]) - 0.2
        ticks = _ticks(app, "rbe3001", q)
        await pid_walk(client, svc, q)  # past the base's limit, in steps within the speed
        np.testing.assert_allclose(_rb_setpoint(app), ticks, atol=0.01)
        too_far = _angler_goal_ticks(app, 3, 0.05)
        r = await client.put(f"{AN}/dynamixel/3/registers/goal_position", json={"raw": too_far})
        assert r.status_code == 200, r.text
        assert _goal(app, 3) == too_far
        # the planner keeps its limits: raw access is for the pass-through only
        r = await client.post(f"{RB}/move/joints", json={"positions": q})
        assert r.status_code == 422 and r.json()["code"] == "joint_limit"
        # and the estop binds raw access too
        assert (await client.post(f"{RB}/estop")).status_code == 200
        r = await client.post(f"{RB}/rbe3001/set-pid", json=_set_pid_body(ticks))
        assert r.status_code == 409 and r.json()["code"] == "estop_latched"


# ---------------------------------------------------------------- velocity limit


async def test_pass_through_velocity_over_the_limit_is_refused_by_the_service() -> None:
    """The checks themselves (the guard: one place for every path)."""
    async with served() as (app, _client):
        guard = app.state.services["rbe3001"].guard
        m = guard.model
        cap = m.transmission.velocity_to_ticks(m.vmax)
        guard.check_passthrough_velocity_ticks(0.9 * cap)  # within: no error
        with pytest.raises(Exception) as info:
            guard.check_passthrough_velocity_ticks(np.array([0.0, 1.5 * cap[1], 0.0]))
        assert info.value.code == "velocity_limit" and "shoulder" in info.value.detail
        # a position step the PID would take faster than the limit, from where the arm is
        here = np.asarray(guard.device.positions, dtype=float)
        guard.check_passthrough(here + m.vmax * 0.02)  # 0.02 s at the limit: accepted
        with pytest.raises(Exception) as info:
            guard.check_passthrough(here + np.array([0.0, 0.0, 0.5]))
        assert info.value.code == "velocity_limit" and "elbow" in info.value.detail
        from app.service import ArmService  # raw access lifts the velocity field's cap
        ArmService(raw_profiles()[0]).guard.check_passthrough_velocity_ticks(10 * cap)


async def test_set_pid_velocity_over_the_limit_is_422_velocity_limit() -> None:
    async with served() as (app, client):
        svc = app.state.services["rbe3001"]
        cap = svc.model.transmission.velocity_to_ticks(svc.model.vmax)
        ticks = _ticks(app, "rbe3001", list((svc.model.lower + svc.model.upper) / 2))
        before = _rb_setpoint(app)
        r = await client.post(f"{RB}/rbe3001/set-pid",
                              json=_set_pid_body(ticks, [0.0, 2.0 * float(cap[1]), 0.0]))
        assert r.status_code == 422 and r.json()["code"] == "velocity_limit", r.text
        assert "shoulder" in r.json()["detail"]
        assert _rb_setpoint(app) == before


# ---------------------------------------------------------------- estop


async def test_estop_refuses_everything_that_moves() -> None:
    async with served() as (app, client):
        rb_q = _ticks(app, "rbe3001", list((app.state.services["rbe3001"].model.lower
                                            + app.state.services["rbe3001"].model.upper) / 2))
        goal_ok = _angler_goal_ticks(app, 3, -0.01)
        moves = [
            ("POST", f"{RB}/move/joints", {"positions": [0.1, 0.5, 0.3]}),
            ("POST", f"{RB}/move/pose", {"x": 0.15, "y": 0.0, "z": 0.2}),
            ("POST", f"{RB}/gripper", {"value": 0.5}),
            ("POST", f"{RB}/rbe3001/set-pid", _set_pid_body(rb_q)),
            ("POST", f"{RB}/rbe3001/set-gain", {"axis": 1, "kp": 0.01, "ki": 0, "kd": 0}),
            ("POST", f"{RB}/rbe3001/set-claw", {"value": 0.5}),
            ("POST", f"{AN}/move/joints", {"positions": [0.0, 0.0, 0.1, 0.0]}),
            ("PUT", f"{AN}/dynamixel/3/registers/goal_position", {"raw": goal_ok}),
            ("PUT", f"{AN}/dynamixel/1/registers/torque_enable", {"raw": 1}),
            ("PUT", f"{AN}/dynamixel/1/registers/goal_velocity", {"raw": 10}),
            ("POST", f"{AN}/dynamixel/sync-write", {"name": "goal_position",
                                                    "values": {"3": goal_ok}}),
            ("POST", f"{AN}/dynamixel/2/reboot", None),
        ]
        for url in (RB, AN):
            assert (await client.post(f"{url}/estop")).json() == {"estop": True}
        before_rb, before_dx = _rb_setpoint(app), {i: _goal(app, i) for i in (1, 2, 3, 4)}
        claw = app.state.services["rbe3001"].driver.link.device.claw_setpoint
        for method, path, body in moves:
            r = await client.request(method, path, json=body)
            assert r.status_code == 409 and r.json()["code"] == "estop_latched", (path, r.text)
        await asyncio.sleep(0.05)
        assert _rb_setpoint(app) == before_rb
        assert {i: _goal(app, i) for i in (1, 2, 3, 4)} == before_dx
        assert app.state.services["rbe3001"].driver.link.device.claw_setpoint == claw
        # reads and the safe writes stay open
        assert (await client.get(f"{RB}/rbe3001/status")).status_code == 200
        r = await client.put(f"{AN}/dynamixel/1/registers/torque_enable", json={"raw": 0})
        assert r.status_code == 200
        # released: the same commands go through again
        for url in (RB, AN):
            assert (await client.delete(f"{url}/estop")).json() == {"estop": False}
        svc = app.state.services["rbe3001"]
        step = _ticks(app, "rbe3001", list(np.asarray(svc.driver.positions) + 0.02))
        r = await client.post(f"{RB}/rbe3001/set-pid", json=_set_pid_body(step))
        assert r.status_code == 200, r.text


# ---------------------------------------------------------------- NaN and infinity

NON_FINITE = ("NaN", "Infinity", "-Infinity", "1e999")


async def test_nan_and_infinity_anywhere_are_422_and_nothing_is_sent() -> None:
    templates = [
        (f"{RB}/move/joints", '{"positions": [%s, 0.5, 0.3]}'),
        (f"{RB}/move/joints", '{"positions": [0.1, 0.5, 0.3], "duration": %s}'),
        (f"{RB}/move/joints", '{"positions": [0.1, 0.5, 0.3], "speed": %s}'),
        (f"{RB}/move/pose", '{"x": 0.1, "y": %s, "z": 0.2}'),
        (f"{RB}/plan/pose", '{"x": %s, "y": 0.0, "z": 0.2}'),
        (f"{RB}/kinematics/forward", '{"positions": [0.1, %s, 0.3]}'),
        (f"{RB}/kinematics/inverse", '{"x": 0.1, "y": 0.0, "z": %s}'),
        (f"{RB}/gripper", '{"value": %s}'),
        (f"{RB}/rbe3001/set-pid", '{"joints": [{"position_ticks": %s}, {"position_ticks": 0},'
                                  ' {"position_ticks": 0}]}'),
        (f"{RB}/rbe3001/set-pid", '{"joints": [{"position_ticks": 0, "velocity_ticks_s": %s},'
                                  ' {"position_ticks": 0}, {"position_ticks": 0}]}'),
        (f"{RB}/rbe3001/set-gain", '{"axis": 0, "kp": %s, "ki": 0, "kd": 0}'),
        (f"{RB}/rbe3001/set-claw", '{"value": %s}'),
        (f"{AN}/move/joints", '{"positions": [0.0, 0.0, %s, 0.0]}'),
        (f"{AN}/kinematics/inverse", '{"x": 0.1, "y": 0.0, "z": 0.0, "theta3": %s}'),
    ]
    async with served() as (app, client):
        before = _rb_setpoint(app)
        for path, template in templates:
            for bad in NON_FINITE:
                r = await client.post(path, content=template % bad,
                                      headers={"content-type": "application/json"})
                assert r.status_code == 422, (path, bad, r.text)
                body = r.json()
                assert set(body) == {"detail", "code"}, body
                assert body["code"] in ("invalid_request", "invalid_json"), (path, bad, body)
                json.dumps(body, allow_nan=False)  # the answer itself is strict JSON
        r = await client.put(f"{AN}/dynamixel/3/registers/goal_position",
                             content='{"raw": NaN}', headers={"content-type": "application/json"})
        assert r.status_code == 422
        await asyncio.sleep(0.05)
        assert _rb_setpoint(app) == before
        assert all(s.motion.current is None for s in app.state.services.values())
        # the service refuses them too, whatever calls it
        svc = app.state.services["rbe3001"]
        for bad in (np.nan, np.inf):
            for call in (lambda b: svc.guard.check_joint_target(np.array([b, 0.5, 0.3])),
                         lambda b: svc.guard.check_passthrough(np.array([b, 0.0, 0.0])),
                         lambda b: svc.guard.check_passthrough_velocity_ticks(
                             np.array([0, b, 0]))):
                with pytest.raises(Exception) as info:
                    call(bad)
                assert info.value.status_code == 422


# ---------------------------------------------------------------- tokens stay secret

OP_SECRET = "op-SECRET-7f3a9c"
VIEW_SECRET = "view-SECRET-51b2e8"
WRONG_SECRET = "wrong-SECRET-0d4e77"


#: The test's own clients log their requests; those lines are not the server's.
CLIENT_LOGGERS = ("httpx", "httpcore", "websockets")


def _server_logs(caplog: pytest.LogCaptureFixture) -> str:
    return "\n".join(f"{r.name}: {r.getMessage()} {r.exc_text or ''}" for r in caplog.records
                     if not r.name.startswith(CLIENT_LOGGERS))


async def test_no_token_in_logs_or_answers(caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.DEBUG)
    settings = make_settings(operator_tokens=OP_SECRET, viewer_tokens=VIEW_SECRET)
    seen: list[str] = []

    def record(r: httpx.Response) -> None:
        seen.append(r.text)
        seen.extend(f"{k}: {v}" for k, v in r.headers.items())

    async with served(settings=settings) as (app, client):
        op = {"Authorization": f"Bearer {OP_SECRET}"}
        view = {"Authorization": f"Bearer {VIEW_SECRET}"}
        wrong = {"Authorization": f"Bearer {WRONG_SECRET}"}
        for headers in (op, view, wrong, {}):
            for method, path, body in (
                    ("GET", f"{API}/health", None), ("GET", f"{API}/arms", None),
                    ("GET", f"{RB}/state", None),
                    ("POST", f"{RB}/move/joints", {"positions": [0.1, 0.5, 0.3]}),
                    ("POST", f"{RB}/move/joints", {"positions": [9.0, 0.5, 0.3]}),
                    ("POST", f"{RB}/move/joints", {"positions": "x"}),
                    ("GET", f"{AN}/dynamixel/1/registers/nope", None),
                    ("POST", f"{RB}/lease", None), ("GET", f"{API}/arms/nope", None)):
                r = await client.request(method, path, json=body, headers=headers)
                record(r)
                # a token in the query string (where a WebSocket may carry it)
                r = await client.request(method, path + f"?token={WRONG_SECRET}", json=body,
                                         headers=headers)
                record(r)
        r = await client.post(f"{RB}/move/joints", content=b"{not json " + OP_SECRET.encode(),
                              headers={**op, "content-type": "application/json"})
        record(r)
    answers = "\n".join(seen)
    logs = _server_logs(caplog)
    for secret in (OP_SECRET, VIEW_SECRET, WRONG_SECRET):
        assert secret not in logs, f"{secret} in the logs"
    for secret in (VIEW_SECRET, WRONG_SECRET):
        assert secret not in answers, f"{secret} in an answer"
    # (the operator's token appears only where the client itself sent it in a body)
    assert answers.count(OP_SECRET) <= 1


async def test_no_token_in_the_server_logs_of_a_websocket(caplog: pytest.LogCaptureFixture
                                                          ) -> None:
    """uvicorn logs each WebSocket handshake and request with its path at INFO (as `armserver
    serve` runs it): a `?token=` must not show."""
    caplog.set_level(logging.INFO)
    settings = make_settings(operator_tokens=OP_SECRET, viewer_tokens=VIEW_SECRET)
    with serve_live(settings) as live:
        url = live.ws_url + "/api/v1/arms/rbe3001/telemetry"
        for name in ("uvicorn.error", "uvicorn.access"):  # they do not propagate to the root
            logging.getLogger(name).setLevel(logging.INFO)
            logging.getLogger(name).addHandler(caplog.handler)
        async with connect(url + f"?token={VIEW_SECRET}&rate=10") as ws:
            assert json.loads(await ws.recv())["type"] == "telemetry"
        async with connect(url + f"?token={WRONG_SECRET}") as ws:
            with pytest.raises(ConnectionClosed):
                await ws.recv()
        async with httpx.AsyncClient() as client:
            await client.get(live.url + f"/api/v1/arms?token={WRONG_SECRET}",
                             headers={"Authorization": f"Bearer {OP_SECRET}"})
        await asyncio.sleep(0.1)
    for name in ("uvicorn.error", "uvicorn.access"):
        logging.getLogger(name).removeHandler(caplog.handler)
    logs = _server_logs(caplog)
    assert "WebSocket" in logs  # the handshake was logged (the check below is not vacuous)
    for secret in (OP_SECRET, VIEW_SECRET, WRONG_SECRET):
        assert secret not in logs, f"{secret} in the server log:\n{logs[-2000:]}"


def test_bind_default_is_loopback() -> None:
    assert Settings(_env_file=None).host == "127.0.0.1"  # type: ignore[call-arg]
    assert Settings().max_body_bytes > 0 and Settings().max_ws_message_bytes > 0


async def test_a_malformed_body_without_a_token_is_401_not_422() -> None:
    """The token is checked before the body is parsed: nothing about the route leaks."""
    settings = make_settings(operator_tokens=OP_SECRET, viewer_tokens=VIEW_SECRET)
    with serve_live(settings) as live:
        async with httpx.AsyncClient(base_url=live.url) as client:
            for path in ("/api/v1/arms/rbe3001/move/pose", "/api/v1/arms/nope/move/pose"):
                r = await client.post(path, content=b"{not json",
                                      headers={"content-type": "application/json"})
                assert r.status_code == 401 and r.json()["code"] == "unauthorized"
                assert r.headers["www-authenticate"] == "Bearer"
            r = await client.post("/api/v1/arms/rbe3001/move/pose", content=b"{not json",
                                  headers={"authorization": f"Bearer {OP_SECRET}",
                                           "content-type": "application/json"})
            assert r.status_code == 422 and r.json()["code"] == "invalid_json"
            assert (await client.get("/api/v1/health")).status_code == 200


async def test_presses_that_meet_while_the_estop_latches_all_wait_for_its_one_hold() -> None:
    """The estop fast path and the route press the estop for one request, and other clients
    may press at the same moment: every press answers after the latch's hold is commanded,
    and the hold is commanded once."""
    from app.service import ArmService

    svc = ArmService(load_profile("rbe3001"))  # on this loop: the presses interleave here
    await svc.start()
    try:
        assert await svc.driver.wait_connected(5.0)
        sent = svc.driver.stats["requests"]
        told: list[bool] = []

        async def press() -> None:
            assert (await svc.latch_estop()).estop is True
            told.append(svc._hold is not None and svc._hold.done())

        await asyncio.gather(press(), press(), press())
        assert told == [True, True, True] and svc.estop
        assert svc.driver.stats["requests"] == sent + 1  # one hold (SET_PID) for the latch
        await press()  # a press on the latched estop: nothing more commanded
        assert svc.driver.stats["requests"] == sent + 1
    finally:
        await svc.close()
