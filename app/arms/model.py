"""The kinematics model contract every arm type implements, and the code they share.

An arm type writes only its own maths (FK, Jacobian, joint origins, IK candidates) in a
subclass of :class:`KinematicsModel`; limits, the IK solution list with its limit flags, the
choice of a solution, the tip-force rule, workspace sampling and the workspace box live here,
once. The server calls the model, never `kinematics` with loose constants (ARCHITECTURE rule
5), and the model turns kinematic failures into the contract's errors (`unreachable`,
`joint_limit`).

Writing a model (see app/arms/rbe3001/model.py for the smallest one):

- set ``points`` (body point names, base first, tip last) and ``has_pitch``;
- implement ``fk`` (tip xyz), ``jacobian`` (d tip / d q), ``joint_origins`` (every body
  point, the last equal to ``fk``), ``solutions`` (every IK solution of one target, the
  preferred first) and ``chain`` (the joint chain the dashboard draws, see :class:`Chain`);
- where the arm has a wrist: ``has_pitch = True``, ``pitch(q)``, and ``solutions`` honours
  the ``pitch`` it is given (None: the model picks one);
- optionally ``candidates`` (a vectorised, reason-free IK for dense lines), ``line_ik`` (how a
  straight line keeps a redundant joint), ``bounds`` (an exact workspace box).

Arrays are numpy float64 in SI units (m, rad) in the arm's base frame and joint order.
"""

from __future__ import annotations

import abc
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, ClassVar, Literal

import numpy as np
from pydantic import BaseModel

from app.errors import InvalidRequest, JointLimit, Unreachable
from kinematics import limits
from kinematics.errors import KinematicsError
from kinematics.singular import TIP_FORCE_MAX_COND, singular_reason
from kinematics.transmission import Transmission

if TYPE_CHECKING:
    from app.config import ArmProfile

__all__ = ["Chain", "ChainStep", "KinematicsModel", "LineIK", "Solution", "chain_points"]

#: Samples of the shared workspace-box estimate (plus every joint-limit corner).
BOUNDS_SAMPLES = 20_000

#: ik_nearest/line_ik: (target xyz, reference joints) -> the joints nearest the reference.
LineIK = Callable[[np.ndarray, np.ndarray], np.ndarray]


@dataclass(frozen=True)
class Solution:
    """One IK solution: joints, whether they are within the limits (and which are not), and
    its index in the model's list (usable as `branch` in move/pose)."""

    positions: np.ndarray
    within_limits: bool
    violations: list[str]
    branch: int


@dataclass(frozen=True)
class ChainStep:
    """One elementary transform of a joint chain, applied to the frame so far: a rotation about
    ``axis`` (unit, in the current frame) by ``offset + q[joint]`` rad, or a translation along
    ``axis`` by ``offset + q[joint]`` m (``joint`` None: by ``offset`` alone). Where ``point``
    is set, the frame origin after this step is that body point."""

    kind: Literal["rotate", "translate"]
    axis: tuple[float, float, float]
    offset: float = 0.0
    joint: int | None = None
    point: str | None = None


@dataclass(frozen=True)
class Chain:
    """An arm's joint chain as the dashboard draws it: from the base frame (the body point
    ``base`` at the origin) through ``steps``; ``side_axis`` is the horizontal axis (0: x,
    1: y) the side view plots against z. :func:`chain_points` evaluates it, and a test holds
    it equal to the model's ``joint_origins``."""

    steps: tuple[ChainStep, ...]
    side_axis: int = 0


def _rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    k = axis / np.linalg.norm(axis)
    kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    rot: np.ndarray = np.eye(3) + np.sin(angle) * kx + (1.0 - np.cos(angle)) * (kx @ kx)
    return rot


def chain_points(chain: Chain, q: Sequence[float]) -> np.ndarray:
    """Body points (B, 3) m of ``chain`` at joints ``q``: the base, then each step's point.
    The reference for the dashboard's JavaScript (app/web/static/app.js `chainPoints`)."""
    rot, pos = np.eye(3), np.zeros(3)
    out = [pos.copy()]
    for st in chain.steps:
        amount = st.offset + (float(q[st.joint]) if st.joint is not None else 0.0)
        axis = np.asarray(st.axis, dtype=float)
        if st.kind == "rotate":
            rot = rot @ _rotation(axis, amount)
        else:
            pos = pos + rot @ (axis * amount)
        if st.point is not None:
            out.append(pos.copy())
    return np.asarray(out, dtype=float)


class KinematicsModel(abc.ABC):
    """An arm's kinematics bound to its profile: geometry, limits and transmission in one
    object. Built once per hosted arm by ``ArmType.model(profile)``.

    Attributes shared by every model: ``profile``, ``geometry`` (the profile's dict),
    ``names``, ``kinds`` (revolute/prismatic), ``n``, ``lower``/``upper`` (joint limits),
    ``vmax``/``amax``/``jmax`` (joint velocity, acceleration, jerk limits), ``transmission``.
    """

    #: Body point names, base first and tip last: the envelope checks each of them.
    points: ClassVar[tuple[str, ...]]
    #: True for an arm with a wrist: poses carry `pitch` (API.md "Wrist pitch").
    has_pitch: ClassVar[bool] = False

    def __init__(self, profile: ArmProfile) -> None:
        self.profile = profile
        self.geometry = dict(profile.geometry)
        self.names = profile.joint_names
        self.kinds = [j.kind for j in profile.joints]
        self.n = len(profile.joints)
        self.lower = np.array(profile.lower, dtype=float)
        self.upper = np.array(profile.upper, dtype=float)
        self.vmax = np.array([j.max_velocity for j in profile.joints], dtype=float)
        self.amax = np.array([j.max_acceleration for j in profile.joints], dtype=float)
        self.jmax = np.array([j.max_jerk for j in profile.joints], dtype=float)
        self.transmission = Transmission.from_joints(
            [j.ticks_per_rev for j in profile.joints],
            [j.offset_ticks for j in profile.joints],
            [j.sign for j in profile.joints],
            [j.lead_m for j in profile.joints],
        )
        self._bounds: tuple[np.ndarray, np.ndarray] | None = None

    # ------------------------------------------------------------ the arm's own maths

    @abc.abstractmethod
    def fk(self, q: np.ndarray) -> np.ndarray:
        """Tip position (..., 3) m for joints (..., n)."""

    def pitch(self, q: np.ndarray) -> np.ndarray | None:
        """The tool's pitch (...) rad for joints (..., n); None for an arm without a wrist."""
        return None

    def tip(self, q: np.ndarray) -> dict[str, float]:
        """The tip as reported (a `schemas.Tip`): x, y, z m, and `pitch` rad only for an arm
        with a wrist. For one q (n,)."""
        p = np.asarray(self.fk(q), dtype=float)
        out = {"x": float(p[0]), "y": float(p[1]), "z": float(p[2])}
        pitch = self.pitch(q)
        if pitch is not None:
            out["pitch"] = float(pitch)
        return out

    @abc.abstractmethod
    def jacobian(self, q: np.ndarray) -> np.ndarray:
        """d tip / d q, (3, n) for one q (an arm with a wrist may add the pitch row: (4, n))."""

    @abc.abstractmethod
    def joint_origins(self, q: np.ndarray) -> np.ndarray:
        """Every body point (..., len(points), 3) m for joints (..., n); the last is the tip."""

    @abc.abstractmethod
    def solutions(self, p: np.ndarray, pitch: float | None,
                  options: BaseModel | None) -> list[np.ndarray]:
        """Every distinct IK solution (each (n,)) of tip ``p`` (3,) m, the preferred first,
        limits not applied. ``pitch`` is None for an arm without a wrist (the base class
        refuses a pitch before calling); ``options`` is an instance of the arm type's
        ``pose_options`` or None. Raise :class:`Unreachable` (or KinematicsError) with the
        reason where there is none."""

    @abc.abstractmethod
    def chain(self) -> Chain:
        """The joint chain the dashboard draws (its points equal ``joint_origins``)."""

    def candidates(self, p: np.ndarray, pitch: float | None,
                   options: BaseModel | None) -> np.ndarray:
        """IK solutions (k, n) of tip ``p`` without reasons or limit messages, for dense IK
        along a line (NaN rows are ignored). Default: ``solutions``; override with the
        vectorised maths where it is faster. May raise like ``solutions``."""
        return np.array(self.solutions(p, pitch, options), dtype=float).reshape(-1, self.n)

    def line_ik(self, p: np.ndarray, q0: np.ndarray, pitch: float | None,
                options: BaseModel | None) -> LineIK:
        """The IK a straight line to ``p`` from joints ``q0`` uses at each point: default, the
        solution nearest the previous point's. An arm with a redundant joint overrides this
        to keep it (the angler keeps theta3 along a line in its dx_used case)."""
        def near(point: np.ndarray, ref: np.ndarray) -> np.ndarray:
            return self.ik_nearest(point, ref, pitch, options)
        return near

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """The axis-aligned box (min (3,), max (3,)) m of reachable tips: by default estimated
        from BOUNDS_SAMPLES joint vectors (seeded) plus every joint-limit corner, a slight
        inner approximation; computed once. Override where the box is known exactly."""
        if self._bounds is None:
            rng = np.random.default_rng(0)
            q = rng.uniform(self.lower, self.upper, size=(BOUNDS_SAMPLES, self.n))
            corners = np.stack(np.meshgrid(*zip(self.lower, self.upper, strict=True),
                                           indexing="ij"), -1).reshape(-1, self.n)
            pts = np.asarray(self.fk(np.concatenate([q, corners])), dtype=float)
            self._bounds = (pts.min(axis=0), pts.max(axis=0))
        return self._bounds

    # ------------------------------------------------------------ shared

    def tip_force(self, q: np.ndarray, tau: np.ndarray,
                  J: np.ndarray | None = None) -> np.ndarray | None:
        """F with J^T F = tau (least squares where J is not square, e.g. the redundant
        angler); None where the one singularity rule (cond(J) above TIP_FORCE_MAX_COND,
        kinematics/singular.py) holds."""
        J = self.jacobian(q) if J is None else J  # the caller's, where it has one already
        if self.tip_force_unavailable(q, J) is not None:
            return None
        if J.shape[0] == J.shape[1]:
            return np.asarray(np.linalg.solve(J.T, tau), dtype=float)
        f, *_ = np.linalg.lstsq(J.T, tau, rcond=None)
        return np.asarray(f, dtype=float)

    def tip_force_unavailable(self, q: np.ndarray, J: np.ndarray | None = None) -> str | None:
        """Why no tip force is given at `q` (the condition-number rule), or None."""
        J = self.jacobian(q) if J is None else J
        return singular_reason(J, TIP_FORCE_MAX_COND)

    def violations(self, q: np.ndarray) -> list[str]:
        """Which joint is outside which limit and by how much; empty within the limits."""
        return limits.violations(q, self.names, self.lower, self.upper, self.kinds)

    def joint_vector(self, positions: Sequence[float]) -> np.ndarray:
        """`positions` as a joint vector, one per joint: 422 `invalid_request` naming the arm
        and its joints for any other length (the one check of every route that takes them)."""
        if len(positions) != self.n:
            raise InvalidRequest(f"{self.profile.name} has {self.n} joints "
                                 f"({', '.join(self.names)}), got {len(positions)} positions")
        return np.array(positions, dtype=float)

    def check_limits(self, q: np.ndarray) -> None:
        v = self.violations(q)
        if v:
            raise JointLimit("; ".join(v))

    def _refuse_pitch(self, pitch: float | None) -> None:
        if pitch is not None and not self.has_pitch:
            raise Unreachable(f"{self.profile.name} has no wrist: a pitch ({pitch:g} rad) "
                              "cannot be met; give x, y, z only")

    def ik(self, p: np.ndarray, pitch: float | None = None,
           options: BaseModel | None = None) -> list[Solution]:
        """Every IK solution of tip `p` (m), each flagged within limits or not.

        Raises Unreachable with the kinematics' reason where there is none (and where a
        pitch is given to an arm without a wrist)."""
        self._refuse_pitch(pitch)
        try:
            sols = self.solutions(np.asarray(p, dtype=float), pitch, options)
        except KinematicsError as exc:
            raise Unreachable(str(exc)) from None
        out = []
        for i, q in enumerate(sols):
            v = self.violations(q)
            out.append(Solution(np.asarray(q, dtype=float), not v, v, i))
        return out

    def ik_nearest(self, p: np.ndarray, ref: np.ndarray, pitch: float | None = None,
                   options: BaseModel | None = None) -> np.ndarray:
        """The IK solution nearest `ref` (limits not applied): the fast path for dense IK along
        a line. Raises Unreachable with the reason where there is none."""
        self._refuse_pitch(pitch)
        try:
            q = self.candidates(p, pitch, options)
        except KinematicsError as exc:
            raise Unreachable(str(exc)) from None
        q = q[np.all(np.isfinite(q), axis=-1)]
        if q.shape[0] == 0:
            self.ik(p, pitch, options)  # raises with the reason
            raise Unreachable(f"no IK solution for {np.round(p, 4).tolist()}")
        return np.asarray(q[int(np.argmin(np.sum((q - ref) ** 2, axis=-1)))], dtype=float)

    def ik_best(self, p: np.ndarray, near: np.ndarray | None, branch: int | None = None,
                pitch: float | None = None, options: BaseModel | None = None) -> Solution:
        """The solution to move to: the given branch, else the within-limits one nearest
        `near` (the first one where `near` is None)."""
        sols = self.ik(p, pitch, options)
        if branch is not None:
            if branch >= len(sols):
                raise Unreachable(f"branch {branch} does not exist: {len(sols)} IK solutions")
            s = sols[branch]
            if not s.within_limits:
                raise JointLimit(f"IK branch {branch}: " + "; ".join(s.violations))
            return s
        ok = [s for s in sols if s.within_limits]
        if not ok:
            raise JointLimit("no IK solution within the joint limits: "
                             + " | ".join("; ".join(s.violations) for s in sols))
        if near is None:
            return ok[0]
        return min(ok, key=lambda s: float(np.sum((s.positions - near) ** 2)))

    def workspace(self, n: int, seed: int = 0) -> np.ndarray:
        """Tips (n, 3) m of joints drawn uniformly within the limits (the same seed and n give
        the same points)."""
        rng = np.random.default_rng(seed)
        q = rng.uniform(self.lower, self.upper, size=(n, self.n))
        return np.asarray(self.fk(q), dtype=float)

    def describe(self) -> dict[str, Any]:
        """The chain as plain data for the API (`ArmDetail.chain`)."""
        c = self.chain()
        return {"points": list(self.points), "side_axis": c.side_axis,
                "steps": [{"kind": st.kind, "axis": list(st.axis), "offset": st.offset,
                           "joint": st.joint, "point": st.point} for st in c.steps]}
