"""The simulated world of a simulated arm (API.md "Simulated world"): read the scene, lay out a
new one. Any viewer reads; the arm's lease holder or an instructor replaces it. A real arm (or
a simulator on a pty or socket) has no world here: 404 `not_found`.

The world is the simulator's surroundings (app/sim/world.py), not the arm: a new scene moves
no joint, and nothing here reaches the device.
"""

from __future__ import annotations

import asyncio
from typing import Annotated

from fastapi import APIRouter, Depends, Header, Request

from app import schemas as s
from app.errors import InvalidRequest, NotFound
from app.service import ArmService
from app.sim.world import Bin, Scene, SceneError, World, WorldObject
from app.web.deps import ArmName, Credentials, ViewerArm, get_access, lookup_arm
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
    x_arm_lease: Annotated[str | None, Header(description="the lease id, while a lease is "
                                              "held on the arm", max_length=128)] = None,
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
