"""The control lease of an arm: take, renew (heartbeat), release (app/classroom/lease.py has the
rules)."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Path, Response, status

from app import schemas as s
from app.web.deps import LeasesDep, OperatorArm
from app.web.routes.common import READ, errors

router = APIRouter(prefix="/arms/{arm}/lease", tags=["lease"])

LeaseId = Annotated[str, Path(max_length=128, description="the lease id")]


@router.post(
    "",
    response_model=s.Lease,
    status_code=status.HTTP_201_CREATED,
    summary="Take the arm's control lease",
    description="Operator token. While held, requests that move the arm or send protocol "
    "commands must carry `X-Arm-Lease: <id>` (others get 409 `leased`); the emergency stop "
    "stays open to everyone authenticated. Renew before `expires` (every `ttl`/3 s is safe): a "
    "lapsed lease brings the arm to a controlled stop and sends a `lease_expired` event. "
    "409 `leased` while another lease is held.",
    responses=errors(*READ, 403, 409),
)
async def take(svc: OperatorArm, leases: LeasesDep) -> s.Lease:
    return await leases.acquire(svc.name)


@router.put(
    "/{lease_id}",
    response_model=s.Lease,
    summary="Renew the lease (heartbeat)",
    description="Extends the lease by its ttl from now. 404 `unknown_lease` for an id that is "
    "not the arm's current lease (released or lapsed).",
    responses=errors(*READ, 403),
)
async def renew(svc: OperatorArm, leases: LeasesDep, lease_id: LeaseId) -> s.Lease:
    return await leases.renew(svc.name, lease_id)


@router.delete(
    "/{lease_id}",
    status_code=status.HTTP_204_NO_CONTENT,
    response_class=Response,
    summary="Release the lease",
    description="Frees the arm for other clients; the arm keeps doing what it does. 404 "
    "`unknown_lease` for an id that is not the arm's current lease.",
    responses=errors(*READ, 403),
)
async def release(svc: OperatorArm, leases: LeasesDep, lease_id: LeaseId) -> Response:
    await leases.release(svc.name, lease_id)
    return Response(status_code=status.HTTP_204_NO_CONTENT)
