"""Joint calibration (API.md "Calibration (v1.2)"): the zeros the hardware does not know,
declared by the pose the arm is in and stored under the hardware's identity; the gravity fit.

Joints a profile marks `zero_known = false` (the rbe3001's three, the angler's theta3) start
not calibrated on a real link, and moves that would move them are refused with 409
`not_calibrated` until POST here declares where the arm is (app/calibration).
"""

from __future__ import annotations

from fastapi import APIRouter

from app import schemas as s
from app.service import ArmService
from app.store import Store
from app.web.deps import ControlArm, InstructorArm, ViewerArm
from app.web.routes.common import READ, errors

router = APIRouter(prefix="/arms/{arm}/calibration", tags=["calibration"])


def use_store(svc: ArmService, store: Store) -> None:
    """At start-up: the arm's calibration is kept in (and found again from) `store`."""
    svc.use_store(store)


@router.get(
    "",
    response_model=s.ArmCalibration,
    summary="The arm's joint calibration and gravity fit",
    description="Per joint: whether its zero is known on this hardware, the offset (the joint "
    "value at which the device reads zero, rad or m), where it came from (`profile`, "
    "`stored` for this hardware, `declared` since the link came up) and when; the gravity fit "
    "(null until one is made) and its last run; the calibration poses the profile names; the "
    "hardware identity it is stored under. Viewer token.",
    responses=errors(*READ),
)
async def get_calibration(svc: ViewerArm) -> s.ArmCalibration:
    return svc.calibration_view()


@router.post(
    "",
    response_model=s.ArmCalibration,
    summary="Declare the pose the arm is in: calibrate its joints",
    description="`{\"positions\": [...]}` (the joint values the arm is at now, rad or m) or "
    "`{\"pose\": NAME}` (a calibration pose the profile names, e.g. the rbe3001's `jig`). "
    "Nothing moves: the joints whose zero the hardware does not know take these values as "
    "their reading now, and the calibration is stored under the hardware's identity (found "
    "again after a restart with the same hardware). 422 `invalid_request` for an unknown pose "
    "or both or neither fields, 422 `joint_limit` for values outside the limits, 409 `busy` "
    "while a motion runs or is queued, 409 `not_supported` for an arm whose joints' zeros are "
    "all known, 503 `link_down` without a fresh reading. Operator token and the arm's lease.",
    responses=errors(401, 403, 404, 409, 422, 503),
)
async def calibrate(svc: ControlArm, req: s.ArmCalibrationRequest) -> s.ArmCalibration:
    return await svc.calibrate(req.positions, req.pose)


@router.delete(
    "",
    response_model=s.ArmCalibration,
    summary="Forget the arm's stored calibration",
    description="The stored calibration of this hardware is dropped and the joints go back "
    "to what the profile knows (joints whose zero the hardware does not know: not "
    "calibrated); the gravity fit goes too. Nothing moves. 409 `busy` while a motion runs or "
    "is queued. Instructor token.",
    responses=errors(401, 403, 404, 409, 422),
)
async def forget(svc: InstructorArm) -> s.ArmCalibration:
    return await svc.forget_calibration()


@router.post(
    "/gravity",
    response_model=s.GravityRun,
    status_code=202,
    summary="Fit the joints' gravity torques: a motion through a few poses",
    description="Each pose (default: home and each joint gravity acts on at a quarter of its "
    "range from either end) is a planned joint move, checked like any move (limits, keep-out "
    "zones, calibration, estop); at rest there the raw joint torques are averaged. Then the "
    "fit (a weight per body point, a constant per joint) is stored with the calibration and "
    "subtracted from `torques` and `tip_force` at every pose; the tare then zeroes the tool's "
    "load. Answers the run (202; with `wait`, when it has ended): its motions by id; GET "
    "`.../calibration` shows its progress and the fit. 409 `no_force_sensing`, 409 `busy` "
    "while a motion or a run is going, 409 `not_calibrated`, 422 `joint_limit`. Operator "
    "token and the arm's lease.",
    responses=errors(401, 403, 404, 409, 422, 503),
)
async def calibrate_gravity(svc: ControlArm,
                            req: s.GravityCalibrationRequest) -> s.GravityRun:
    return await svc.calibrate_gravity(req.poses, req.wait)
