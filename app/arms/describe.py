"""What an arm can do, from its profile alone (`GET /api/v1/arms`' capabilities): the arm's
service answers with it, and a lab's front for an arm whose worker is down and has not
answered yet (app/lab/front.py)."""

from __future__ import annotations

from app import schemas as s
from app.arms import arm_type
from app.arms.model import KinematicsModel
from app.config import ArmProfile


def capabilities(profile: ArmProfile, model: KinematicsModel | None = None) -> s.Capabilities:
    """`profile`'s capabilities; `model`: its arm type's kinematics bound to it, if built."""
    t = arm_type(profile.model)
    model = model if model is not None else t.model(profile)
    return s.Capabilities(gripper=profile.gripper.actuated,
                          force_sensing=force_sensing(profile), protocol=t.protocol,
                          pitch=model.has_pitch)


def force_sensing(profile: ArmProfile) -> bool:
    """Whether the arm senses force: a force sensor, or joint torques (stall torques given)."""
    return profile.force is not None or any(j.stall_torque_nm for j in profile.joints)
