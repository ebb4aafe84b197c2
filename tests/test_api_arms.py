"""Health, arms, state and the error contract (shapes, codes, never a 500), over the real app."""

from __future__ import annotations

import asyncio

import httpx
import pytest
from conftest import make_settings
from fastapi import FastAPI

from app.schemas import ArmDetail, Health, Sample
from app.web.factory import create_app

API = "/api/v1"


async def test_health_lists_every_arm_up(app_client: httpx.AsyncClient) -> None:
    r = await app_client.get(f"{API}/health")
    assert r.status_code == 200
    h = Health.model_validate(r.json())
    assert h.status == "ok" and h.auth is False
    assert set(h.arms) == {"rbe3001", "angler"}
    assert all(link.connected and link.state == "up" for link in h.arms.values())


async def test_arms_list_and_detail(app_client: httpx.AsyncClient) -> None:
    r = await app_client.get(f"{API}/arms")
    assert r.status_code == 200
    by_name = {a["name"]: a for a in r.json()}
    assert by_name["rbe3001"]["capabilities"] == {"gripper": True, "force_sensing": True,
                                                  "protocol": "rbe3001", "paths": ["joint", "line"]}
    assert by_name["angler"]["capabilities"]["protocol"] == "dynamixel"
    assert by_name["angler"]["capabilities"]["gripper"] is False

    d = ArmDetail.model_validate((await app_client.get(f"{API}/arms/rbe3001")).json())
    assert [j.name for j in d.joints] == ["base", "shoulder", "elbow"]
    assert d.joints[1].min == pytest.approx(-0.35) and d.joints[1].max == pytest.approx(1.75)
    assert d.poll_hz == 500.0 and d.estop is False
    assert d.link.kind == "sim" and d.link.connected
    a = ArmDetail.model_validate((await app_client.get(f"{API}/arms/angler")).json())
    assert [j.kind for j in a.joints] == ["prismatic", "prismatic", "revolute", "prismatic"]


async def test_the_detail_counts_telemetry_subscribers_and_what_they_lost(
        app_and_client: tuple[FastAPI, httpx.AsyncClient]) -> None:
    """`telemetry`: subscribers now, samples published, and samples lost by subscribers to
    their backlog bound, together (what the benchmark reads to say every client got every
    sample)."""
    app, app_client = app_and_client
    hub = app.state.services["rbe3001"].hub
    before = ArmDetail.model_validate((await app_client.get(f"{API}/arms/rbe3001")).json())
    assert before.telemetry is not None and before.telemetry.published >= 1
    slow = hub.subscribe(backlog=3)
    try:
        published = hub.published
        for _ in range(500):  # the arm publishes at 500 Hz (bounded: 5 s)
            if hub.published >= published + 10:
                break
            await asyncio.sleep(0.01)
        _, _, dropped = slow.take()
        assert dropped >= 7
        d = ArmDetail.model_validate((await app_client.get(f"{API}/arms/rbe3001")).json())
        assert d.telemetry is not None
        assert d.telemetry.subscribers == before.telemetry.subscribers + 1
        assert d.telemetry.dropped == before.telemetry.dropped + dropped
        assert d.telemetry.published >= published + 10
    finally:
        slow.close()


async def test_state_is_a_fresh_sample(app_client: httpx.AsyncClient) -> None:
    s1 = Sample.model_validate((await app_client.get(f"{API}/arms/rbe3001/state")).json())
    s2 = Sample.model_validate((await app_client.get(f"{API}/arms/rbe3001/state")).json())
    assert len(s1.positions) == 3 and s1.link == "up" and not s1.stale
    assert s2.seq >= s1.seq
    assert s1.tip_force is not None  # the rbe3001 senses joint torques
    ang = Sample.model_validate((await app_client.get(f"{API}/arms/angler/state")).json())
    assert len(ang.positions) == 4


async def test_unknown_arm_is_404_with_code(app_client: httpx.AsyncClient) -> None:
    for method, path in [("GET", "/arms/nope"), ("GET", "/arms/nope/state"),
                         ("POST", "/arms/nope/stop"), ("GET", "/arms/nope/workspace")]:
        r = await app_client.request(method, API + path)
        assert r.status_code == 404, path
        assert r.json()["code"] == "unknown_arm"
        assert "rbe3001" in r.json()["detail"]


async def test_unknown_path_and_method_have_the_error_shape(app_client: httpx.AsyncClient) -> None:
    r = await app_client.get(f"{API}/nowhere")
    assert r.status_code == 404 and r.json()["code"] == "not_found"
    r = await app_client.delete(f"{API}/health")
    assert r.status_code == 405 and r.json()["code"] == "method_not_allowed"
    r = await app_client.get(f"{API}/arms/rbe3001/move/joints")
    assert r.status_code == 405 and r.json()["code"] == "method_not_allowed"


async def test_nan_in_a_body_is_422_with_json_safe_detail(app_client: httpx.AsyncClient) -> None:
    r = await app_client.post(f"{API}/arms/rbe3001/kinematics/inverse",
                              content=b'{"x": NaN, "y": 0, "z": 0.2}',
                              headers={"content-type": "application/json"})
    assert r.status_code == 422
    body = r.json()
    assert body["code"] == "invalid_request"
    assert body["detail"][0]["loc"] == ["body", "x"]
    assert "input" not in body["detail"][0]  # NaN is not JSON
    r = await app_client.post(f"{API}/arms/rbe3001/move/joints",
                              content=b'{"positions": [0, Infinity, 0]}',
                              headers={"content-type": "application/json"})
    assert r.status_code == 422 and r.json()["code"] == "invalid_request"


@pytest.mark.parametrize("raw", [b'{"positions": [', b"not json", b'{"positions": [0,0,0]}}'])
async def test_malformed_json_is_422_invalid_json(app_client: httpx.AsyncClient,
                                                  raw: bytes) -> None:
    r = await app_client.post(f"{API}/arms/rbe3001/kinematics/forward", content=raw,
                              headers={"content-type": "application/json"})
    assert r.status_code == 422
    assert r.json()["code"] == "invalid_json"


async def test_validation_errors_name_the_field(app_client: httpx.AsyncClient) -> None:
    r = await app_client.post(f"{API}/arms/rbe3001/gripper", json={"value": 1.5})
    assert r.status_code == 422
    d = r.json()["detail"][0]
    assert d["loc"] == ["body", "value"] and d["ctx"] == {"le": "1.0"}
    r = await app_client.post(f"{API}/arms/rbe3001/move/joints", json={"positions": [0, 0, 0],
                                                                       "bogus": 1})
    assert r.status_code == 422 and r.json()["detail"][0]["type"] == "extra_forbidden"


async def test_body_over_the_limit_is_413() -> None:
    from conftest import running_client

    async with running_client(make_settings(max_body_bytes=1024)) as (_, client):
        r = await client.post(f"{API}/arms/rbe3001/kinematics/forward",
                              content=b'{"positions": [' + b"0," * 1000 + b"0]}",
                              headers={"content-type": "application/json"})
        assert r.status_code == 413 and r.json()["code"] == "too_large"

        async def chunks():  # no Content-Length: counted as it streams
            for _ in range(20):
                yield b" " * 100

        r = await client.post(f"{API}/arms/rbe3001/kinematics/forward", content=chunks(),
                              headers={"content-type": "application/json"})
        assert r.status_code == 413 and r.json()["code"] == "too_large"
        r = await client.post(f"{API}/arms/rbe3001/kinematics/forward",
                              json={"positions": [0, 0, 0]})
        assert r.status_code == 200


async def test_cors_allows_only_the_configured_origins() -> None:
    from conftest import running_client

    async with running_client(make_settings(cors_origins="http://lab.example")) as (_, client):
        r = await client.get(f"{API}/health", headers={"Origin": "http://lab.example"})
        assert r.headers["access-control-allow-origin"] == "http://lab.example"
        r = await client.get(f"{API}/health", headers={"Origin": "http://evil.example"})
        assert "access-control-allow-origin" not in r.headers


async def test_openapi_documents_every_route(app_client: httpx.AsyncClient) -> None:
    spec = (await app_client.get("/openapi.json")).json()
    paths = spec["paths"]
    expected = {
        "/api/v1/health", "/api/v1/arms", "/api/v1/arms/{arm}", "/api/v1/arms/{arm}/state",
        "/api/v1/arms/{arm}/move/joints", "/api/v1/arms/{arm}/move/pose",
        "/api/v1/arms/{arm}/plan/joints", "/api/v1/arms/{arm}/plan/pose",
        "/api/v1/arms/{arm}/motions/{motion_id}", "/api/v1/arms/{arm}/stop",
        "/api/v1/arms/{arm}/estop", "/api/v1/arms/{arm}/gripper",
        "/api/v1/arms/{arm}/kinematics/forward", "/api/v1/arms/{arm}/kinematics/inverse",
        "/api/v1/arms/{arm}/workspace",
        "/api/v1/arms/{arm}/rbe3001/set-pid", "/api/v1/arms/{arm}/rbe3001/status",
        "/api/v1/arms/{arm}/rbe3001/set-gain", "/api/v1/arms/{arm}/rbe3001/set-claw",
        "/api/v1/arms/{arm}/dynamixel/ping",
        "/api/v1/arms/{arm}/dynamixel/{dxl_id}/registers/{name}",
        "/api/v1/arms/{arm}/dynamixel/sync-read", "/api/v1/arms/{arm}/dynamixel/sync-write",
        "/api/v1/arms/{arm}/dynamixel/{dxl_id}/reboot", "/api/v1/arms/{arm}/torque",
        "/api/v1/arms/{arm}/lease", "/api/v1/arms/{arm}/lease/{lease_id}",
    }
    assert expected <= set(paths)
    for path, ops in paths.items():
        for method, op in ops.items():
            assert op.get("summary") and op.get("description"), (method, path)
            for code, resp in op["responses"].items():
                if int(code) >= 400:  # every error documented as {detail, code}
                    ref = resp["content"]["application/json"]["schema"]["$ref"]
                    assert ref.endswith("/ErrorBody"), (method, path, code)
    assert {"ErrorBody", "TelemetryMessage", "EventMessage", "Sample"} <= set(
        spec["components"]["schemas"])
    assert "HTTPBearer" in spec["components"]["securitySchemes"]


async def test_dashboard_is_served_when_present(app_client: httpx.AsyncClient) -> None:
    from app.web.factory import STATIC_DIR

    if not (STATIC_DIR / "index.html").is_file():
        pytest.skip("no dashboard in app/static")
    r = await app_client.get("/")
    assert r.status_code == 200 and "text/html" in r.headers["content-type"]


def test_create_app_takes_explicit_profiles() -> None:
    from app.arms.loading import load_profile

    app = create_app(make_settings(), [load_profile("angler")])
    assert app.title == "armserver"


async def test_the_last_resort_handler_answers_502_and_counts() -> None:
    """The belt under the braces: a bug answers 502 `internal_error`, never a 500, and is
    counted (every other test asserts the count stays 0)."""
    app = create_app(make_settings(), [])

    @app.get("/api/v1/boom")
    async def boom() -> None:
        raise RuntimeError("a bug")

    async with app.router.lifespan_context(app):
        transport = httpx.ASGITransport(app=app)
        async with httpx.AsyncClient(transport=transport,
                                     base_url="http://armserver.test") as client:
            r = await client.get("/api/v1/boom")
    assert r.status_code == 502
    assert r.json() == {"detail": "internal error (logged); please report it",
                        "code": "internal_error"}
    assert app.state.internal_errors == 1
