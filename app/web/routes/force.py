"""Force tare (API.md "Force"): make the current joint torques the zero of `torques` and
`tip_force`, or clear that. The arm detail's `force` says what the readings are worth."""

from __future__ import annotations

from fastapi import APIRouter

from app import schemas as s
from app.web.deps import ControlArm
from app.web.routes.common import errors

router = APIRouter(tags=["force"])

_DOC = (" 409 `no_force_sensing` on an arm that senses no joint torques; 409 `leased` while "
        "another client holds the lease.")


@router.post(
    "/arms/{arm}/force/tare",
    response_model=s.ForceTare,
    summary="Tare the joint torques",
    description="The current joint torques (as sensed, before any earlier tare) become the zero "
    "of `torques` and `tip_force` in every sample until the next tare, a DELETE or a restart. "
    "Answers the offsets (N m, or N on a prismatic joint). 503 `link_down` when there is no "
    "fresh reading to tare against." + _DOC,
    responses=errors(401, 403, 404, 409, 422, 503),
)
async def tare(svc: ControlArm) -> s.ForceTare:
    return await svc.tare_force()


@router.delete(
    "/arms/{arm}/force/tare",
    response_model=s.ForceTare,
    summary="Clear the tare",
    description="Readings are published as sensed again; answers `offsets: null`." + _DOC,
    responses=errors(401, 403, 404, 409, 422),
)
async def clear_tare(svc: ControlArm) -> s.ForceTare:
    return await svc.clear_tare()
