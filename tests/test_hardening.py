"""Issue 11, items 4, 5, 6, 8, 9, 10, 11, 12: what a hostile or careless client (or config)
must not be able to do, through the real app over the simulated arms.

- 4: a tiny `speed` is 422 with ruckig's reason (was 502); a lone surrogate anywhere in a body
  is a clean 422 with one short log line (was a 502 with a traceback).
- 6: registers the driver relies on are 409 `in_use` in pass-through, naming the proper route.
- 8: tokens never reach the log, percent-encoded parameter names or debug-level handshakes.
- 9: an open server accepts only its own Host names and same-origin browser writes.
- 10: numbers are strict: `true` or `"1"` is not a joint position.
- 12: motion history by age (410 `motion_expired`), stops say who, identical 401 bodies.
"""

from __future__ import annotations

import asyncio
import logging
import socket
from typing import Any

import httpx
import pytest
from conftest import make_settings, running_client

from app.web.deps import ViewerRole

API = "/api/v1"
RB = f"{API}/arms/rbe3001"
AN = f"{API}/arms/angler"
JSON = {"content-type": "application/json"}


def _setpoint(app: Any) -> list[float]:
    return list(app.state.services["rbe3001"].driver.link.device.setpoint)


# ---------------------------------------------------------------- 4: no 502 for bad input


@pytest.mark.parametrize("speed", [1e-12, 1e-9, 1e-6, 3e-5])
async def test_a_tiny_speed_is_422_with_the_reason(speed: float) -> None:
    async with running_client() as (app, client):
        before = _setpoint(app)
        r = await client.post(f"{RB}/move/joints",
                              json={"positions": [0.5, 0.6, 0.4], "speed": speed})
        assert r.status_code == 422, r.text
        assert r.json()["code"] == "invalid_request"
        assert "longer than" in r.json()["detail"] and "speed" in r.json()["detail"]
        r = await client.post(f"{RB}/plan/joints",
                              json={"positions": [0.5, 0.6, 0.4], "speed": speed})
        assert r.status_code == 422, r.text
        assert _setpoint(app) == before


SURROGATE_BODIES = [
    ("POST", f"{RB}/move/pose", b'{"x": 0.1, "y": 0, "z": 0.2, "path": "\\ud800"}'),
    ("POST", f"{RB}/move/joints", b'{"positions": [0, 0, 0], "\\ud800": 1}'),
    ("POST", f"{RB}/move/joints", b'{"positions": "\\udfff"}'),
    ("PUT", f"{AN}/dynamixel/1/registers/led", b'{"raw": "\\ud800x"}'),
    ("POST", f"{AN}/dynamixel/sync-read", b'{"name": "\\ud800", "ids": [1]}'),
    ("POST", f"{RB}/kinematics/inverse", b'{"x": 0.1, "y": 0, "z": 0.2, "ik_case": "\\ud83d"}'),
]


@pytest.mark.parametrize(("method", "path", "body"), SURROGATE_BODIES)
async def test_a_lone_surrogate_is_a_clean_4xx(method: str, path: str, body: bytes,
                                               caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.INFO)
    async with running_client() as (app, client):
        r = await client.request(method, path, content=body, headers=JSON)
        assert 400 <= r.status_code < 500, r.text
        assert set(r.json()) == {"detail", "code"}
        assert app.state.internal_errors == 0
    assert not any(rec.exc_info for rec in caplog.records), "a traceback was logged"
    lines = [rec.getMessage() for rec in caplog.records if "surrogate" in rec.getMessage()]
    assert all("\n" not in m and len(m) < 200 for m in lines)


# ---------------------------------------------------------------- 10: strict numbers


STRICT_CASES = [
    ("POST", f"{RB}/move/joints", {"positions": [True, 0.5, 0.3]}),
    ("POST", f"{RB}/move/joints", {"positions": [0.1, "1", 0.3]}),
    ("POST", f"{RB}/move/joints", {"positions": [0.1, 0.5, 0.3], "speed": True}),
    ("POST", f"{RB}/move/joints", {"positions": [0.1, 0.5, 0.3], "duration": "2"}),
    ("POST", f"{RB}/move/joints", {"positions": [0.1, 0.5, 0.3], "wait": 1}),
    ("POST", f"{RB}/move/pose", {"x": True, "y": 0.0, "z": 0.2}),
    ("POST", f"{RB}/move/pose", {"x": 0.15, "y": 0.0, "z": 0.2, "branch": True}),
    ("POST", f"{RB}/kinematics/forward", {"positions": ["0", 0, 0]}),
    ("POST", f"{RB}/gripper", {"value": True}),
    ("POST", f"{RB}/rbe3001/set-claw", {"value": "1"}),
    ("POST", f"{RB}/rbe3001/set-gain", {"axis": True, "kp": 0.005, "ki": 0, "kd": 0}),
    ("POST", f"{RB}/rbe3001/set-pid", {"joints": [{"position_ticks": True}] * 3}),
    ("PUT", f"{AN}/dynamixel/1/registers/led", {"raw": True}),
    ("PUT", f"{AN}/dynamixel/1/registers/led", {"raw": "1"}),
    ("POST", f"{AN}/dynamixel/sync-read", {"name": "led", "ids": [True]}),
    ("POST", f"{AN}/dynamixel/sync-write", {"name": "led", "values": {"1": True}}),
    ("POST", f"{AN}/dynamixel/ping", {"id": True}),
]


@pytest.mark.parametrize(("method", "path", "body"), STRICT_CASES)
async def test_booleans_and_strings_are_not_numbers(method: str, path: str,
                                                    body: dict[str, Any]) -> None:
    async with running_client() as (app, client):
        before = _setpoint(app)
        r = await client.request(method, path, json=body)
        assert r.status_code == 422, r.text
        assert r.json()["code"] == "invalid_request"
        assert _setpoint(app) == before
        assert app.state.services["rbe3001"].motion.current is None


async def test_integers_are_still_numbers() -> None:
    async with running_client() as (_, client):
        r = await client.post(f"{RB}/kinematics/forward", json={"positions": [0, 1, 0]})
        assert r.status_code == 200, r.text
        r = await client.post(f"{RB}/move/joints", json={"positions": [0, 0, 0], "speed": 1})
        assert r.status_code == 202, r.text
        r = await client.post(f"{AN}/dynamixel/sync-write", json={"name": "led",
                                                                  "values": {"1": 1}})
        assert r.status_code == 200, r.text


# ---------------------------------------------------------------- 9: Host and Origin


async def test_an_open_server_refuses_foreign_host_names() -> None:
    async with running_client() as (app, client):
        before = _setpoint(app)
        for host in ("evil.example", "evil.example:8000", "127.0.0.1.evil.example",
                     "localhost.evil.example"):
            r = await client.post(f"{RB}/move/joints", json={"positions": [0.3, 0.5, 0.3]},
                                  headers={"Host": host})
            assert r.status_code == 400, (host, r.text)
            assert r.json()["code"] == "bad_host"
            r = await client.get(f"{API}/arms", headers={"Host": host})
            assert r.status_code == 400 and r.json()["code"] == "bad_host"
        assert app.state.services["rbe3001"].motion.current is None
        assert _setpoint(app) == before
        for host in ("127.0.0.1:8000", "localhost", "LOCALHOST:1", "[::1]:8000", "armserver.test"):
            r = await client.get(f"{API}/arms", headers={"Host": host})
            assert r.status_code == 200, (host, r.text)


async def test_allowed_hosts_extends_the_list_and_tokens_lift_the_check() -> None:
    settings = make_settings(allowed_hosts="armserver.test,arm.lab.example")
    async with running_client(settings) as (_, client):
        r = await client.get(f"{API}/arms", headers={"Host": "arm.lab.example:8000"})
        assert r.status_code == 200
        r = await client.get(f"{API}/arms", headers={"Host": "evil.example"})
        assert r.status_code == 400
    settings = make_settings(operator_tokens="op-secret-1")
    async with running_client(settings, {"Authorization": "Bearer op-secret-1"}) as (_, client):
        r = await client.get(f"{API}/arms", headers={"Host": "anything.example"})
        assert r.status_code == 200


def test_a_wildcard_bind_accepts_ip_literals_not_names() -> None:
    from app.web.hostguard import HostPolicy

    p = HostPolicy(make_settings(host="0.0.0.0", allowed_hosts=""))
    assert p.host_ok("192.168.1.5:8000") and p.host_ok("[fe80::1]:8000")
    assert not p.host_ok("rebind.evil.example:8000")
    p = HostPolicy(make_settings(host="192.168.1.5", allowed_hosts=""))
    assert p.host_ok("192.168.1.5:8000") and not p.host_ok("10.0.0.9")


CROSS = [
    {"Origin": "http://evil.example"},
    {"Origin": "null"},
    {"Origin": "http://armserver.test:8080"},  # another port is another origin
    {"Origin": "https://armserver.test"},  # another scheme too
    {"Sec-Fetch-Site": "cross-site"},
    {"Sec-Fetch-Site": "same-site"},
]


@pytest.mark.parametrize("headers", CROSS)
async def test_an_open_server_refuses_cross_origin_writes(headers: dict[str, str]) -> None:
    async with running_client() as (app, client):
        before = _setpoint(app)
        r = await client.post(f"{RB}/move/joints", json={"positions": [0.3, 0.5, 0.3]},
                              headers=headers)
        assert r.status_code == 403 and r.json()["code"] == "cross_origin", r.text
        # a "simple" cross-site form post, no preflight: the classic CSRF
        r = await client.post(f"{RB}/estop", content=b"x=1", headers={
            **headers, "content-type": "application/x-www-form-urlencoded"})
        assert r.status_code == 403 and r.json()["code"] == "cross_origin"
        assert not app.state.services["rbe3001"].estop
        assert app.state.services["rbe3001"].motion.current is None
        assert _setpoint(app) == before
        r = await client.get(f"{API}/arms", headers=headers)  # reading is not changing
        assert r.status_code == 200


async def test_same_origin_and_allowed_origins_may_write() -> None:
    async with running_client() as (_, client):
        for headers in ({"Origin": "http://armserver.test"}, {"Sec-Fetch-Site": "same-origin"},
                        {"Sec-Fetch-Site": "none"}, {}):
            r = await client.post(f"{RB}/stop", headers=headers)
            assert r.status_code == 200, (headers, r.text)
    settings = make_settings(cors_origins="http://dash.lab.example:5173")
    async with running_client(settings) as (_, client):
        r = await client.post(f"{RB}/stop", headers={"Origin": "http://dash.lab.example:5173",
                                                      "Sec-Fetch-Site": "cross-site"})
        assert r.status_code == 200, r.text
        r = await client.post(f"{RB}/stop", headers={"Origin": "http://evil.example"})
        assert r.status_code == 403


async def test_websocket_upgrades_from_foreign_origins_are_closed_4403() -> None:
    from conftest import serve_live
    from websockets.asyncio.client import connect
    from websockets.exceptions import ConnectionClosed

    with serve_live() as live:
        url = live.ws_url + "/api/v1/arms/rbe3001/telemetry?rate=10"
        port = int(live.url.rsplit(":", 1)[1])
        rebound = f"ws://rebind.evil.example:{port}/api/v1/arms/rbe3001/telemetry?rate=10"
        for target, kw in ((url, {"origin": "http://evil.example"}),
                           # a DNS-rebound name: the socket reaches us, the Host is foreign
                           (rebound, {"sock": socket.create_connection(("127.0.0.1", port))})):
            async with connect(target, **kw) as ws:  # type: ignore[arg-type]
                with pytest.raises(ConnectionClosed) as info:
                    await ws.recv()
                assert info.value.rcvd is not None and info.value.rcvd.code == 4403
        own = live.url  # the dashboard's own page
        async with connect(url, origin=own) as ws:  # type: ignore[arg-type]
            assert '"telemetry"' in await ws.recv()
        async with connect(url) as ws:  # not a browser: no Origin
            assert '"telemetry"' in await ws.recv()


# ---------------------------------------------------------------- 8: no token in the log

SECRET = "op2-SECRET-91c3"


def test_redaction_decodes_parameter_names_and_blanks_credentials() -> None:
    from app.web.security import redact

    assert SECRET not in redact(f"GET /t?tok%65n={SECRET}&rate=1")
    assert SECRET not in redact(f"GET /t?rate=1&%74oken={SECRET}")
    assert SECRET not in redact(f"GET /t?ACCESS_TOKEN={SECRET}")
    assert SECRET not in redact(f"< authorization: Bearer {SECRET}")
    assert SECRET not in redact(f"< Authorization: {SECRET}")
    assert redact("GET /t?rate=10&tokens=1") == "GET /t?rate=10&tokens=1"


async def test_no_token_in_the_log_at_debug_level(caplog: pytest.LogCaptureFixture) -> None:
    """`?tok%65n=` is `?token=` to the server, and at debug level uvicorn logs every header of
    a WebSocket handshake: neither may show the token."""
    from conftest import serve_live
    from websockets.asyncio.client import connect

    caplog.set_level(logging.DEBUG)
    settings = make_settings(operator_tokens=SECRET)
    names = ("uvicorn.error", "uvicorn.access", "uvicorn")
    with serve_live(settings) as live:
        for name in names:
            logging.getLogger(name).setLevel(logging.DEBUG)
            logging.getLogger(name).addHandler(caplog.handler)
        try:
            url = live.ws_url + "/api/v1/arms/rbe3001/telemetry"
            async with connect(url + f"?tok%65n={SECRET}&rate=10") as ws:
                assert '"telemetry"' in await ws.recv()  # the encoded name is accepted...
            async with connect(url + "?rate=10",
                               additional_headers={"Authorization": f"Bearer {SECRET}"}) as ws:
                assert '"telemetry"' in await ws.recv()
            async with httpx.AsyncClient() as client:
                await client.get(live.url + f"/api/v1/arms?t%6Fken={SECRET}",
                                 headers={"Authorization": f"Bearer {SECRET}"})
        finally:
            for name in names:
                logging.getLogger(name).removeHandler(caplog.handler)
                logging.getLogger(name).setLevel(logging.WARNING)
    logs = "\n".join(f"{r.name}: {r.getMessage()}" for r in caplog.records
                     if not r.name.startswith(("httpx", "httpcore", "websockets.client")))
    assert "authorization: ***" in logs.lower()  # the handshake was logged: not vacuous
    assert "tok%65n=***" in logs
    assert SECRET not in logs, logs[-3000:]


# ---------------------------------------------------------------- 6: guarded registers

GUARDED = [("profile_velocity", 32767, "move/joints"), ("profile_acceleration", 0, "move/joints"),
           ("velocity_limit", 1023, "max_velocity"), ("acceleration_limit", 32767,
                                                      "max_acceleration"),
           ("max_position_limit", 4095, "joints.max"), ("min_position_limit", 0, "joints.min"),
           ("shutdown", 0, "/reboot"), ("homing_offset", 1000, "/home"),
           ("operating_mode", 16, "/reboot"), ("drive_mode", 1, "joints.sign"),
           ("return_delay_time", 254, "link.timeout_s"), ("secondary_id", 7, "motor_id")]


@pytest.mark.parametrize(("name", "raw", "route"), GUARDED)
async def test_registers_the_driver_relies_on_are_in_use(name: str, raw: int, route: str) -> None:
    async with running_client() as (app, client):
        bus = app.state.services["angler"].driver.link.device
        before = [bus.servo(i).get(name) for i in (1, 2, 3, 4)]
        r = await client.put(f"{AN}/dynamixel/2/registers/{name}", json={"raw": raw})
        assert r.status_code == 409, r.text
        assert r.json()["code"] == "in_use"
        assert name in r.json()["detail"] and route in r.json()["detail"]
        r = await client.post(f"{AN}/dynamixel/sync-write",
                              json={"name": name, "values": {"1": raw, "3": raw}})
        assert r.status_code == 409 and r.json()["code"] == "in_use"
        assert [bus.servo(i).get(name) for i in (1, 2, 3, 4)] == before


# ---------------------------------------------------------------- 12: history, who, 401


async def test_the_token_gate_and_the_routes_answer_the_same_401() -> None:
    settings = make_settings(operator_tokens="op-secret-1")
    async with running_client(settings) as (app, client):
        @app.get("/probe")  # outside /api/v1: the gate lets it through, the route decides
        async def probe(_: ViewerRole) -> dict[str, str]:
            return {}

        app.router.routes.insert(0, app.router.routes.pop())  # before the dashboard's mount
        for headers in ({}, {"Authorization": "Bearer wrong"}):
            gate = await client.get(f"{RB}/state", headers=headers)
            route = await client.get("/probe", headers=headers)
            assert gate.status_code == route.status_code == 401
            assert gate.content == route.content, (gate.content, route.content)
            assert gate.headers["www-authenticate"] == route.headers["www-authenticate"]
            assert gate.headers["content-type"] == route.headers["content-type"]


async def test_history_keeps_recent_motions_beyond_the_count() -> None:
    """256 entries were forgotten within seconds under load: the last 10 minutes stay too."""
    async with running_client() as (_, client):
        ids = []
        for k in range(300):
            r = await client.post(f"{RB}/move/joints", json={
                "positions": [0.01 * (k % 7), 0.3, 0.2], "mode": "replace"})
            assert r.status_code == 202, r.text
            ids.append(r.json()["id"])
        await client.post(f"{RB}/stop")
        for mid in (ids[0], ids[1], ids[150]):
            r = await client.get(f"{RB}/motions/{mid}")
            assert r.status_code == 200, r.text
            assert r.json()["status"] == "stopped"


async def test_an_expired_motion_is_410_with_what_is_known() -> None:
    async with running_client() as (app, client):
        ex = app.state.services["rbe3001"].motion
        ex.history, ex.history_s = 2, 0.0  # keep the minimum: the last two, no age
        ids = []
        for k in range(4):
            if ids:  # the one before has ended (the replace runs on the control loop)
                for _ in range(500):
                    if (await client.get(f"{RB}/motions/{ids[-1]}")).json()["status"] in (
                            "done", "stopped", "failed"):
                        break
                    await asyncio.sleep(0.01)
            r = await client.post(f"{RB}/move/joints", json={
                "positions": [0.05 * k, 0.3, 0.2], "mode": "replace"})
            ids.append(r.json()["id"])
        r = await client.get(f"{RB}/motions/{ids[0]}")
        assert r.status_code == 410, r.text
        body = r.json()
        assert body["code"] == "motion_expired"
        assert ids[0] in body["detail"] and "ended done" in body["detail"]
        r = await client.delete(f"{RB}/motions/{ids[0]}")
        assert r.status_code == 410 and r.json()["code"] == "motion_expired"
        assert (await client.get(f"{RB}/motions/{ids[3]}")).status_code == 200
        # an id it never issued is still 404
        r = await client.get(f"{RB}/motions/m999999-0123abcd")
        assert r.status_code == 404 and r.json()["code"] == "unknown_motion"


async def test_a_stop_says_who_stopped_the_motion() -> None:
    token = "op-secret-1"
    settings = make_settings(operator_tokens=token)
    async with running_client(settings, {"Authorization": f"Bearer {token}"}) as (_, client):
        r = await client.post(f"{RB}/move/joints", json={"positions": [1.0, 1.2, 1.0],
                                                         "duration": 20.0})
        mid = r.json()["id"]
        r = await client.post(f"{RB}/stop")
        assert r.status_code == 200 and mid in r.json()["stopped"]
        reason = (await client.get(f"{RB}/motions/{mid}")).json()["reason"]
        import hashlib
        name = hashlib.sha256(token.encode()).hexdigest()[:8]
        assert reason.startswith(f"stopped by operator {name} from "), reason
        assert token not in reason
        r = await client.post(f"{RB}/move/joints", json={"positions": [0.5, 0.9, 0.5],
                                                         "duration": 20.0})
        mid = r.json()["id"]
        r = await client.delete(f"{RB}/motions/{mid}")
        assert r.json()["status"] == "stopped"
        assert r.json()["reason"].startswith(f"cancelled by operator {name}"), r.json()


async def test_a_lapsed_lease_says_so_in_the_stopped_motion() -> None:
    import asyncio

    # (a 1 s ttl: the move must be sent while the lease lives; 0.3 s was a budget a busy
    # machine's stall between the two requests could spend)
    async with running_client(make_settings(lease_ttl_s=1.0)) as (_, client):
        lease = (await client.post(f"{RB}/lease")).json()["id"]
        r = await client.post(f"{RB}/move/joints", headers={"X-Arm-Lease": lease},
                              json={"positions": [1.0, 1.2, 1.0], "duration": 20.0})
        assert r.status_code == 202, r.text
        mid = r.json()["id"]
        for _ in range(100):
            body = (await client.get(f"{RB}/motions/{mid}")).json()
            if body["status"] != "running" and body["status"] != "queued":
                break
            await asyncio.sleep(0.05)
        assert body["status"] == "stopped"
        assert "lease" in body["reason"] and "lapsed" in body["reason"], body["reason"]


async def test_a_tiny_speed_on_a_line_is_422_invalid_request_not_unreachable() -> None:
    async with running_client() as (app, client):
        state = (await client.get(f"{RB}/state")).json()
        tip = state["tip"]
        r = await client.post(f"{RB}/move/pose", json={
            "x": tip["x"] - 0.05, "y": tip["y"] + 0.05, "z": tip["z"], "path": "line",
            "speed": 1e-9})
        assert r.status_code == 422, r.text
        assert r.json()["code"] == "invalid_request" and "higher speed" in r.json()["detail"]
