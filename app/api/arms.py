"""Health, the list of arms, one arm's description and its latest state."""

from __future__ import annotations

from fastapi import APIRouter, Request, Response

from app import schemas as s
from app.api.common import READ, errors
from app.deps import ServicesDep, SettingsDep, ViewerArm, ViewerRole

router = APIRouter(tags=["arms"])


@router.get(
    "/health",
    response_model=s.Health,
    summary="Liveness and per-arm link state",
    description="Open to everyone (no token needed). `status` is `ok` when every arm's link "
    "is up, `degraded` otherwise; the server itself answers either way.",
)
async def health(request: Request, services: ServicesDep, settings: SettingsDep) -> s.Health:
    links = {name: svc.link_status() for name, svc in services.items()}
    ok = all(link.connected for link in links.values())
    bridge = getattr(request.app.state, "mqtt", None)
    mqtt = s.MqttStatus.model_validate(bridge.status()) if bridge is not None else None
    return s.Health(status="ok" if ok else "degraded", arms=links, auth=settings.auth_enabled,
                    mqtt=mqtt)


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
    return Response(content=svc.hub.latest_json, media_type="application/json")
