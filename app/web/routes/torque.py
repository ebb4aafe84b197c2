"""The joints' torque (an addition to API.md): off, the arm free to be moved by hand (a
demonstration shown by hand, a leader on another worker of a lab freed for teleoperation),
or on again, holding where the hand left it (`ArmService.set_torque`)."""

from __future__ import annotations

from fastapi import APIRouter, Request

from app import schemas as s
from app.classroom.lease import LeaseManager
from app.errors import Busy
from app.safety.falling import falling_refusal
from app.web.deps import LeaseId, OperatorArm, OperatorCaller
from app.web.routes.common import DEVICE, errors
from app.web.routes.teleop import sessions_of
from app.web.security import Role

router = APIRouter(prefix="/arms/{arm}", tags=["arm state"])


@router.put(
    "/torque",
    response_model=s.TorqueState,
    summary="Switch the joints' torque off (moved by hand) or on again (holding)",
    description="Body `{\"on\": false}`: every joint's torque off, the arm free to be moved by "
    "hand, its positions still sampled; `{\"on\": true}`: on again, each joint holding where "
    "it is (its goal written as its present position first, so it does not go back to an "
    "older one). Neither is refused by the emergency stop's latch: torque off is the safe "
    "write, and torque on moves nothing. Torque off is 409 `in_use` where joints fall without "
    "torque (the profile's `falls_without_torque`: the angler's z winch, an "
    "OpenManipulator-X's shoulder, elbow and wrist) unless the body says `\"load_supported\": "
    "true` (held by hand, or resting) or the profile allows raw access, as a reboot's. 409 "
    "`busy` while a motion runs or is queued, or while the arm leads or follows a "
    "teleoperation session of this server (the session switches a leader's torque itself); "
    "409 `not_supported` where the device has no torque switch (the rbe3001). Operator token; "
    "torque off also the arm's lease (X-Arm-Lease; 409 `leased`), torque on not: holding "
    "where it is, like the emergency stop's hold, is open to every operator (and a session "
    "that freed a leader on another worker gives its torque back whoever holds its lease by "
    "then). A `torque` event tells the arm's subscribers.",
    responses=errors(*DEVICE),
)
async def set_torque(svc: OperatorArm, who: OperatorCaller, request: Request,
                     req: s.TorqueRequest, x_arm_lease: LeaseId = None) -> s.TorqueState:
    if not req.on:  # the arm goes limp: a command to it like a move, under its lease
        leases: LeaseManager = request.app.state.leases
        await leases.check(svc.name, x_arm_lease, gated=who.role < Role.INSTRUCTOR)
    session = sessions_of(request).running_with(svc.name)
    if session is not None:
        raise Busy(f"{svc.name} is in teleoperation session {session.id} ({session.leader.name} "
                   f"drives {session.follower.name}), which switches a leader's torque itself: "
                   f"stop it first (DELETE /api/v1/teleop/{session.id})")
    falls = svc.profile.falling_joints
    if not req.on and falls and not req.load_supported:
        raise falling_refusal(svc.name, falls, "this request")
    await svc.set_torque(req.on)
    return s.TorqueState(arm=svc.name, on=req.on)
