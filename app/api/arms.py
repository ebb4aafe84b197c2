"""Health, the list of arms, one arm's description and its latest state."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, FastAPI, Request, Response
from starlette.routing import BaseRoute, Match, NoMatchFound
from starlette.types import Receive, Scope, Send

from app import schemas as s
from app.api.common import READ, errors
from app.auth import bearer_token
from app.deps import ServicesDep, SettingsDep, ViewerArm, ViewerRole

router = APIRouter(tags=["arms"])


@router.get(
    "/health",
    response_model=s.Health,
    summary="Liveness and per-arm link state",
    description="Open to everyone (no token needed). `status` is `ok` when every arm's link "
    "is up and the store takes writes, `degraded` otherwise; the server itself answers either "
    "way.",
)
async def health(services: ServicesDep, settings: SettingsDep, request: Request) -> s.Health:
    links = {name: svc.link_status() for name, svc in services.items()}
    ok = all(link.connected for link in links.values())
    db = getattr(request.app.state, "store", None)
    store = s.StoreStatus(**vars(db.health())) if db is not None else None
    ok = ok and (store is None or store.ok)
    bridge = getattr(request.app.state, "mqtt", None)
    mqtt = s.MqttStatus.model_validate(bridge.status()) if bridge is not None else None
    return s.Health(status="ok" if ok else "degraded", arms=links, auth=settings.auth_enabled,
                    store=store, mqtt=mqtt)


@router.get(
    "/arms",
    response_model=list[s.ArmSummary],
    summary="List the hosted arms",
    description="Name, model, link and capabilities of every arm this server hosts.",
    responses=errors(401),
)
async def list_arms(_: ViewerRole, services: ServicesDep) -> list[s.ArmSummary]:
    return [svc.summary() for svc in services.values()]


@router.get(
    "/arms/{arm}",
    response_model=s.ArmDetail,
    summary="Describe one arm",
    description="Joints (name, revolute/prismatic, limits in rad or m), link (kind, address, "
    "connected, last error), capabilities (gripper, force sensing), estop latch, poll rate.",
    responses=errors(*READ),
)
async def arm_detail(svc: ViewerArm) -> s.ArmDetail:
    return svc.detail()


@router.get(
    "/arms/{arm}/state",
    response_model=s.Sample,
    summary="Latest telemetry sample",
    description="The device's latest sample, in the same shape as a WebSocket sample: joint "
    "positions (rad/m) and velocities, tip and tip velocity (m, m/s), torques and tip force "
    "where sensed, gripper, motion, estop, link. 503 `link_down` until the device has answered "
    "once; afterwards a lost link shows as `link` and `stale`.",
    responses=errors(*READ, 503),
)
async def arm_state(svc: ViewerArm) -> Response:
    svc.state()  # 503 link_down before the first sample
    # The hub encoded this sample once at publish time; answer those bytes as they are.
    return Response(content=svc.hub.latest_bytes, media_type="application/json")


class StateFastPath(BaseRoute):
    """`GET {prefix}/arms/{arm}/state` answered straight from the hub's encoded bytes.

    The state route is the hot read: this route, ahead of the others, takes only a request the
    regular route would answer 200 (a valid token where tokens are on, a known arm with a
    sample) and sends the bytes the hub encoded at publish time, with none of FastAPI's
    per-request work (dependency solving, request objects). Anything else falls through to
    `arm_state` above, which answers the errors and documents the route in OpenAPI. The
    middleware (limits, Host and Origin checks, token gate) runs before either."""

    def __init__(self, prefix: str) -> None:
        self.head = prefix + "/arms/"

    def matches(self, scope: Scope) -> tuple[Match, Scope]:
        if scope["type"] != "http" or scope.get("method") != "GET":
            return Match.NONE, {}
        path: str = scope["path"]
        if not (path.startswith(self.head) and path.endswith("/state")):
            return Match.NONE, {}
        name = path[len(self.head):-len("/state")]
        state = scope["app"].state
        svc = state.services.get(name) if 0 < len(name) <= 64 else None
        body = svc.hub.latest_bytes if svc is not None else None
        if body is None:
            return Match.NONE, {}
        access = state.access
        if access.enabled:
            header = _header(scope, b"authorization")
            if access.role_of(bearer_token(header)) is None:
                return Match.NONE, {}
        return Match.FULL, {"armserver.state": body}

    async def handle(self, scope: Scope, receive: Receive, send: Send) -> None:
        body: bytes = scope["armserver.state"]
        await send({"type": "http.response.start", "status": 200,
                    "headers": [(b"content-length", str(len(body)).encode()),
                                (b"content-type", b"application/json")]})
        await send({"type": "http.response.body", "body": body})

    def url_path_for(self, name: str, /, **path_params: Any) -> Any:
        raise NoMatchFound(name, path_params)


def _header(scope: Scope, name: bytes) -> str | None:
    for key, value in scope.get("headers", ()):
        if key == name:
            return value.decode("latin-1")  # type: ignore[no-any-return]  # ASGI: bytes
    return None


def install_fast_paths(app: FastAPI, prefix: str) -> None:
    """Put the hot read routes ahead of every other route (see StateFastPath)."""
    app.router.routes.insert(0, StateFastPath(prefix))
