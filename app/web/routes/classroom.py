"""People, the classroom queue and the instructor's controls (API.md "People and roles",
"Queue and hand-off"; app/classroom/queue.py has the rules)."""

from __future__ import annotations

from typing import Annotated, cast

from fastapi import APIRouter, Depends, Path, Request, Response, status

from app import schemas as s
from app.classroom.queue import Classroom
from app.web.deps import (
    InstructorCaller,
    OperatorCaller,
    ServicesDep,
    ViewerCaller,
    lookup_arm,
)
from app.web.routes.common import READ, errors

router = APIRouter(tags=["classroom"])

EntryId = Annotated[str, Path(max_length=64, description="the queue entry's id")]
ArmName = Annotated[str, Path(max_length=64, description="arm name")]


async def get_classroom(request: Request) -> Classroom:
    return cast(Classroom, request.app.state.classroom)  # app.state is untyped: set in main


ClassroomDep = Annotated[Classroom, Depends(get_classroom)]


@router.get("/me", response_model=s.Me, summary="Who am I",
            description="The caller's name and role (never the token).", responses=errors(401))
async def me(who: ViewerCaller) -> s.Me:
    return s.Me(name=who.name, role=who.role.name.lower())


@router.post("/arms/{arm}/queue", response_model=s.QueueEntry,
             status_code=status.HTTP_201_CREATED, summary="Join the arm's queue",
             description="Operator token. Answers your entry; poll it (or watch the telemetry "
             "socket's `lease_offered` event) and, once `offered`, claim the lease by renewing "
             "it (PUT /lease/{lease_id}) within the claim window. 409 `already_queued` if you "
             "are in the queue already.", responses=errors(*READ, 403, 409))
async def join(who: OperatorCaller, services: ServicesDep, arm: ArmName,
               room: ClassroomDep) -> s.QueueEntry:
    svc = lookup_arm(services, arm)
    return room.join(svc.name, who)


@router.get("/arms/{arm}/queue", response_model=s.QueueStatus, summary="The arm's queue",
            description="The holder, the time left in their slot, the entries in order, and "
            "the hand-off state.", responses=errors(*READ))
async def queue_status(who: ViewerCaller, services: ServicesDep, arm: ArmName,
                       room: ClassroomDep) -> s.QueueStatus:
    return room.status(lookup_arm(services, arm).name, who)


@router.put("/arms/{arm}/queue", response_model=s.QueueStatus, summary="Reorder the queue",
            description="Instructor token. `order` names every waiting entry once; 422 "
            "`invalid_order` otherwise. The current holder keeps their slot.",
            responses=errors(*READ, 403))
async def reorder(who: InstructorCaller, services: ServicesDep, arm: ArmName,
                  body: s.QueueOrder, room: ClassroomDep) -> s.QueueStatus:
    return room.reorder(lookup_arm(services, arm).name, body.order, who)


@router.delete("/arms/{arm}/queue", response_model=s.QueueStatus, summary="Clear the queue",
               description="Instructor token. Every waiting entry ends `expired`; the current "
               "holder keeps their slot (revoke it with DELETE /lease).",
               responses=errors(*READ, 403))
async def clear(who: InstructorCaller, services: ServicesDep, arm: ArmName,
                room: ClassroomDep) -> s.QueueStatus:
    return room.clear(lookup_arm(services, arm).name, who)


@router.get("/arms/{arm}/queue/{entry_id}", response_model=s.QueueEntry,
            summary="One queue entry",
            description="`waiting`, `offered` (with the lease id, for its owner only), "
            "`holding`, `done`, `expired`. 404 `unknown_entry`.", responses=errors(*READ))
async def entry(who: ViewerCaller, services: ServicesDep, arm: ArmName, entry_id: EntryId,
                room: ClassroomDep) -> s.QueueEntry:
    return room.get(lookup_arm(services, arm).name, entry_id, who)


@router.delete("/arms/{arm}/queue/{entry_id}", response_model=s.QueueEntry,
               summary="Leave the queue",
               description="The entry's owner or an instructor. Leaving while offered or "
               "holding ends the lease (the arm is handed off to the next).",
               responses=errors(*READ, 403))
async def leave(who: OperatorCaller, services: ServicesDep, arm: ArmName, entry_id: EntryId,
                room: ClassroomDep) -> s.QueueEntry:
    return await room.leave(lookup_arm(services, arm).name, entry_id, who)


@router.delete("/arms/{arm}/lease", status_code=status.HTTP_204_NO_CONTENT,
               response_class=Response, summary="Revoke the arm's lease",
               description="Instructor token. Ends the current lease whoever holds it (the arm "
               "stops, `lease_expired` and `lease_ended` events), then hands the arm off to the "
               "next in the queue. With no lease held and a failed hand-off, tries the "
               "hand-off again.", responses=errors(*READ, 403))
async def revoke(who: InstructorCaller, services: ServicesDep, arm: ArmName,
                 room: ClassroomDep) -> Response:
    await room.revoke(lookup_arm(services, arm).name, who)
    return Response(status_code=status.HTTP_204_NO_CONTENT)
