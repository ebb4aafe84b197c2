"""The angler's kinematics model: kinematics/pprp.py (PPRP: x and y carriages, the t3 arm, the
z carriage) bound to a profile, with its IK options (`ik_case`, `theta3`)."""

from __future__ import annotations

from typing import TYPE_CHECKING, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from app.arms.model import Chain, ChainStep, KinematicsModel, LineIK, Solution
from app.errors import Unreachable
from kinematics import chain, pprp

if TYPE_CHECKING:
    from app.config import ArmProfile


class AnglerIK(BaseModel):
    """The angler's IK options (move/pose and inverse requests carry them by these names)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    ik_case: Literal["dx_zero", "dx_used"] | None = Field(
        None, description="`dx_zero` (dx = 0, theta3 reaches x) or `dx_used` (the design's "
        "case 2: dx = px -/+ r, theta3 = -/+90 deg; a line keeps theta3); none: the design's "
        "choice, dx_zero where |px| <= r")
    theta3: float | None = Field(None, description="dx_used case: theta3 to use, rad (none: "
                                 "the design's -/+90 deg)")


def _opts(options: BaseModel | None) -> AnglerIK:
    return options if isinstance(options, AnglerIK) else AnglerIK(ik_case=None, theta3=None)


class PprpModel(KinematicsModel):
    """Joints (dx, dy, t3, dz) (m, m, rad, m); geometry r (t3 axis to magnet) and h (drop from
    the z carriage to the magnet), m."""

    points = chain.PPRP_POINTS

    def __init__(self, profile: ArmProfile) -> None:
        super().__init__(profile)
        g = profile.geometry
        self.geom = pprp.PPRP(r=g["r"], h=g["h"])

    def fk(self, q: np.ndarray) -> np.ndarray:
        return pprp.fk(q, self.geom)

    def jacobian(self, q: np.ndarray) -> np.ndarray:
        return pprp.jacobian(q, self.geom)

    def joint_origins(self, q: np.ndarray) -> np.ndarray:
        return chain.pprp_points(q, self.geom)

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        return pprp.bounds(self.geom, self.lower, self.upper)  # exact

    def solutions(self, p: np.ndarray, pitch: float | None,
                  options: BaseModel | None) -> list[np.ndarray]:
        o = _opts(options)
        lo, hi = self.bounds()
        pa = np.asarray(p, dtype=float)
        if np.any(pa < lo - 1e-9) or np.any(pa > hi + 1e-9):
            raise Unreachable(
                f"out of reach: ({pa[0]:.3f}, {pa[1]:.3f}, {pa[2]:.3f}) m is outside the "
                f"workspace ({lo.round(3).tolist()} .. {hi.round(3).tolist()} m)")
        # no case named: every solution of both cases, the design's choice first
        return pprp.ik_one(p, self.geom, case=o.ik_case, theta3=o.theta3)

    def candidates(self, p: np.ndarray, pitch: float | None,
                   options: BaseModel | None) -> np.ndarray:
        o = _opts(options)
        case = o.ik_case or pprp.auto_case(p, self.geom)
        return pprp.ik(p, self.geom, case, o.theta3).q

    def ik_best(self, p: np.ndarray, near: np.ndarray | None, branch: int | None = None,
                pitch: float | None = None, options: BaseModel | None = None) -> Solution:
        o = _opts(options)
        if o.ik_case is None and branch is None:  # the design's case
            options = o.model_copy(update={"ik_case": pprp.auto_case(p, self.geom)})
        return super().ik_best(p, near, branch, pitch, options)

    def line_ik(self, p: np.ndarray, q0: np.ndarray, pitch: float | None,
                options: BaseModel | None) -> LineIK:
        """The named case, else the design's choice; in case dx_used a line keeps theta3 (the
        carriages draw it) at each previous point's value."""
        o = _opts(options)
        case = o.ik_case or pprp.auto_case(p, self.geom)
        keep = case == "dx_used"

        def near(point: np.ndarray, ref: np.ndarray) -> np.ndarray:
            th = float(ref[2]) if keep else None
            return self.ik_nearest(point, ref, None, AnglerIK(ik_case=case, theta3=th))
        return near

    def chain(self) -> Chain:
        g = self.geom
        return Chain(steps=(
            ChainStep("translate", (1.0, 0.0, 0.0), joint=0, point="x_carriage"),
            ChainStep("translate", (0.0, 1.0, 0.0), joint=1, point="column"),
            ChainStep("rotate", (0.0, 0.0, 1.0), joint=2),
            ChainStep("translate", (0.0, 1.0, 0.0), offset=g.r, point="arm_end"),
            ChainStep("translate", (0.0, 0.0, 1.0), offset=-g.h, joint=3, point="tip"),
        ), side_axis=1)
