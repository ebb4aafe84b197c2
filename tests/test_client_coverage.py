"""Every route of the server has a client method, and every client method its route.

The routes come from the app's own OpenAPI document (`create_app().openapi()`), so a route
added to the server without a client method (or a method whose route was removed) fails here.
Each mapped method is then called on a client over a recording transport, and the request it
sends must be exactly its route's method and path.
"""

from __future__ import annotations

import inspect
import re
from typing import Any

import httpx
import pytest

from app.client import ArmClient, ArmServerError, AsyncArmClient
from app.web.factory import create_app

#: (HTTP method, OpenAPI path) -> client method name. Path parameter names are ignored.
ROUTES: dict[tuple[str, str], str] = {
    ("GET", "/api/v1/health"): "health",
    ("GET", "/api/v1/arms"): "arms",
    ("GET", "/api/v1/arms/{arm}"): "arm",
    ("GET", "/api/v1/arms/{arm}/state"): "state",
    ("POST", "/api/v1/arms/{arm}/move/joints"): "move_joints",
    ("POST", "/api/v1/arms/{arm}/move/pose"): "move_pose",
    ("POST", "/api/v1/arms/{arm}/plan/joints"): "plan_joints",
    ("POST", "/api/v1/arms/{arm}/plan/pose"): "plan_pose",
    ("GET", "/api/v1/arms/{arm}/motions/{id}"): "motion",
    ("DELETE", "/api/v1/arms/{arm}/motions/{id}"): "cancel_motion",
    ("POST", "/api/v1/arms/{arm}/stop"): "stop",
    ("POST", "/api/v1/arms/{arm}/estop"): "estop",
    ("DELETE", "/api/v1/arms/{arm}/estop"): "release_estop",
    ("POST", "/api/v1/arms/{arm}/gripper"): "gripper",
    ("POST", "/api/v1/arms/{arm}/force/tare"): "tare_force",
    ("DELETE", "/api/v1/arms/{arm}/force/tare"): "clear_tare",
    ("POST", "/api/v1/arms/{arm}/kinematics/forward"): "forward",
    ("POST", "/api/v1/arms/{arm}/kinematics/inverse"): "inverse",
    ("POST", "/api/v1/arms/{arm}/kinematics/inverse-velocity"): "inverse_velocity",
    ("GET", "/api/v1/arms/{arm}/workspace"): "workspace",
    ("POST", "/api/v1/arms/{arm}/rbe3001/set-pid"): "rbe3001_set_pid",
    ("GET", "/api/v1/arms/{arm}/rbe3001/status"): "rbe3001_status",
    ("POST", "/api/v1/arms/{arm}/rbe3001/set-gain"): "rbe3001_set_gain",
    ("POST", "/api/v1/arms/{arm}/rbe3001/set-claw"): "rbe3001_set_claw",
    ("POST", "/api/v1/arms/{arm}/dynamixel/ping"): "dxl_ping",
    ("GET", "/api/v1/arms/{arm}/dynamixel/{id}/registers/{name}"): "dxl_read_register",
    ("PUT", "/api/v1/arms/{arm}/dynamixel/{id}/registers/{name}"): "dxl_write_register",
    ("POST", "/api/v1/arms/{arm}/dynamixel/sync-read"): "dxl_sync_read",
    ("POST", "/api/v1/arms/{arm}/dynamixel/sync-write"): "dxl_sync_write",
    ("POST", "/api/v1/arms/{arm}/dynamixel/{id}/reboot"): "dxl_reboot",
    ("POST", "/api/v1/arms/{arm}/home"): "home",
    ("DELETE", "/api/v1/arms/{arm}/home"): "unhome",
    ("PUT", "/api/v1/arms/{arm}/torque"): "set_torque",
    ("GET", "/api/v1/arms/{arm}/calibration"): "calibration",
    ("POST", "/api/v1/arms/{arm}/calibration"): "calibrate",
    ("DELETE", "/api/v1/arms/{arm}/calibration"): "forget_calibration",
    ("POST", "/api/v1/arms/{arm}/calibration/gravity"): "calibrate_gravity",
    ("POST", "/api/v1/arms/{arm}/lease"): "take_lease",
    ("PUT", "/api/v1/arms/{arm}/lease/{id}"): "renew_lease",
    ("DELETE", "/api/v1/arms/{arm}/lease/{id}"): "release_lease",
    ("GET", "/api/v1/arms/{arm}/safety"): "safety",
    ("PUT", "/api/v1/arms/{arm}/safety"): "set_safety",
    ("GET", "/api/v1/arms/{arm}/world"): "world",
    ("PUT", "/api/v1/arms/{arm}/world"): "set_world",
    ("PUT", "/api/v1/arms/{arm}/world/hand"): "move_hand",
    ("DELETE", "/api/v1/arms/{arm}/world/hand"): "let_go_hand",
    ("POST", "/api/v1/teleop"): "start_teleop",
    ("GET", "/api/v1/teleop"): "teleop_sessions",
    ("POST", "/api/v1/arms/{arm}/replay"): "replay",
    ("DELETE", "/api/v1/teleop/{id}"): "stop_teleop",
    ("GET", "/api/v1/me"): "me",
    ("POST", "/api/v1/arms/{arm}/queue"): "join_queue",
    ("GET", "/api/v1/arms/{arm}/queue"): "queue",
    ("PUT", "/api/v1/arms/{arm}/queue"): "reorder_queue",
    ("DELETE", "/api/v1/arms/{arm}/queue"): "clear_queue",
    ("GET", "/api/v1/arms/{arm}/queue/{id}"): "queue_entry",
    ("DELETE", "/api/v1/arms/{arm}/queue/{id}"): "leave_queue",
    ("DELETE", "/api/v1/arms/{arm}/lease"): "revoke_lease",
    ("GET", "/api/v1/audit"): "audit",
    ("GET", "/api/v1/recordings"): "recordings",
    ("GET", "/api/v1/recordings/{id}"): "recording",
    ("POST", "/api/v1/recordings"): "create_recording",
    ("POST", "/api/v1/recordings/{id}/episodes"): "start_episode",
    ("POST", "/api/v1/recordings/{id}/episodes/stop"): "stop_episode",
    ("DELETE", "/api/v1/recordings/{id}/episodes/current"): "discard_episode",
    ("GET", "/api/v1/recordings/{id}/archive"): "recording_archive",
    ("GET", "/api/v1/cameras"): "cameras",
    ("GET", "/api/v1/cameras/{cam}"): "camera",
    ("GET", "/api/v1/cameras/{cam}/frame.jpg"): "camera_frame",
    ("GET", "/api/v1/cameras/{cam}/stream"): "camera_stream",
    ("GET", "/api/v1/cameras/{cam}/detections"): "detections",
    ("GET", "/api/v1/cameras/{cam}/calibration"): "camera_calibration",
    ("POST", "/api/v1/cameras/{cam}/calibration"): "calibrate_camera",
    ("GET", "/api/v1/setup-servos"): "servo_setup",
    ("POST", "/api/v1/setup-servos/scan"): "scan_servos",
    ("POST", "/api/v1/setup-servos/assign"): "assign_servo",
    ("POST", "/api/v1/setup-servos/practice"): "start_practice_bus",
    ("POST", "/api/v1/setup-servos/practice/servos"): "plug_practice_servo",
    ("DELETE", "/api/v1/setup-servos/practice"): "stop_practice_bus",
}

#: Routes outside OpenAPI (WebSocket) and helpers built on routes: method -> what it uses.
EXTRA = {
    "telemetry": "WS /api/v1/arms/{arm}/telemetry",
    "telemetry_messages": "WS /api/v1/arms/{arm}/telemetry",
    "wait_motion": "GET /api/v1/arms/{arm}/motions/{id} (polled)",
    "hold_lease": "POST/PUT/DELETE /api/v1/arms/{arm}/lease",
    "queue_turn": "POST/GET/DELETE /api/v1/arms/{arm}/queue, PUT/DELETE .../lease",
    "audit_csv": "GET /api/v1/audit (Accept: text/csv)",
}

#: Arguments to call each method with over the recording transport.
ARGS: dict[str, tuple[Any, ...]] = {
    "health": (), "arms": (), "arm": ("a1",), "state": ("a1",),
    "move_joints": ("a1", [0.1, 0.2, 0.3]), "move_pose": ("a1", 0.1, 0.0, 0.2),
    "plan_joints": ("a1", [0.1, 0.2, 0.3]), "plan_pose": ("a1", 0.1, 0.0, 0.2),
    "motion": ("a1", "m1"), "cancel_motion": ("a1", "m1"), "stop": ("a1",),
    "estop": ("a1",), "release_estop": ("a1",), "gripper": ("a1", 0.5),
    "forward": ("a1", [0.1, 0.2, 0.3]), "inverse": ("a1", 0.1, 0.0, 0.2),
    "inverse_velocity": ("a1", [0.1, 0.2, 0.3], [0.01, 0.0, 0.0]),
    "workspace": ("a1",), "rbe3001_set_pid": ("a1", [0, 0, 0]), "rbe3001_status": ("a1",),
    "rbe3001_set_gain": ("a1", 0, 1.0, 0.0, 0.0), "rbe3001_set_claw": ("a1", 1.0),
    "dxl_ping": ("a1",), "dxl_read_register": ("a1", 3, "led"),
    "dxl_write_register": ("a1", 3, "led", 1), "dxl_sync_read": ("a1", "led", [1, 2]),
    "dxl_sync_write": ("a1", "led", {1: 0}), "dxl_reboot": ("a1", 3), "home": ("a1",),
    "unhome": ("a1",), "set_torque": ("a1", False),
    "calibration": ("a1",), "calibrate": ("a1", None, "jig"), "forget_calibration": ("a1",),
    "calibrate_gravity": ("a1",),
    "take_lease": ("a1",),
    "renew_lease": ("a1", "L1"), "release_lease": ("a1", "L1"),
    "safety": ("a1",), "set_safety": ("a1",),
    "world": ("a1",), "set_world": ("a1", {"objects": [], "bins": []}),
    "move_hand": ("a1", [0.0, 0.0]), "let_go_hand": ("a1",),
    "tare_force": ("a1",), "clear_tare": ("a1",),
    "start_teleop": ("a1", "a2"), "teleop_sessions": (), "stop_teleop": ("t1",),
    "replay": ("a1", "r1", 0),
    "me": (), "join_queue": ("a1",), "queue": ("a1",), "reorder_queue": ("a1", ["e1"]),
    "clear_queue": ("a1",), "queue_entry": ("a1", "e1"), "leave_queue": ("a1", "e1"),
    "revoke_lease": ("a1",), "audit": (),
    "recordings": (), "recording": ("r1",), "create_recording": ("r1", ["a1"]),
    "start_episode": ("r1",), "stop_episode": ("r1",), "discard_episode": ("r1",),
    "recording_archive": ("r1",),
    "cameras": (), "camera": ("c1",), "camera_frame": ("c1",), "camera_stream": ("c1",),
    "detections": ("c1",), "camera_calibration": ("c1",),
    "calibrate_camera": ("c1", [((0, 0), (0.1, 0, 0))] * 4),
    "servo_setup": (), "scan_servos": ("socket://127.0.0.1:1", "p1"),
    "assign_servo": ("socket://127.0.0.1:1", "p1", "j1"), "start_practice_bus": (),
    "plug_practice_servo": (), "stop_practice_bus": (),
}


def _norm(path: str) -> str:
    return re.sub(r"\{[^}]+\}", "{}", path)


def _served() -> set[tuple[str, str]]:
    spec = create_app().openapi()
    return {(method.upper(), _norm(path)) for path, ops in spec["paths"].items()
            for method in ops if method.upper() in {"GET", "POST", "PUT", "DELETE", "PATCH"}}


def test_every_route_has_a_client_method_and_back() -> None:
    served = _served()
    mapped = {(m, _norm(p)) for m, p in ROUTES}
    assert not served - mapped, f"routes without a client method: {sorted(served - mapped)}"
    assert not mapped - served, f"client methods without a route: {sorted(mapped - served)}"
    assert len(set(ROUTES.values())) == len(ROUTES), "one method per route"


@pytest.mark.parametrize("cls", [ArmClient, AsyncArmClient])
def test_every_mapped_method_exists(cls: type) -> None:
    for name in [*ROUTES.values(), *EXTRA]:
        assert callable(getattr(cls, name, None)), f"{cls.__name__}.{name} is missing"


def test_sync_and_async_clients_have_the_same_methods() -> None:
    def public(cls: type) -> set[str]:
        return {n for n, _ in inspect.getmembers(cls, callable) if not n.startswith("_")}
    assert public(ArmClient) - {"close"} == public(AsyncArmClient) - {"aclose"}


def _recording() -> tuple[list[httpx.Request], httpx.MockTransport]:
    seen: list[httpx.Request] = []

    def handler(request: httpx.Request) -> httpx.Response:
        seen.append(request)
        return httpx.Response(418, json={"detail": "recorded", "code": "recorded"})
    return seen, httpx.MockTransport(handler)


def _matches(route: tuple[str, str], request: httpx.Request) -> bool:
    method, path = route
    pattern = "^" + re.sub(r"\\\{[^}]+\\\}", "[^/]+", re.escape(path)) + "$"
    return request.method == method and re.match(pattern, request.url.path) is not None


def test_each_method_sends_its_route() -> None:
    seen, transport = _recording()
    with ArmClient("http://armserver.test", transport=transport) as c:
        for route, name in ROUTES.items():
            seen.clear()
            with pytest.raises(ArmServerError) as info:
                getattr(c, name)(*ARGS[name])
            assert info.value.code == "recorded"
            assert len(seen) == 1, f"{name} sent {len(seen)} requests"
            assert _matches(route, seen[0]), (
                f"{name} sent {seen[0].method} {seen[0].url.path}, not {route}")


async def test_each_async_method_sends_its_route() -> None:
    seen, transport = _recording()
    async with AsyncArmClient("http://armserver.test", transport=transport) as c:
        for route, name in ROUTES.items():
            seen.clear()
            with pytest.raises(ArmServerError):
                await getattr(c, name)(*ARGS[name])
            assert len(seen) == 1 and _matches(route, seen[0]), (name, seen)


# ------------------------------------------------------------ the sync client is made, not mirrored


def _public(cls: type) -> dict[str, Any]:
    return {n: f for n, f in vars(cls).items() if not n.startswith("_") and callable(f)}


def test_each_sync_method_is_made_from_the_async_one() -> None:
    for name, fn in _public(AsyncArmClient).items():
        if name == "aclose":
            continue
        twin = getattr(ArmClient, name)
        assert twin.__wrapped__ is fn, name  # made by app.client.sync, not written by hand
        assert inspect.signature(twin) == inspect.signature(fn), name
        assert twin.__doc__ == fn.__doc__, name
        assert twin.__name__ == name and twin.__module__ == fn.__module__


def test_a_new_async_method_without_its_twin_is_reported() -> None:
    from app.client.sync import missing_twins

    assert missing_twins(AsyncArmClient, ArmClient) == []

    class Grown(AsyncArmClient):
        async def new_route(self) -> None:
            """A route added to the async client only."""

    assert missing_twins(Grown, ArmClient) == ["new_route"]


def test_the_client_package_has_no_import_cycle() -> None:
    """Within app/client/ (and to app.errors): each module's imports, followed, never return."""
    import ast
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    graph: dict[str, set[str]] = {}
    for path in sorted((root / "app" / "client").glob("*.py")):
        mod = "app.client" + ("" if path.stem == "__init__" else "." + path.stem)
        deps: set[str] = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                if node.module.startswith("app.client") and node.module != mod:
                    deps.add(node.module)
        graph[mod] = deps
    assert {"app.client.aio", "app.client.sync", "app.client.core"} <= set(graph)
    assert "app.client.sync" not in graph["app.client.aio"]

    def reaches(start: str, goal: str, seen: set[str]) -> bool:
        for dep in graph.get(start, ()):
            if dep == goal or (dep not in seen and reaches(dep, goal, seen | {dep})):
                return True
        return False
    cyclic = [m for m in graph if m != "app.client" and reaches(m, m, set())]
    assert not cyclic, cyclic
