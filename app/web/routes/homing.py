"""Homing: declare an arm's current physical pose (API.md "Faults and homing").

Joints whose zero is lost at power-up (the profile's `needs_homing`: the angler's multi-turn
screws and winch) start not homed on a real link, and moves that would move them are refused
with 409 `not_homed` until this route says where the arm is.
"""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Body

from app import schemas as s
from app.web.deps import ControlArm, OperatorRole
from app.web.routes.common import errors
from app.web.security import Role

router = APIRouter(prefix="/arms/{arm}", tags=["faults and homing"])


@router.post(
    "/home",
    response_model=s.ArmDetail,
    summary="Declare the arm's current physical pose (homing)",
    description="Body `{\"positions\": [...]}` (rad, m; one per joint), or no body for the "
    "profile's home pose: the joints that need homing take these positions as where they are "
    "now (nothing moves); joints with absolute encoders keep their reading. Answers the arm "
    "detail with `homed` all true. 409 `already_homed` on an arm whose joints are all homed "
    "(a new declaration would move its limits and zones) unless the token is an instructor's "
    "or the arm was un-homed first (DELETE .../home); 409 `busy` while a motion runs or is "
    "queued, 422 `joint_limit` / `invalid_request` for positions outside the limits or of the "
    "wrong length, 503 `link_down` without a fresh reading. Operator token.",
    responses=errors(401, 403, 404, 409, 422, 503),
)
async def home(svc: ControlArm, role: OperatorRole,
               req: Annotated[s.HomeRequest | None, Body()] = None) -> s.ArmDetail:
    return await svc.home(req.positions if req is not None else None,
                          rehome=role >= Role.INSTRUCTOR)


@router.delete(
    "/home",
    response_model=s.ArmDetail,
    summary="Un-home the arm on purpose",
    description="The joints that need homing forget their zero (`homed` false): moves that "
    "would move them are refused with 409 `not_homed` until POST .../home declares the pose "
    "again. Nothing moves. 409 `busy` while a motion runs or is queued. Operator token.",
    responses=errors(401, 403, 404, 409, 422),
)
async def unhome(svc: ControlArm) -> s.ArmDetail:
    return await svc.unhome()
