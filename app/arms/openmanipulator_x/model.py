"""The OpenManipulator-X's kinematics model: kinematics/omx.py (four revolute joints: waist
about z, shoulder, elbow and wrist about y) bound to a profile. The arm has a wrist: poses
carry `pitch` (API.md "Wrist pitch"), the tool's angle from the horizontal in the arm's
vertical plane, positive pointing up.

IK: with a pitch, every branch of kinematics/omx.py `ik_one` (the waist facing the target
first, elbow up before elbow down); without one, the pitch `ik_position` picks (the pitch
nearest the target's elevation from the shoulder at which a solution within the joint limits
faces the target). A straight line turns the pitch evenly from the start's to the target's.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from pydantic import BaseModel

from app.arms.model import Chain, ChainStep, KinematicsModel, LineIK
from kinematics import omx

if TYPE_CHECKING:
    from app.config import ArmProfile

#: The geometry keys of a profile (metres, kinematics/omx.py `OMX`).
GEOMETRY_KEYS = frozenset({"bx", "bz", "d1", "a2x", "a2z", "l3", "l4"})


class OmxModel(KinematicsModel):
    """Joints (waist, shoulder, elbow, wrist) rad; tip (x, y, z) m and pitch rad."""

    points = omx.POINTS
    has_pitch = True

    def __init__(self, profile: ArmProfile) -> None:
        super().__init__(profile)
        self.geom = omx.OMX(**{k: float(profile.geometry[k]) for k in GEOMETRY_KEYS})

    def fk(self, q: np.ndarray) -> np.ndarray:
        return np.asarray(omx.fk(q, self.geom)[..., :3], dtype=float)

    def pitch(self, q: np.ndarray) -> np.ndarray | None:
        return np.asarray(omx.fk(q, self.geom)[..., 3], dtype=float)

    def jacobian(self, q: np.ndarray) -> np.ndarray:
        """(4, 4): rows x, y, z (m/rad) and pitch (rad/rad); the tip force solve then gives
        the force (N) and the moment about the pitch axis (N m)."""
        return omx.jacobian(q, self.geom)

    def joint_origins(self, q: np.ndarray) -> np.ndarray:
        return omx.joint_origins(q, self.geom)

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        if self._bounds is None:
            self._bounds = omx.bounds(self.geom, self.lower, self.upper,
                                      rng=np.random.default_rng(0))
        return self._bounds

    def _pitch_for(self, p: np.ndarray, pitch: float | None) -> float:
        if pitch is not None:
            return float(pitch)
        best, _ = omx.ik_position(p, self.geom, self.lower, self.upper)
        return best

    def solutions(self, p: np.ndarray, pitch: float | None,
                  options: BaseModel | None) -> list[np.ndarray]:
        pa = np.asarray(p, dtype=float).reshape(3)
        if pitch is None:
            _, sols = omx.ik_position(pa, self.geom, self.lower, self.upper)
            return [np.asarray(s, dtype=float) for s in sols]
        return [np.asarray(s, dtype=float)
                for s in omx.ik_one((*pa, float(pitch)), self.geom)]

    def candidates(self, p: np.ndarray, pitch: float | None,
                   options: BaseModel | None) -> np.ndarray:
        pa = np.asarray(p, dtype=float).reshape(3)
        target = np.array([*pa, self._pitch_for(pa, pitch)])
        return np.asarray(omx.ik(target, self.geom).q, dtype=float)

    def line_ik(self, p: np.ndarray, q0: np.ndarray, pitch: float | None,
                options: BaseModel | None) -> LineIK:
        """Each point of the line from the tip at ``q0`` to ``p`` takes the pitch turned
        evenly from the start's to the target's (by the shorter way), by its fraction along
        the line; the branch nearest the previous point's."""
        start = self.fk(np.asarray(q0, dtype=float))
        pa = np.asarray(p, dtype=float).reshape(3)
        p0 = float(omx.fk(np.asarray(q0, dtype=float), self.geom)[3])
        turn = float(omx.wrap(self._pitch_for(pa, pitch) - p0))
        d = pa - start
        dd = float(d @ d)

        def near(point: np.ndarray, ref: np.ndarray) -> np.ndarray:
            s = 1.0 if dd == 0.0 else min(1.0, max(0.0, float((point - start) @ d) / dd))
            return self.ik_nearest(point, ref, p0 + s * turn, options)
        return near

    def chain(self) -> Chain:
        g = self.geom
        x, y, z = (1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)
        return Chain(steps=(
            ChainStep("translate", x, offset=g.bx),
            ChainStep("translate", z, offset=g.bz, point="waist"),
            ChainStep("rotate", z, joint=0),
            ChainStep("translate", z, offset=g.d1, point="shoulder"),
            ChainStep("rotate", y, joint=1),
            ChainStep("translate", x, offset=g.a2x),
            ChainStep("translate", z, offset=g.a2z, point="elbow"),
            ChainStep("rotate", y, joint=2),
            ChainStep("translate", x, offset=g.l3, point="wrist"),
            ChainStep("rotate", y, joint=3),
            ChainStep("translate", x, offset=g.l4, point="tip"),
        ))
