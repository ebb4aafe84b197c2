"""RBE3001 arm: a 3-DOF RRR manipulator (base, shoulder, elbow).

Joint order is ``(q0 base, q1 shoulder, q2 elbow)`` in radians; positions are
metres in the base frame. Forward kinematics, as in the course notes::

    rho = L2 cos q1 + L3 sin(q1 - q2)          # horizontal reach
    x   = cos q0 * rho
    y   = sin q0 * rho
    z   = L1 + L2 sin q1 - L3 cos(q1 - q2)

Every function is vectorised over leading axes: ``q`` is (..., 3), points are
(..., 3). Geometry is an argument (:class:`RRR`, from the arm profile).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from kinematics.errors import Singular, Unreachable
from kinematics.limits import corners, distinct_solutions, draw, within
from kinematics.singular import TIP_FORCE_MAX_COND, condition_number

__all__ = [
    "RRR",
    "IKSolutions",
    "bounds",
    "fk",
    "ik",
    "ik_near",
    "ik_one",
    "inverse_velocity",
    "inverse_velocity_one",
    "jacobian",
    "tip_force",
    "tip_force_one",
    "workspace",
    "wrap",
]

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]

_TOL = 1e-12  # slack on the reach boundary, m (relative to the link lengths)


@dataclass(frozen=True)
class RRR:
    """Link lengths in metres; defaults are the design values 8, 6.5, 8.125 in."""

    l1: float = 0.2032
    l2: float = 0.1651
    l3: float = 0.206375


@dataclass(frozen=True)
class IKSolutions:
    """Every IK branch: ``q`` (..., 4, 3) rad, NaN where ``valid`` (..., 4) is False.

    Branch order: (base, elbow) = (q0, +), (q0, -), (q0 + pi, +), (q0 + pi, -).
    """

    q: FloatArray
    valid: BoolArray


def wrap(a: npt.ArrayLike) -> FloatArray:
    """Angles wrapped to (-pi, pi], rad, same shape as ``a``."""
    aa = np.asarray(a, dtype=np.float64)
    return np.asarray(np.pi - np.mod(np.pi - aa, 2.0 * np.pi))


def _q(q: npt.ArrayLike) -> FloatArray:
    qa = np.asarray(q, dtype=np.float64)
    if qa.shape[-1:] != (3,):
        raise ValueError(f"expected joints of shape (..., 3), got {qa.shape}")
    return qa


def fk(q: npt.ArrayLike, g: RRR = RRR()) -> FloatArray:
    """Tip position (..., 3) m for joints ``q`` (..., 3) rad."""
    qa = _q(q)
    q0, q1, q2 = qa[..., 0], qa[..., 1], qa[..., 2]
    rho = g.l2 * np.cos(q1) + g.l3 * np.sin(q1 - q2)
    z = g.l1 + g.l2 * np.sin(q1) - g.l3 * np.cos(q1 - q2)
    return np.stack([np.cos(q0) * rho, np.sin(q0) * rho, z], axis=-1)


def jacobian(q: npt.ArrayLike, g: RRR = RRR()) -> FloatArray:
    """Analytic d(fk)/dq, (..., 3, 3): rows x, y, z (m), columns q0, q1, q2 (rad)."""
    qa = _q(q)
    q0, q1, q2 = qa[..., 0], qa[..., 1], qa[..., 2]
    c0, s0 = np.cos(q0), np.sin(q0)
    sphi, cphi = np.sin(q1 - q2), np.cos(q1 - q2)
    rho = g.l2 * np.cos(q1) + g.l3 * sphi
    drho1 = -g.l2 * np.sin(q1) + g.l3 * cphi
    drho2 = -g.l3 * cphi
    zero = np.zeros_like(q0)
    rows = [
        np.stack([-s0 * rho, c0 * drho1, c0 * drho2], axis=-1),
        np.stack([c0 * rho, s0 * drho1, s0 * drho2], axis=-1),
        np.stack([zero, rho, -g.l3 * sphi], axis=-1),
    ]
    return np.stack(rows, axis=-2)


def ik(
    p: npt.ArrayLike,
    g: RRR = RRR(),
    lower: npt.ArrayLike | None = None,
    upper: npt.ArrayLike | None = None,
) -> IKSolutions:
    """Every joint solution for tip points ``p`` (..., 3) m.

    Two elbow branches times two base branches (q0 and q0 + pi with the reach
    negated), angles wrapped to (-pi, pi]. On the base axis (x = y = 0) q0 is
    free; we pick q0 = 0 (and pi for the flipped pair). If ``lower`` and
    ``upper`` (3,) are given, solutions outside them are marked invalid too.
    """
    pa = np.asarray(p, dtype=np.float64)
    if pa.shape[-1:] != (3,):
        raise ValueError(f"expected points of shape (..., 3), got {pa.shape}")
    x, y, zr = pa[..., 0], pa[..., 1], pa[..., 2] - g.l1
    rho = np.hypot(x, y)
    q0 = np.arctan2(y, x)
    c = (rho**2 + zr**2 - g.l2**2 - g.l3**2) / (2.0 * g.l2 * g.l3)
    ok = np.abs(c) <= 1.0 + _TOL
    t2 = np.arccos(np.clip(c, -1.0, 1.0))  # planar relative elbow angle, >= 0
    base = np.stack([q0, q0, q0 + np.pi, q0 + np.pi], axis=-1)
    reach = np.stack([rho, rho, -rho, -rho], axis=-1)
    t2b = np.stack([t2, -t2, t2, -t2], axis=-1)
    zb = zr[..., None]
    t1 = np.arctan2(zb, reach) - np.arctan2(g.l3 * np.sin(t2b), g.l2 + g.l3 * np.cos(t2b))
    q = np.stack([wrap(base), wrap(t1), wrap(-t2b - np.pi / 2.0)], axis=-1)
    valid = np.broadcast_to(ok[..., None], q.shape[:-1]).copy()
    if lower is not None and upper is not None:
        valid &= within(q, lower, upper)
    return IKSolutions(q=np.where(valid[..., None], q, np.nan), valid=valid)


def ik_one(
    p: npt.ArrayLike,
    g: RRR = RRR(),
    lower: npt.ArrayLike | None = None,
    upper: npt.ArrayLike | None = None,
) -> list[FloatArray]:
    """Distinct solutions (each (3,) rad) for one point ``p`` (3,) m.

    Raises :class:`Unreachable` with the reason: out of reach (farther than
    L2 + L3 from the shoulder), inside the inner hole (closer than |L2 - L3|),
    or, with limits given, every solution outside the joint limits. On the
    base axis q0 = 0 is chosen (any q0 would do).
    """
    pa = np.asarray(p, dtype=np.float64).reshape(3)
    if not np.all(np.isfinite(pa)):
        raise Unreachable(f"target {pa.tolist()} is not a finite point")
    d = float(np.hypot(np.hypot(pa[0], pa[1]), pa[2] - g.l1))
    outer, inner = g.l2 + g.l3, abs(g.l2 - g.l3)
    if d > outer * (1.0 + _TOL):
        raise Unreachable(f"out of reach: {d:.3f} m from the shoulder, reach is {outer:.3f} m")
    if d < inner * (1.0 - _TOL):
        raise Unreachable(
            f"inside the inner hole: {d:.3f} m from the shoulder, the arm cannot fold"
            f" closer than |L2 - L3| = {inner:.3f} m"
        )
    sols = ik(pa, g)
    return distinct_solutions(sols.q[sols.valid], pa, lower, upper)


def ik_near(
    p: npt.ArrayLike,
    q_prev: npt.ArrayLike,
    g: RRR = RRR(),
    lower: npt.ArrayLike | None = None,
    upper: npt.ArrayLike | None = None,
) -> FloatArray:
    """The solution nearest ``q_prev`` (..., 3), unwrapped next to it; (..., 3) rad.

    Nearness is the wrapped joint distance, so tracking a path point by point
    stays on one branch. With limits given, in-limit solutions are preferred
    (use that to pick a start, not to track a path: it may jump branches), but
    an out-of-limit one is still returned when no other exists, so the caller
    can say which joint is out. NaN if unreachable.
    """
    sols = ik(p, g)
    qp = np.asarray(q_prev, dtype=np.float64)[..., None, :]
    cand = qp + wrap(sols.q - qp)
    cost = np.sum((cand - qp) ** 2, axis=-1)
    if lower is not None and upper is not None:
        cost = cost + 1e6 * ~within(cand, lower, upper)
    cost = np.where(sols.valid, cost, np.inf)
    k = np.argmin(cost, axis=-1)
    best = np.take_along_axis(cand, k[..., None, None], axis=-2)[..., 0, :]
    return np.asarray(best)


def _cond(j: FloatArray) -> FloatArray:
    return condition_number(j)


def _guarded_solve(
    a: FloatArray, b: FloatArray, max_cond: float
) -> tuple[FloatArray, FloatArray]:
    """Solve a x = b on stacks; NaN rows where cond(a) > max_cond (or NaN)."""
    cond = _cond(a)
    ok = cond <= max_cond
    safe = np.where(ok[..., None, None], a, np.eye(a.shape[-1]))
    bb = np.broadcast_to(b, safe.shape[:-1])
    x = np.linalg.solve(safe, bb[..., None])[..., 0]
    return np.where(ok[..., None], x, np.nan), cond


def inverse_velocity(
    q: npt.ArrayLike, xdot: npt.ArrayLike, g: RRR = RRR(), max_cond: float = 1e4
) -> tuple[FloatArray, FloatArray]:
    """Joint rates (..., 3) rad/s giving tip velocity ``xdot`` (..., 3) m/s at ``q``.

    Solves J qdot = xdot (no explicit inverse). Returns ``(qdot, cond)`` with
    ``cond`` (...,) the 2-norm condition number of J; rows with cond above
    ``max_cond`` (near a singularity: arm stretched, folded, or tip on the
    base axis) get NaN qdot.
    """
    return _guarded_solve(jacobian(q, g), np.asarray(xdot, dtype=np.float64), max_cond)


def inverse_velocity_one(
    q: npt.ArrayLike, xdot: npt.ArrayLike, g: RRR = RRR(), max_cond: float = 1e4
) -> FloatArray:
    """Single-configuration :func:`inverse_velocity`; raises :class:`Singular`."""
    qdot, cond = inverse_velocity(np.reshape(q, 3), np.reshape(xdot, 3), g, max_cond)
    if not np.all(np.isfinite(qdot)):
        raise Singular(
            f"singular: Jacobian condition number {float(cond):.3g} exceeds {max_cond:.3g};"
            " move away from full stretch, full fold or the base axis",
            float(cond),
        )
    return qdot


def tip_force(
    q: npt.ArrayLike, tau: npt.ArrayLike, g: RRR = RRR(),
    max_cond: float = TIP_FORCE_MAX_COND,
) -> FloatArray:
    """Tip force (..., 3) N balancing joint torques ``tau`` (..., 3) N m.

    Solves J^T F = tau; NaN rows where cond(J) exceeds ``max_cond`` (the one rule,
    :data:`kinematics.singular.TIP_FORCE_MAX_COND`).
    """
    jt = np.swapaxes(jacobian(q, g), -1, -2)
    f, _ = _guarded_solve(jt, np.asarray(tau, dtype=np.float64), max_cond)
    return f


def tip_force_one(
    q: npt.ArrayLike, tau: npt.ArrayLike, g: RRR = RRR(),
    max_cond: float = TIP_FORCE_MAX_COND,
) -> FloatArray:
    """Single-configuration :func:`tip_force` (3,) N; raises :class:`Singular`."""
    f = tip_force(np.reshape(q, 3), np.reshape(tau, 3), g, max_cond)
    if not np.all(np.isfinite(f)):
        cond = float(_cond(jacobian(np.reshape(q, 3), g)))
        raise Singular(
            f"singular: Jacobian condition number {cond:.3g} exceeds {max_cond:.3g}; the"
            " torques do not determine a unique tip force here",
            cond,
        )
    return f


def workspace(
    g: RRR,
    lower: npt.ArrayLike,
    upper: npt.ArrayLike,
    n: int,
    rng: np.random.Generator | None = None,
) -> FloatArray:
    """Tip points (n, 3) m from joints drawn uniformly within the limits (3,)."""
    return fk(draw(lower, upper, n, rng), g)


def bounds(
    g: RRR,
    lower: npt.ArrayLike,
    upper: npt.ArrayLike,
    n: int = 20_000,
    rng: np.random.Generator | None = None,
) -> tuple[FloatArray, FloatArray]:
    """Axis-aligned box (min (3,), max (3,)) m of the reachable workspace.

    Estimated from ``n`` samples plus the 8 joint-limit corners, so it is a
    slight inner approximation (a few mm with the default n).
    """
    pts = fk(np.concatenate([draw(lower, upper, n, rng), corners(lower, upper)]), g)
    return pts.min(axis=0), pts.max(axis=0)
