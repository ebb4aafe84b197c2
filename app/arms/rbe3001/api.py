"""RBE3001 protocol pass-through: SET_PID 37, STATUS 38, SET_GAIN 39, SET_CLAW 40.

Raw device units (encoder ticks). These bypass the motion planner but never the emergency stop,
and a SET_PID position obeys the joint limits unless the profile allows raw access. Each command
is encoded here once before it is queued, so a value the packet cannot carry (a float32
overflow) is a 422 for the caller, not a failure inside the task that owns the link.
"""

from __future__ import annotations

import struct

import numpy as np
from fastapi import APIRouter

from app import schemas as s
from app.arms.rbe3001.driver import Rbe3001Driver
from app.errors import InvalidRequest, OutOfRange
from app.service import ArmService
from app.web.deps import ControlArm
from app.web.routes.common import DEVICE, errors
from protocol import rbe3001 as rb

router = APIRouter(prefix="/arms/{arm}/rbe3001", tags=["rbe3001"])

_NOT_SUPPORTED = "409 `not_supported` on an arm that does not speak the RBE3001 protocol."


def _driver(svc: ArmService) -> Rbe3001Driver:
    return svc.protocol_driver("rbe3001", Rbe3001Driver)


def _encodable(cmd: rb.Command) -> None:
    try:
        rb.encode_command(cmd)
    except (ValueError, OverflowError, struct.error) as exc:
        raise InvalidRequest(f"{type(cmd).__name__} cannot be encoded: {exc}") from None


@router.post(
    "/set-pid",
    response_model=s.SetPidReply,
    summary="SET_PID (37): joint position setpoints in encoder ticks",
    description="Three setpoints (position ticks; velocity and force are carried but unused by "
    "the firmware). Checked like a planned move, from where the arm is: 422 `joint_limit` "
    "outside the joint limits (unless the profile allows raw access), 422 `velocity_limit` for "
    "a step the firmware's PID would take faster than the joint's velocity limit (more than "
    "0.03 s of motion at the limit from the measured position; send a planned move or "
    "smaller steps), 422 `keep_out` for a path into a keep-out zone or below the floor (raw "
    "access too), 409 `busy` while a planned motion runs or is queued, 409 `estop_latched` "
    "while the estop is latched. Answers the positions the firmware reported. "
    + _NOT_SUPPORTED,
    responses=errors(*DEVICE),
)
async def set_pid(svc: ControlArm, req: s.SetPid) -> s.SetPidReply:
    drv = _driver(svc)
    setpoints = [(j.position_ticks, j.velocity_ticks_s, j.force) for j in req.joints]
    joints = tuple(rb.JointSetpoint(*sp) for sp in setpoints)
    _encodable(rb.SetPid(joints))  # type: ignore[arg-type]  # 3 joints: the schema's length
    svc.check_passthrough_velocities(np.array([sp[1] for sp in setpoints]))
    goals = {k: float(sp[0]) for k, sp in enumerate(setpoints)}
    reply = await svc.command_passthrough(goals, lambda: drv.set_pid(setpoints))
    return s.SetPidReply(position_ticks=[float(x) for x in reply.position_ticks])


@router.get(
    "/status",
    response_model=s.Rbe3001Status,
    summary="STATUS (38): positions, velocities, strain gauges",
    description="One STATUS exchange with the firmware (not the cached telemetry): positions "
    "(ticks), velocities (ticks/s) and raw strain-gauge ADC fractions. Operator token (it "
    "uses the bus). " + _NOT_SUPPORTED,
    responses=errors(*DEVICE),
)
async def status(svc: ControlArm) -> s.Rbe3001Status:
    reply = await _driver(svc).status()
    return s.Rbe3001Status(position_ticks=[float(x) for x in reply.position_ticks],
                           velocity_ticks_s=[float(x) for x in reply.velocity_ticks_s],
                           strain_adc=[float(x) for x in reply.strain_adc])


@router.post(
    "/set-gain",
    response_model=s.Ack,
    summary="SET_GAIN (39): PID gains of one joint",
    description="kp, ki, kd in firmware units (each 0..1000; the firmware's default kp is "
    "0.005, and a negative gain makes the loop unstable: 422) for axis 0-2; kp below the "
    "joint's `min_kp` in the profile is 422 `out_of_range` unless the profile allows raw "
    "access (with kp 0 the simulated shoulder fell past its limit), and so is kp + ki above "
    "its `max_kp_ki` (the firmware's integral is the error's running mean: at rest ki adds to "
    "kp, and a stiffer loop chatters). Refused while the "
    "estop is latched (new gains can move a joint). The firmware's reply carries nothing: "
    "`reply` says whether it answered (`sent`: no reply within one timeout, as builds that "
    "answer nothing). " + _NOT_SUPPORTED,
    responses=errors(*DEVICE),
)
async def set_gain(svc: ControlArm, req: s.SetGain) -> s.Ack:
    drv = _driver(svc)
    _encodable(rb.SetGain(req.axis, req.kp, req.ki, req.kd))
    joint = svc.profile.joints[req.axis]
    if joint.min_kp is not None and req.kp < joint.min_kp and not svc.profile.raw_access:
        raise OutOfRange(f"kp {req.kp:g} for {joint.name} is below the profile's min_kp "
                         f"{joint.min_kp:g}: a joint with too little proportional gain no longer "
                         "holds against its load (at kp 0 the shoulder falls), and catches up "
                         "faster than any plan when it is raised again. Tuning below it needs a "
                         "profile with raw_access = true")
    top = joint.max_kp_ki
    # (a sum a user reads as the bound is taken: 0.005 + 0.025 is above 0.03 in floats)
    if top is not None and req.kp + req.ki > top + 1e-12 and not svc.profile.raw_access:
        raise OutOfRange(f"kp + ki {req.kp + req.ki:g} for {joint.name} is above the "
                         f"profile's max_kp_ki {top:g}: the firmware's integral is the error's "
                         "running mean, so at rest ki adds to kp, and a loop that stiff "
                         "chatters (the simulated shoulder at 0.05: 1.7 rad/s, past its speed "
                         "limit). Tuning above it needs a profile with raw_access = true")
    svc.require_motion_allowed()
    how = await drv.set_gain(req.axis, req.kp, req.ki, req.kd)
    return s.Ack(command="SET_GAIN", reply=how)


@router.post(
    "/set-claw",
    response_model=s.Ack,
    summary="SET_CLAW (40): claw setpoint",
    description="0.0 open .. 1.0 closed. Refused while the estop is latched. `reply` as for "
    "SET_GAIN. " + _NOT_SUPPORTED,
    responses=errors(*DEVICE),
)
async def set_claw(svc: ControlArm, req: s.SetClaw) -> s.Ack:
    drv = _driver(svc)
    svc.require_motion_allowed()
    how = await drv.set_claw(req.value)
    return s.Ack(command="SET_CLAW", reply=how)
