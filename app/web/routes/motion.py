"""Moves, plans (previews without motion), motion status and cancel, stop, emergency stop and
the gripper. Every check (limits, reachability, velocity, estop) is the motion executor's and
the service's; this module only maps HTTP onto them."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Path, Response, status

from app import schemas as s
from app.web.deps import CallerDep, ControlArm, OperatorArm, ViewerArm
from app.web.routes.common import DEVICE, READ, check_joint_count, errors, motion_answer

router = APIRouter(tags=["motion"])

_GONE = {410: "a motion this arm has forgotten (`motion_expired`), with what is known"}
MotionId = Annotated[str, Path(description="motion id, as answered by a move", max_length=64)]

_MOVE_DOC = (
    " Checked before anything is sent: joint limits (422 `joint_limit`, naming the joint, the "
    "limit and how far off), reachability (422 `unreachable`), velocity and acceleration limits; "
    "refused with 409 `estop_latched` while the emergency stop is latched and 409 `leased` "
    "while another client holds the lease. Answers 202 with the motion (id, status, planned "
    "duration) at once, or, with `wait: true`, 200 with its final state when it ends (`done`, "
    "`stopped` or `failed` with the reason)."
)


@router.post(
    "/arms/{arm}/move/joints",
    response_model=s.Motion,
    status_code=status.HTTP_202_ACCEPTED,
    summary="Joint-space move",
    description="Move to target joint positions (rad/m, in the arm's joint order), with an "
    "optional duration (s) or speed fraction; `mode` `queue` runs after the current motion, "
    "`replace` blends out of it now." + _MOVE_DOC,
    responses={200: {"model": s.Motion, "description": "final state (with `wait: true`)"},
               **errors(*DEVICE)},
)
async def move_joints(svc: ControlArm, req: s.MoveJoints, response: Response) -> s.Motion:
    check_joint_count(svc, req.positions)
    record = await svc.move_joints(req)
    return await motion_answer(record, req.wait, response)


@router.post(
    "/arms/{arm}/move/pose",
    response_model=s.Motion,
    status_code=status.HTTP_202_ACCEPTED,
    summary="Move the tool tip to x, y, z",
    description="Tip target in metres in the arm's base frame; `path` `joint` interpolates in "
    "joint space, `line` moves the tip along a straight line. `branch` picks an IK solution "
    "(default: the within-limits one nearest the current joints)." + _MOVE_DOC,
    responses={200: {"model": s.Motion, "description": "final state (with `wait: true`)"},
               **errors(*DEVICE)},
)
async def move_pose(svc: ControlArm, req: s.MovePose, response: Response) -> s.Motion:
    record = await svc.move_pose(req)
    return await motion_answer(record, req.wait, response)


@router.post(
    "/arms/{arm}/plan/joints",
    response_model=s.Motion,
    summary="Plan a joint-space move without running it",
    description="The same checks and plan as POST move/joints (same body; `wait` and `mode` "
    "are ignored), answered with status `queued` and `planned_path` (the tip path, up to 50 "
    "points); nothing is sent to the device.",
    responses=errors(*READ, 409),
)
async def plan_joints(svc: ViewerArm, req: s.MoveJoints) -> s.Motion:
    check_joint_count(svc, req.positions)
    return await svc.preview_joints(req)


@router.post(
    "/arms/{arm}/plan/pose",
    response_model=s.Motion,
    summary="Plan a tip move without running it",
    description="The same checks and plan as POST move/pose, answered with status `queued` and "
    "`planned_path`; nothing is sent to the device.",
    responses=errors(*READ, 409),
)
async def plan_pose(svc: ViewerArm, req: s.MovePose) -> s.Motion:
    return await svc.preview_pose(req)


@router.get(
    "/arms/{arm}/motions/{motion_id}",
    response_model=s.Motion,
    summary="Status of one motion",
    description="queued, running, done, stopped or failed (with `reason` and `code`); "
    "`progress` 0..1. 404 `unknown_motion` for an id this arm never had; 410 `motion_expired` "
    "for one it has forgotten (history: the last 256 motions or 10 minutes, whichever is more), "
    "with what is still known about it.",
    responses=errors(*READ, 410, extra=_GONE),
)
async def get_motion(svc: ViewerArm, motion_id: MotionId) -> s.Motion:
    return svc.motion_record(motion_id).to_schema()


@router.delete(
    "/arms/{arm}/motions/{motion_id}",
    response_model=s.Motion,
    summary="Cancel a motion",
    description="Cancel a queued or running motion: a running one decelerates and the arm holds. "
    "Operator token; open without the lease (stopping is always allowed). Cancelling an "
    "ended motion answers it unchanged. The motion's `reason` says who cancelled it.",
    responses=errors(*READ, 403, 410, extra=_GONE),
)
async def cancel_motion(svc: OperatorArm, motion_id: MotionId, who: CallerDep) -> s.Motion:
    rec = await svc.cancel_motion(motion_id, f"cancelled by {who}")
    return rec.to_schema()


@router.post(
    "/arms/{arm}/stop",
    response_model=s.StopResult,
    summary="Stop all motion",
    description="Stop the running motion and clear the queue; the arm holds position. Operator "
    "token; open without the lease (stopping is always allowed). Answers the ids stopped; "
    "their `reason` says who stopped them.",
    responses=errors(*READ, 403, 503, 504),
)
async def stop(svc: OperatorArm, who: CallerDep) -> s.StopResult:
    return await svc.stop(f"stopped by {who} (POST /api/v1/arms/{svc.name}/stop)")


@router.post(
    "/arms/{arm}/estop",
    response_model=s.EstopState,
    summary="Latch the emergency stop",
    description="Motion stops now and the queue is cleared; every move is refused with 409 "
    "`estop_latched` until released. Open to every authenticated client, viewer tokens "
    "included, lease or not. The latch is kept in the data folder's store: a server (or a "
    "lab's worker) restarted, crashed or killed while it is latched starts the arm latched. "
    "Answered once the hold is commanded and the latch's record is on disk (a disk that "
    "refuses it, or holds it over 0.5 s, does not hold the answer back: the store retries, "
    "and health says).",
    responses=errors(*READ),
)
async def estop(svc: ViewerArm) -> s.EstopState:
    return await svc.latch_estop()


@router.delete(
    "/arms/{arm}/estop",
    response_model=s.EstopState,
    summary="Release the emergency stop",
    description="Release the latch (the arm does not move until commanded); the only way it "
    "is released, a restart included. Operator token, "
    "and the lease id while a lease is held: releasing re-enables motion, so it needs the same "
    "right as moving.",
    responses=errors(*READ, 403, 409),
)
async def release_estop(svc: ControlArm) -> s.EstopState:
    return await svc.release_estop()


@router.post(
    "/arms/{arm}/gripper",
    response_model=s.GripperState,
    summary="Set the gripper",
    description="0.0 open .. 1.0 closed. 409 `no_gripper` on an arm without an actuated gripper "
    "(the angler's magnet is passive); 409 `estop_latched` while the estop is latched.",
    responses=errors(*DEVICE),
)
async def gripper(svc: ControlArm, req: s.GripperCommand) -> s.GripperState:
    return await svc.set_gripper(req.value)
