"""The simulated world of a simulated arm (API.md "Simulated world"): read the scene, lay out a
new one. Any viewer reads; the arm's lease holder or an instructor replaces it. A real arm (or
a simulator on a pty or socket) has no world here: 404 `not_found`.

The world is the simulator's surroundings (app/sim/world.py), not the arm: a new scene moves
no joint. The hand (PUT .../world/hand, app/sim/hand.py) is the one part of the world that
touches the arm, as a person's hand does: it moves the simulated servos whose torque is off,
on the device's side of the link; the server reads where they went as it reads hardware.
"""

from __future__ import annotations

import asyncio
from typing import Annotated

from fastapi import APIRouter, Depends, Request, Response, status

from app import schemas as s
from app.errors import InvalidRequest, NotFound, NotSupported
from app.schemas.world import HandMoveRequest, HandState
from app.service import ArmService
from app.sim.hand import Hand
from app.sim.world import Bin, Scene, SceneError, World, WorldObject
from app.web.deps import ArmName, Credentials, LeaseId, ViewerArm, get_access, lookup_arm
from app.web.routes.common import READ, errors
from app.web.security import Role

router = APIRouter(prefix="/arms/{arm}/world", tags=["world"])


def world_of(svc: ArmService) -> World:
    w = svc.world
    if w is None:
        raise NotFound(f"{svc.name} has no simulated world: it is not simulated in this "
                       "server")
    return w


async def editor_arm(
    request: Request,
    cred: Credentials,
    arm: ArmName,
    x_arm_lease: LeaseId = None,
) -> ArmService:
    """An instructor's arm, or an operator's holding its lease (a scene is a lab set-up: a
    teacher lays one out whoever holds the arm)."""
    who = get_access(request).require_identity(
        cred.credentials if cred is not None else None, Role.OPERATOR)
    svc = lookup_arm(request.app.state.services, arm)
    if who.role < Role.INSTRUCTOR:
        await request.app.state.leases.check(svc.name, x_arm_lease)
    return svc


EditorArm = Annotated[ArmService, Depends(editor_arm)]


def to_body(scene: Scene) -> s.WorldScene:
    t = scene.table
    return s.WorldScene(
        objects=[s.WorldObject(id=o.id, kind=o.kind, color=o.color, held=o.held,
                               position=s.Vec3(x=o.position[0], y=o.position[1],
                                               z=o.position[2]))
                 for o in scene.objects],
        bins=[s.WorldBin(name=b.name, color=b.color,
                         min=s.Vec3(x=b.lo[0], y=b.lo[1], z=b.lo[2]),
                         max=s.Vec3(x=b.hi[0], y=b.hi[1], z=b.hi[2])) for b in scene.bins],
        table=s.WorldTable(x_min=t.x0, x_max=t.x1, y_min=t.y0, y_max=t.y1, z=t.z),
        tip=None if scene.tip is None else s.Vec3(x=scene.tip[0], y=scene.tip[1],
                                                  z=scene.tip[2]),
        gripper=scene.gripper)


@router.get(
    "",
    response_model=s.WorldScene,
    summary="The simulated arm's world",
    description="Objects (centre, m, base frame; `held` while in the end effector), bins "
    "(boxes on the table), the table, and where the simulated tip is. Simulated arms only: "
    "404 `not_found` on a real arm.",
    responses=errors(*READ),
)
async def get_world(svc: ViewerArm) -> s.WorldScene:
    # the world replays the device's readings since the last read: off the HTTP loop
    return to_body(await asyncio.to_thread(world_of(svc).scene))


@router.put(
    "",
    response_model=s.WorldScene,
    summary="Lay out a new scene (lease holder or instructor)",
    description="Replaces every object and bin; `held`, `table`, `tip` and `gripper` are not "
    "used, and each object settles on what is below it (a bin's floor or the table). Refused "
    "whole, nothing changed, with 422 `invalid_request` and the reason: an object off the "
    "table, an unknown colour, a kind the end effector cannot take (`ball`/`block` for a "
    "claw, `target` for a magnet), ids not unique, a bin off the table or with min not below "
    "max, a number that is not finite. Simulated arms only: 404 `not_found` on a real arm.",
    responses=errors(401, 403, 404, 409, 422),
)
async def put_world(svc: EditorArm, body: s.WorldScene) -> s.WorldScene:
    world = world_of(svc)
    objects = [WorldObject(o.id, o.kind, o.color, (o.position.x, o.position.y, o.position.z))
               for o in body.objects]
    bins = [Bin(b.name, b.color, (b.min.x, b.min.y, b.min.z), (b.max.x, b.max.y, b.max.z))
            for b in body.bins]
    try:
        return to_body(await asyncio.to_thread(world.set_scene, objects, bins))
    except SceneError as exc:
        raise InvalidRequest(str(exc)) from None


#: The longest a PUT of the hand with `wait` waits beyond the move's own time, s.
HAND_WAIT_S = 2.0
#: How often it looks whether the hand has arrived, s.
HAND_LOOK_S = 0.02


def hand_of(svc: ArmService) -> Hand:
    world_of(svc)  # 404 on a real arm
    hand = svc.hand
    if hand is None:
        raise NotSupported(f"{svc.name}'s simulated device has no servos a hand could move "
                           "(its joints have no torque switch)")
    return hand


@router.put(
    "/hand",
    response_model=HandState,
    summary="Move the simulated arm by hand (its servos' torque off)",
    description="A hand in the world moves the arm's joints, as a person moves an arm whose "
    "servos' torque is off (a teleoperation leader): in a straight line in joint space from "
    "where they are to `positions`, at `speed` on the joint with the longest way. It acts on "
    "the simulated servos (their Present Position and Velocity), never on the server: the "
    "server reads them over the link as from hardware. Only while the arm's torque is off "
    "(POST /api/v1/teleop with `free_leader`): a servo with torque on keeps its goal, so 409 "
    "`conflict` while any joint holds torque, and a joint whose torque comes on during a "
    "move is let go. A new move replaces one under way. 422 `invalid_request` (width, "
    "speed), 422 `joint_limit` (beyond the arm's joint limits); 409 `not_supported` for a "
    "simulated device without servos (the rbe3001's firmware); lease holder or instructor. "
    "Simulated arms only: 404 `not_found` on a real arm. With `wait: true` it answers when "
    "the hand has arrived or let go. The hand stays on the arm and holds it where it left it "
    "until DELETE: a joint that falls without torque (the profile's `falls_without_torque`) "
    "falls on the simulated bus while its torque is off and no hand holds it, as on "
    "hardware; without `positions` the hand takes hold where the arm is (moving nothing, so "
    "allowed with the torque on): hold a leader, then free it.",
    responses=errors(401, 403, 404, 409, 422),
)
async def put_hand(svc: EditorArm, body: HandMoveRequest) -> HandState:
    hand = hand_of(svc)
    goal = hand.here() if body.positions is None else body.positions
    move = hand.move_to(goal, body.speed)
    if body.wait:
        here = svc.positions
        way = (0.0 if here is None else
               float(max(abs(a - b) for a, b in zip(here, move.goal, strict=False))))
        for _ in range(int((way / move.speed + HAND_WAIT_S) / HAND_LOOK_S)):
            if not hand.busy(move.serial):  # the device's thread moves it: nothing to await
                break
            await asyncio.sleep(HAND_LOOK_S)
    return HandState(positions=list(move.goal), speed=move.speed,
                     moving=hand.busy(move.serial))


@router.delete(
    "/hand",
    status_code=status.HTTP_204_NO_CONTENT,
    summary="Take the hand off the simulated arm",
    description="The hand lets go: a move under way ends where it is, and a joint that "
    "falls without torque (the profile's `falls_without_torque`: the angler's z winch, an "
    "OpenManipulator-X's shoulder, elbow and wrist) whose servo's torque is off falls, down "
    "the slope of the arm's weight to a joint limit, as on hardware. Nothing happens to an "
    "arm the hand is not on. 409 `not_supported` for a simulated device without servos; "
    "lease holder or instructor; 404 `not_found` on a real arm.",
    responses=errors(401, 403, 404, 409, 422),
)
async def delete_hand(svc: EditorArm) -> Response:
    hand_of(svc).let_go()
    return Response(status_code=status.HTTP_204_NO_CONTENT)
