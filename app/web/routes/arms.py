"""Health, the list of arms, one arm's description and its latest state."""

from __future__ import annotations

import logging
from typing import Any

from fastapi import APIRouter, FastAPI, Request, Response
from starlette.types import ASGIApp, Receive, Scope, Send

from app import schemas as s
from app.web.deps import ServicesDep, SettingsDep, ViewerArm, ViewerRole
from app.web.hostguard import HostPolicy
from app.web.routes.common import READ, errors
from app.web.security import bearer_token_of

log = logging.getLogger(__name__)

#: Longest the estop fast path waits for the sample that shows its latch, s (the latch
#: publishes it at once; a bound all the same, the route waits longer for the hold).
ESTOP_SAMPLE_WAIT_S = 0.02


def _shows_estop(sample: dict[str, Any]) -> bool:
    return bool(sample.get("estop"))

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
    hub = getattr(request.app.state, "cameras", None)
    cams = {name: s.CameraStatus(up=up, last_error=err)
            for name, (up, err) in (hub.status().items() if hub is not None else ())}
    return s.Health(status="ok" if ok else "degraded", arms=links, auth=settings.auth_enabled,
                    store=store, mqtt=mqtt, cameras=cams)


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
    return Response(content=svc.latest_bytes, media_type="application/json")


class StateFastPath:
    """`GET {prefix}/arms/{arm}/state` answered straight from the hub's encoded bytes, as the
    outermost ASGI layer of the app.

    The state route is the hot read. This layer takes only a request the full stack would
    answer 200 and that nothing else would touch: no body, no `Origin` (CORS and the
    cross-origin checks are the full stack's), a Host the server answers to (open servers,
    `app.web.hostguard`), a valid token where tokens are on, a known arm with a sample; and it
    sends the bytes the hub encoded at publish time. Every other request goes down the stack
    as before: the middleware (audit, last-resort errors, CORS, Host and Origin, token gate,
    body limit) and `arm_state` above, which answers the errors and documents the route in
    OpenAPI. A request this layer answers is one the regular route would answer the same way
    (`tests/test_sample_pipeline.py` compares them), without crossing the six middleware
    layers, the router and FastAPI's dependency solving (profiled: about half of what a
    request cost the server before).

    It also presses the emergency stop early: a `POST .../estop` that passes the same checks
    latches here, on the request's head, then goes down the stack as any request (see
    `_press_estop`)."""

    def __init__(self, app: ASGIApp, app_ref: FastAPI, prefix: str, hosts: HostPolicy) -> None:
        self.app = app
        self.state = app_ref.state
        self.head = prefix + "/arms/"
        self.hosts = hosts

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        body = self._answer(scope) if scope["type"] == "http" else None
        if body is None:
            if scope["type"] == "http" and scope.get("method") == "POST":
                await self._press_estop(scope)
            await self.app(scope, receive, send)
            return
        await send({"type": "http.response.start", "status": 200,
                    "headers": [(b"content-length", str(len(body)).encode()),
                                (b"content-type", b"application/json")]})
        await send({"type": "http.response.body", "body": body})

    def _answer(self, scope: Scope) -> bytes | None:
        """The bytes to answer `scope` with, or None: the full stack answers it."""
        if scope.get("method") != "GET":
            return None
        svc = self._arm(scope, "/state", b"")
        return svc.latest_bytes if svc is not None else None

    async def _press_estop(self, scope: Scope) -> None:
        """`POST {prefix}/arms/{arm}/estop`, a request the estop route will accept (the same
        conditions as a state read, an empty body): latch now, on the head alone. The request
        then goes down the stack as any other (audited, answered by the route, whose own
        press finds the latch set and waits for the same hold): the stop does not wait for
        the six middleware layers, the router and FastAPI's dependency solving (about 0.5 ms
        of a request on the test machine). An estop is the one write worth it: latching
        early is always the safe side."""
        svc = self._arm(scope, "/estop", b"0")
        if svc is None or svc.estop:  # (a press on a latched estop changes nothing)
            return
        try:
            # This loop sends the telemetry: it waits (idle) for the sample that shows the
            # latch and sends it before it spends itself on the rest of this request (the
            # route answers after the hold anyway, later than that sample).
            await svc.sample_where(_shows_estop, ESTOP_SAMPLE_WAIT_S, svc.press_estop)
        except Exception:  # outside the error layers: the route's press still follows
            log.exception("estop fast path: the early press failed")
        finally:
            svc.pressed_sample_sent()  # the latch's record, after the sample (ArmService)

    def _arm(self, scope: Scope, tail: str, length: bytes) -> Any:
        """The arm of `{prefix}/arms/{arm}{tail}` if the full stack would let `scope` through
        to its route: no Origin (CORS and the cross-origin checks are the full stack's), a
        body of `length` bytes or none (b"": none), a Host the server answers to (open
        servers, `app.web.hostguard`), a valid token where tokens are on, a known arm; else None."""
        path: str = scope["path"]
        if not (path.startswith(self.head) and path.endswith(tail)):
            return None
        host = auth = None
        for key, value in scope.get("headers", ()):
            if key == b"host":
                host = value
            elif key == b"authorization":
                auth = value
            elif key == b"content-length" and value == length:
                continue
            elif key in _FULL_STACK_HEADERS:
                return None
        if self.hosts.enabled and not self.hosts.host_ok(
                host.decode("latin-1") if host is not None else None):
            return None
        access = self.state.access
        if access.enabled and access.role_of(
                bearer_token_of(auth)) is None:
            return None
        name = path[len(self.head):-len(tail)]
        return self.state.services.get(name) if 0 < len(name) <= 64 else None


#: Request headers that send a state read down the full stack: a body (the body limit), an
#: Origin or a fetch site (CORS and the cross-origin checks).
_FULL_STACK_HEADERS = frozenset({b"origin", b"sec-fetch-site", b"content-length",
                                 b"transfer-encoding"})


def install_fast_paths(app: FastAPI, prefix: str, hosts: HostPolicy) -> None:
    """Put the hot read outside every other layer (see StateFastPath): call it after the last
    `add_middleware` but HeadAsGet's (app/web/middleware.py), so that only that one is
    outside it."""
    app.add_middleware(StateFastPath, app_ref=app, prefix=prefix, hosts=hosts)
