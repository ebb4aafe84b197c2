"""From a leader's joints to a follower's joint target: one to one for like arms (scaled,
offset and clamped), or through the tip for unlike ones (the leader's forward kinematics, the
follower's inverse kinematics nearest where it is). Pure: numbers in, a target out.

`step_towards` bounds how far the follower's setpoint moves in one tick (its velocity limit
times the tracking margin and the speed override, over the time since the last command), so
a leader that jumps (or the first tick of a session, far from the follower) is followed at
the follower's own speed limit rather than refused by the guard.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from app.arms.model import KinematicsModel
from app.errors import ArmError, InvalidRequest


class NoTarget(Exception):
    """The leader's pose has no follower target (outside its workspace): the tick holds."""


@dataclass(frozen=True)
class JointMap:
    """follower q = clip(offset + scale * leader q) per joint, clipped to the follower's joint
    limits narrowed by `margin` (rad or m) on each side."""

    scale: np.ndarray
    offset: np.ndarray
    lower: np.ndarray
    upper: np.ndarray

    def target(self, leader_q: np.ndarray, follower_q: np.ndarray) -> np.ndarray:
        del follower_q  # one to one: where the follower is does not matter
        q = self.offset + self.scale * np.asarray(leader_q, dtype=float)
        return np.asarray(np.clip(q, self.lower, self.upper), dtype=float)


@dataclass(frozen=True)
class TipMap:
    """The leader's tip (x, y, z and, where both have a wrist, pitch) scaled about the origin
    and offset, then the follower's IK solution within its limits nearest where it is."""

    leader: KinematicsModel
    follower: KinematicsModel
    scale: float
    offset: np.ndarray
    lower: np.ndarray
    upper: np.ndarray

    def target(self, leader_q: np.ndarray, follower_q: np.ndarray) -> np.ndarray:
        q = np.asarray(leader_q, dtype=float)
        p = self.offset + self.scale * np.asarray(self.leader.fk(q), dtype=float)
        pitch = None
        if self.leader.has_pitch and self.follower.has_pitch:
            lp = self.leader.pitch(q)
            pitch = None if lp is None else float(lp)
        try:
            sol = self.follower.ik_best(p, np.asarray(follower_q, dtype=float), None, pitch)
        except ArmError as exc:
            raise NoTarget(exc.detail) from None
        return np.asarray(np.clip(sol.positions, self.lower, self.upper), dtype=float)


Mapping = JointMap | TipMap


def joint_map(leader: KinematicsModel, follower: KinematicsModel, scale: list[float] | None,
              offset: list[float] | None, margin: float) -> JointMap:
    """A one-to-one map; 422 unless both arms have the same number of joints of the same
    kinds (use the tip mapping between unlike arms) and scale/offset have one value each."""
    if leader.n != follower.n or list(leader.kinds) != list(follower.kinds):
        raise InvalidRequest(
            f"mapping `joints` needs like arms: the leader has {leader.n} joints "
            f"({', '.join(leader.kinds)}), the follower {follower.n} "
            f"({', '.join(follower.kinds)}); use mapping `tip`")
    n = follower.n
    s = _per_joint(scale, n, 1.0, "scale")
    o = _per_joint(offset, n, 0.0, "offset")
    lo, hi = _narrowed(follower, margin)
    return JointMap(s, o, lo, hi)


def tip_map(leader: KinematicsModel, follower: KinematicsModel, scale: float,
            offset: list[float] | None, margin: float) -> TipMap:
    o = np.zeros(3) if offset is None else np.asarray(offset, dtype=float)
    if o.shape != (3,):
        raise InvalidRequest(f"tip_offset takes x, y, z (3 values), got {len(o)}")
    lo, hi = _narrowed(follower, margin)
    return TipMap(leader, follower, float(scale), o, lo, hi)


def _per_joint(values: list[float] | None, n: int, default: float, what: str) -> np.ndarray:
    if values is None:
        return np.full(n, default)
    if len(values) != n:
        raise InvalidRequest(f"{what} takes one value per follower joint ({n}), got "
                             f"{len(values)}")
    return np.asarray(values, dtype=float)


def _narrowed(model: KinematicsModel, margin: float) -> tuple[np.ndarray, np.ndarray]:
    lo = np.asarray(model.lower, dtype=float) + margin
    hi = np.asarray(model.upper, dtype=float) - margin
    if np.any(lo > hi):
        raise InvalidRequest(f"clamp margin {margin:g} leaves no range of a follower joint")
    return lo, hi


def step_towards(last: np.ndarray, target: np.ndarray, cap: np.ndarray) -> np.ndarray:
    """`target`, or the point `cap` (per joint, >= 0) along the way from `last` where it is
    farther: every joint scaled by the same fraction, so the path keeps its direction."""
    delta = np.asarray(target, dtype=float) - last
    over = np.abs(delta) / np.maximum(cap, 1e-12)
    worst = float(np.max(over)) if over.size else 0.0
    if worst <= 1.0:
        return np.asarray(target, dtype=float)
    return np.asarray(last + delta / worst, dtype=float)
