"""An arm's kinematics bound to its profile: geometry, limits and transmission in one object.

The server calls this, never `kinematics` with loose constants (ARCHITECTURE rule 5). Kinematic
failures are turned into the contract's errors here (`unreachable`, `joint_limit`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from app.config import ArmProfile
from app.errors import JointLimit, Unreachable
from kinematics import limits, pprp, rrr
from kinematics.errors import KinematicsError
from kinematics.singular import TIP_FORCE_MAX_COND, singular_reason
from kinematics.transmission import Transmission


@dataclass(frozen=True)
class Solution:
    positions: np.ndarray
    within_limits: bool
    violations: list[str]
    branch: int


class ArmModel:
    def __init__(self, profile: ArmProfile) -> None:
        self.profile = profile
        self.names = profile.joint_names
        self.kinds = [j.kind for j in profile.joints]
        self.lower = np.array(profile.lower, dtype=float)
        self.upper = np.array(profile.upper, dtype=float)
        self.vmax = np.array([j.max_velocity for j in profile.joints], dtype=float)
        self.amax = np.array([j.max_acceleration for j in profile.joints], dtype=float)
        self.jmax = np.array([j.max_jerk for j in profile.joints], dtype=float)
        self.n = len(profile.joints)
        g = profile.geometry
        self.is_rrr = profile.model == "rbe3001"
        self.geom: rrr.RRR | pprp.PPRP
        if self.is_rrr:
            self.geom = rrr.RRR(l1=g["l1"], l2=g["l2"], l3=g["l3"])
        else:
            self.geom = pprp.PPRP(r=g["r"], h=g["h"])
        self.transmission = Transmission.from_joints(
            [j.ticks_per_rev for j in profile.joints],
            [j.offset_ticks for j in profile.joints],
            [j.sign for j in profile.joints],
            [j.lead_m for j in profile.joints],
        )

    # --------------------------------------------------------- forward

    def fk(self, q: np.ndarray) -> np.ndarray:
        if self.is_rrr:
            return rrr.fk(q, self.geom)  # type: ignore[arg-type]
        return pprp.fk(q, self.geom)  # type: ignore[arg-type]

    def jacobian(self, q: np.ndarray) -> np.ndarray:
        if self.is_rrr:
            return rrr.jacobian(q, self.geom)  # type: ignore[arg-type]
        return pprp.jacobian(q, self.geom)  # type: ignore[arg-type]

    def tip_force(self, q: np.ndarray, tau: np.ndarray,
                  J: np.ndarray | None = None) -> np.ndarray | None:
        """F with J^T F = tau (least squares for the redundant angler); None where the one
        singularity rule (cond(J) above TIP_FORCE_MAX_COND, kinematics/singular.py) holds."""
        J = self.jacobian(q) if J is None else J  # the caller's, where it has one already
        if self.tip_force_unavailable(q, J) is not None:
            return None
        if self.is_rrr:
            return np.linalg.solve(J.T, tau)
        f: np.ndarray = np.linalg.lstsq(J.T, tau, rcond=None)[0]
        return f

    def tip_force_unavailable(self, q: np.ndarray, J: np.ndarray | None = None) -> str | None:
        """Why no tip force is given at `q` (the condition-number rule), or None."""
        J = self.jacobian(q) if J is None else J
        return singular_reason(J, TIP_FORCE_MAX_COND)

    # --------------------------------------------------------- limits

    def violations(self, q: np.ndarray) -> list[str]:
        return limits.violations(q, self.names, self.lower, self.upper, self.kinds)

    def check_limits(self, q: np.ndarray) -> None:
        v = self.violations(q)
        if v:
            raise JointLimit("; ".join(v))

    # --------------------------------------------------------- inverse

    def ik(self, p: np.ndarray, ik_case: str | None = None,
           theta3: float | None = None) -> list[Solution]:
        """Every IK solution of tip `p` (m), each flagged within limits or not.

        Raises Unreachable with the kinematics' reason where there is none."""
        try:
            if self.is_rrr:
                sols = rrr.ik_one(p, self.geom)  # type: ignore[arg-type]
            else:
                lo, hi = pprp.bounds(self.geom, self.lower, self.upper)  # type: ignore[arg-type]
                pa = np.asarray(p, dtype=float)
                if np.any(pa < lo - 1e-9) or np.any(pa > hi + 1e-9):
                    raise Unreachable(
                        f"out of reach: ({pa[0]:.3f}, {pa[1]:.3f}, {pa[2]:.3f}) m is outside the "
                        f"workspace ({lo.round(3).tolist()} .. {hi.round(3).tolist()} m)")
                # no case named: every solution of both cases, the design's choice first
                sols = pprp.ik_one(p, self.geom, case=ik_case,  # type: ignore[arg-type]
                                   theta3=theta3)
        except KinematicsError as exc:
            raise Unreachable(str(exc)) from None
        out = []
        for i, q in enumerate(sols):
            v = self.violations(q)
            out.append(Solution(np.asarray(q, dtype=float), not v, v, i))
        return out

    def ik_nearest(self, p: np.ndarray, ref: np.ndarray, ik_case: str | None = None,
                   theta3: float | None = None) -> np.ndarray:
        """The IK solution nearest `ref` (limits not applied): the fast path for dense IK along
        a line (~30 us a point, against ~0.5 ms for `ik` with its reasons and limit messages).
        Raises Unreachable with the reason where there is none."""
        sols: rrr.IKSolutions | pprp.IKSolutions
        if self.is_rrr:
            sols = rrr.ik(p, self.geom)  # type: ignore[arg-type]
        else:
            case = ik_case or pprp.auto_case(p, self.geom)  # type: ignore[arg-type]
            sols = pprp.ik(p, self.geom, case, theta3)  # type: ignore[arg-type]
        q = sols.q[sols.valid]
        if q.shape[0] == 0:
            self.ik(p, ik_case, theta3)  # raises with the reason
            raise Unreachable(f"no IK solution for {np.round(p, 4).tolist()}")
        best: np.ndarray = q[int(np.argmin(np.sum((q - ref) ** 2, axis=-1)))]
        return best

    def ik_best(self, p: np.ndarray, near: np.ndarray | None, branch: int | None = None,
                ik_case: str | None = None, theta3: float | None = None) -> Solution:
        """The solution to move to: the given branch, else the within-limits one nearest `near`."""
        if ik_case is None and not self.is_rrr and branch is None:
            ik_case = pprp.auto_case(p, self.geom)  # type: ignore[arg-type]  # the design's
        sols = self.ik(p, ik_case, theta3)
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
        rng = np.random.default_rng(seed)
        q = rng.uniform(self.lower, self.upper, size=(n, self.n))
        return self.fk(q)
