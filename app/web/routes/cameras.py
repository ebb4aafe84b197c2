"""Cameras: the list, one camera, its latest frame and MJPEG stream, colour detections and the
camera-to-table calibration (API.md "Cameras (v1.2)"; the cameras live in app/cameras).

Viewers read everything; a calibration is an operator's, under the lease of the camera's arm
while one is held (it is fitted from positions the arm's tip was jogged to).
"""

from __future__ import annotations

from typing import Annotated, cast

import numpy as np
from fastapi import APIRouter, Header, Path, Query, Request, Response
from fastapi.responses import StreamingResponse

from app import schemas as s
from app.cameras.camera import Camera
from app.cameras.hub import CameraHub
from app.cameras.mjpeg import BOUNDARY
from app.classroom.lease import LeaseManager
from app.errors import NotFound
from app.web.deps import Credentials, ViewerRole, get_access
from app.web.routes.common import READ, errors
from app.web.security import Role

router = APIRouter(prefix="/cameras", tags=["cameras"])

CamName = Annotated[str, Path(description="camera name, as in GET /api/v1/cameras",
                              max_length=64)]
#: Errors of a route that needs frames.
FRAMES = (*READ, 503)


def _hub(request: Request) -> CameraHub:
    hub = getattr(request.app.state, "cameras", None)
    if hub is None:
        raise NotFound("this server has no cameras (not started)")
    return cast(CameraHub, hub)


def summary(hub: CameraHub, cam: Camera) -> s.CameraSummary:
    c = cam.config
    return s.CameraSummary(name=cam.name, arm=c.arm, kind=c.kind, width=c.width,
                           height=c.height, fps=c.fps, up=cam.up,
                           calibrated=cam.name in hub.calibrations)


@router.get("", response_model=list[s.CameraSummary], summary="List the cameras",
            description="Every camera: name, arm, source kind, size, fps, up, calibrated.",
            responses=errors(401))
async def list_cameras(_: ViewerRole, request: Request) -> list[s.CameraSummary]:
    hub = _hub(request)
    return [summary(hub, cam) for cam in hub.cameras.values()]


@router.get("/{cam}", response_model=s.CameraDetail, summary="Describe one camera",
            description="With its source, last error (why it is down), frame counter and the "
            "colours it detects.", responses=errors(*READ))
async def camera_detail(_: ViewerRole, request: Request, cam: CamName) -> s.CameraDetail:
    hub = _hub(request)
    c = hub.get(cam)
    return s.CameraDetail(**summary(hub, c).model_dump(), source=c.config.source,
                          last_error=c.last_error, frame_seq=c.frames, connects=c.connects,
                          colors=list(c.config.palette()),
                          streaming_clients=hub.feed(cam).clients)


@router.get("/{cam}/frame.jpg", response_class=Response, summary="The latest frame (JPEG)",
            description="`image/jpeg`, header `X-Frame-Seq`: the frame's number. Encoded once "
            "per frame however many clients ask. 503 `camera_down` with the last error while "
            "the camera is down.",
            responses={**errors(*FRAMES), 200: {"content": {"image/jpeg": {}}}})
async def frame_jpg(_: ViewerRole, request: Request, cam: CamName) -> Response:
    seq, data = await _hub(request).jpeg(cam)
    return Response(data, media_type="image/jpeg",
                    headers={"X-Frame-Seq": str(seq), "Cache-Control": "no-store"})


@router.get("/{cam}/stream", response_class=StreamingResponse, summary="MJPEG stream",
            description=f"`multipart/x-mixed-replace; boundary={BOUNDARY}`: each part a JPEG "
            "with `Content-Length` and `X-Frame-Seq`. One producer per camera; a slow client "
            "drops frames (it gets the newest), none is buffered for it.",
            responses={**errors(*FRAMES),
                       200: {"content": {f"multipart/x-mixed-replace; boundary={BOUNDARY}": {}}}})
async def stream(_: ViewerRole, request: Request, cam: CamName) -> StreamingResponse:
    parts = await _hub(request).stream(cam)
    return StreamingResponse(parts, media_type=f"multipart/x-mixed-replace; boundary={BOUNDARY}",
                             headers={"Cache-Control": "no-store"})


@router.get("/{cam}/detections", response_model=s.Detections,
            summary="Objects of a colour in the latest frame",
            description="HSV thresholds, morphological open and close, connected components, a "
            "minimum area: each object's centroid, area, bounding box and (once the camera is "
            "calibrated) its position on the table in the arm's base frame; largest first. "
            "All colours without `color`. `took_ms`: the detection's own time.",
            responses=errors(*FRAMES, 409))
async def detections(
    _: ViewerRole, request: Request, cam: CamName,
    color: Annotated[str | None, Query(max_length=32, description="a colour name (default: "
                                       "all the camera knows)")] = None,
    min_area: Annotated[int, Query(ge=1, le=100_000_000, description="smallest object, px")]
    = 50,
) -> s.Detections:
    hub = _hub(request)
    frame, blobs, xy, took = await hub.detect(cam, [color] if color else None, min_area)
    cal = hub.calibrations.get(cam)
    out = []
    for k, b in enumerate(blobs):
        pos = None
        if xy is not None and cal is not None:
            pos = s.Vec3(x=float(xy[k, 0]), y=float(xy[k, 1]), z=cal.z)
        out.append(s.Detection(color=b.color, pixel=s.Pixel(u=b.u, v=b.v), area=b.area,
                               bbox=b.bbox, position=pos))
    return s.Detections(camera=cam, frame_seq=frame.seq, time=frame.time,
                        took_ms=took * 1000.0, detections=out)


def _calibration(hub: CameraHub, cam: str) -> s.Calibration:
    hub.get(cam)
    cal = hub.calibrations.get(cam)
    if cal is None:
        return s.Calibration(camera=cam, calibrated=False)
    return s.Calibration(camera=cam, calibrated=True, **cal.as_dict())


@router.get("/{cam}/calibration", response_model=s.Calibration,
            summary="The camera's table calibration",
            description="The stored homography (table plane to image) and its reprojection "
            "error; `calibrated: false` before the first.", responses=errors(*READ))
async def get_calibration(_: ViewerRole, request: Request, cam: CamName) -> s.Calibration:
    return _calibration(_hub(request), cam)


@router.post("/{cam}/calibration", response_model=s.Calibration,
             summary="Fit the table calibration",
             description="From 4 or more correspondences: a pixel and the tip's position there "
             "on the table (base frame, m). Stored per camera and used at once. 422 "
             "`invalid_request` with the reason when degenerate (too few points, a point twice, "
             "collinear, not on one level table); nothing changes then. An operator, with the "
             "lease of the camera's arm while one is held.",
             responses=errors(401, 403, 404, 409, 422))
async def post_calibration(
    request: Request, cred: Credentials, cam: CamName, body: s.CalibrationRequest,
    x_arm_lease: Annotated[str | None, Header(max_length=128, description="the lease id of "
                                              "the camera's arm, while one is held")] = None,
) -> s.Calibration:
    who = get_access(request).require_identity(cred.credentials if cred else None,
                                               Role.OPERATOR)
    hub = _hub(request)
    camera = hub.get(cam)
    leases: LeaseManager = request.app.state.leases
    await leases.check(camera.config.arm, x_arm_lease, gated=who.role < Role.INSTRUCTOR)
    uv = np.array([[p.pixel.u, p.pixel.v] for p in body.points])
    xyz = np.array([[p.position.x, p.position.y, p.position.z] for p in body.points])
    await hub.calibrate(cam, uv, xyz)
    return _calibration(hub, cam)
