"""The RBE3001's kinematics model: kinematics/rrr.py (3-DOF RRR arm) bound to a profile."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from pydantic import BaseModel

from app.arms.model import Chain, ChainStep, KinematicsModel
from kinematics import chain, rrr

if TYPE_CHECKING:
    from app.config import ArmProfile


class RrrModel(KinematicsModel):
    """Base yaw, shoulder and elbow pitch; geometry l1 (shoulder height), l2, l3 (links), m."""

    points = chain.RRR_POINTS

    def __init__(self, profile: ArmProfile) -> None:
        super().__init__(profile)
        g = profile.geometry
        self.geom = rrr.RRR(l1=g["l1"], l2=g["l2"], l3=g["l3"])

    def fk(self, q: np.ndarray) -> np.ndarray:
        return rrr.fk(q, self.geom)

    def jacobian(self, q: np.ndarray) -> np.ndarray:
        return rrr.jacobian(q, self.geom)

    def joint_origins(self, q: np.ndarray) -> np.ndarray:
        return chain.rrr_points(q, self.geom)

    def solutions(self, p: np.ndarray, pitch: float | None,
                  options: BaseModel | None) -> list[np.ndarray]:
        return rrr.ik_one(p, self.geom)

    def candidates(self, p: np.ndarray, pitch: float | None,
                   options: BaseModel | None) -> np.ndarray:
        return rrr.ik(p, self.geom).q

    def chain(self) -> Chain:
        g = self.geom
        return Chain(steps=(
            ChainStep("rotate", (0.0, 0.0, 1.0), joint=0),
            ChainStep("translate", (0.0, 0.0, 1.0), offset=g.l1, point="shoulder"),
            ChainStep("rotate", (0.0, -1.0, 0.0), joint=1),
            ChainStep("translate", (1.0, 0.0, 0.0), offset=g.l2, point="elbow"),
            ChainStep("rotate", (0.0, 1.0, 0.0), joint=2),
            ChainStep("translate", (0.0, 0.0, -1.0), offset=g.l3, point="tip"),
        ), side_axis=0)
