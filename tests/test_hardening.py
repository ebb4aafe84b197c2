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

import logging
from typing import Any

import httpx
import pytest
from conftest import make_settings, running_client

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
