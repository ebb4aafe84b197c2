"""An arm's kinematics model from its profile, through the arm-type registry.

The contract and the shared code are in app/arms/model.py (`KinematicsModel`); each arm type
binds its own maths (app/arms/<name>/model.py). This module stays as the one-call way in.
"""

from __future__ import annotations

from app.arms import arm_type
from app.arms.model import KinematicsModel, Solution
from app.config import ArmProfile

__all__ = ["ArmModel", "KinematicsModel", "Solution", "model_for"]


def model_for(profile: ArmProfile) -> KinematicsModel:
    """The kinematics model of `profile`'s arm type, bound to it."""
    return arm_type(profile.model).model(profile)


#: Kept for callers of the 0.2 name (`ArmModel(profile)`): the same as `model_for`.
ArmModel = model_for
