"""Angler arm: a PPRP manipulator, joints ``(dx, dy, t3, dz)`` (m, m, rad, m).

Two ball-screw carriages move the column in x and y, ``t3`` turns an arm of
length ``r`` about the vertical, and a winch lowers the magnet, which hangs
``h`` below the z carriage. Tip position::

    tip = (dx - r sin t3,  dy + r cos t3,  dz - h)

Forward kinematics is the product of the DH link transforms (standard
convention ``A = Rz(theta) Tz(d) Tx(a) Rx(alpha)``) after a fixed base
rotation ``T0 = Ry(+pi/2)`` that points z0 along world x, so that the first
prismatic joint moves along x::

    i  joint   theta           d          a   alpha
    1  dx      0               dx         0   -pi/2    prismatic along world x
    2  dy      -pi/2           dy         0   +pi/2    prismatic along world y
    3  t3      t3 + pi/2       0          r   0        revolute about world z
    4  dz      0               dz - h     0   0        prismatic along world z

Frame 2 is aligned with the world; frame 4's origin is the magnet.
Everything is vectorised over leading axes; geometry is :class:`PPRP`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
import numpy.typing as npt

from kinematics.errors import Unreachable
from kinematics.limits import distinct_solutions, draw, within
from kinematics.rrr import wrap

__all__ = [
    "PPRP",
    "IKSolutions",
    "auto_case",
    "bounds",
    "design_theta3",
    "dh_transform",
    "fk",
    "fk_pose",
    "ik",
    "ik_near",
    "ik_one",
    "inverse_velocity",
    "jacobian",
    "workspace",
]

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]
Case = Literal["dx_zero", "dx_used"]


@dataclass(frozen=True)
class PPRP:
    """``r``: t3 axis to the magnet, m; ``h``: drop from z carriage to magnet, m."""

    r: float = 0.1
    h: float = 0.05


@dataclass(frozen=True)
class IKSolutions:
    """Solutions ``q`` (..., K, 4), NaN where ``valid`` (..., K) is False."""

    q: FloatArray
    valid: BoolArray


def _q(q: npt.ArrayLike) -> FloatArray:
    qa = np.asarray(q, dtype=np.float64)
    if qa.shape[-1:] != (4,):
        raise ValueError(f"expected joints of shape (..., 4), got {qa.shape}")
    return qa


def dh_transform(
    theta: npt.ArrayLike, d: npt.ArrayLike, a: npt.ArrayLike, alpha: npt.ArrayLike
) -> FloatArray:
    """Standard DH link transform Rz(theta) Tz(d) Tx(a) Rx(alpha), (..., 4, 4).

    Parameters broadcast together; trig is taken before broadcasting, so a
    constant alpha costs one cos, not one per point.
    """
    th, dd, aa, al = (np.asarray(v, dtype=np.float64) for v in (theta, d, a, alpha))
    out = np.zeros(np.broadcast_shapes(th.shape, dd.shape, aa.shape, al.shape) + (4, 4))
    ct, st, ca, sa = np.cos(th), np.sin(th), np.cos(al), np.sin(al)
    out[..., 0, 0], out[..., 0, 1], out[..., 0, 2], out[..., 0, 3] = ct, -st * ca, st * sa, aa * ct
    out[..., 1, 0], out[..., 1, 1], out[..., 1, 2], out[..., 1, 3] = st, ct * ca, -ct * sa, aa * st
    out[..., 2, 1], out[..., 2, 2], out[..., 2, 3] = sa, ca, dd
    out[..., 3, 3] = 1.0
    return out


_T0 = np.array([[0.0, 0.0, 1.0, 0.0], [0.0, 1.0, 0.0, 0.0], [-1.0, 0.0, 0.0, 0.0],
                [0.0, 0.0, 0.0, 1.0]])  # Ry(+pi/2)


def fk_pose(q: npt.ArrayLike, g: PPRP = PPRP()) -> FloatArray:
    """Magnet pose (..., 4, 4) as T0 A1 A2 A3 A4 from the DH table above."""
    qa = _q(q)
    dx, dy, t3, dz = qa[..., 0], qa[..., 1], qa[..., 2], qa[..., 3]
    hp = np.pi / 2.0
    a1 = dh_transform(0.0, dx, 0.0, -hp)
    a2 = dh_transform(-hp, dy, 0.0, hp)
    a3 = dh_transform(t3 + hp, 0.0, g.r, 0.0)
    a4 = dh_transform(0.0, dz - g.h, 0.0, 0.0)
    return np.asarray(_T0 @ a1 @ a2 @ a3 @ a4)


def fk(q: npt.ArrayLike, g: PPRP = PPRP()) -> FloatArray:
    """Magnet position (..., 3) m for joints ``q`` (..., 4)."""
    return np.asarray(fk_pose(q, g)[..., :3, 3])


def jacobian(q: npt.ArrayLike, g: PPRP = PPRP()) -> FloatArray:
    """d(fk)/dq, (..., 3, 4): rows x, y, z; columns dx, dy, t3, dz."""
    qa = _q(q)
    t3 = qa[..., 2]
    j = np.zeros(qa.shape[:-1] + (3, 4))
    j[..., 0, 0] = 1.0
    j[..., 1, 1] = 1.0
    j[..., 2, 3] = 1.0
    j[..., 0, 2] = -g.r * np.cos(t3)
    j[..., 1, 2] = -g.r * np.sin(t3)
    return j


def design_theta3(x: npt.ArrayLike) -> FloatArray:
    """The design document's second IK case: dx = px - r for px > 0 (px + r for px < 0), so
    t3 = asin((dx - px) / r) = -pi/2 (+pi/2): the arm points along +x (-x) and the x
    carriage stands r short of the target. px = 0 takes -pi/2."""
    return np.where(np.asarray(x, dtype=np.float64) < 0.0, np.pi / 2.0, -np.pi / 2.0)


def auto_case(p: npt.ArrayLike, g: PPRP = PPRP()) -> Case:
    """The design document's choice when none is named: dx = 0 where the arm alone reaches
    x (|px| <= r), else the second case."""
    x = float(np.asarray(p, dtype=np.float64).reshape(3)[0])
    return "dx_zero" if abs(x) <= g.r * (1.0 + 1e-12) else "dx_used"


def ik(
    p: npt.ArrayLike,
    g: PPRP = PPRP(),
    case: Case = "dx_zero",
    theta3: npt.ArrayLike | None = None,
    lower: npt.ArrayLike | None = None,
    upper: npt.ArrayLike | None = None,
) -> IKSolutions:
    """Joint solutions for magnet points ``p`` (..., 3) m.

    The arm is redundant in the plane (3 joints for x, y), so one freedom is
    fixed by ``case``:

    - ``"dx_zero"``: dx = 0, t3 = asin(-x / r) and its twin pi - asin(-x / r)
      (K = 2), dy = y - r cos t3. Valid only where |x| <= r.
    - ``"dx_used"``: t3 = ``theta3`` (rad, broadcast over points), dx = x + r sin t3,
      dy = y - r cos t3 (K = 1). Always valid geometrically. With ``theta3`` None, the
      design document's case 2 (:func:`design_theta3`): t3 = -/+ pi/2, dx = px -/+ r.

    In both, dz = z + h (inverts :func:`fk` exactly). With ``lower``/``upper``
    (4,) given, out-of-limit solutions are marked invalid.
    """
    pa = np.asarray(p, dtype=np.float64)
    if pa.shape[-1:] != (3,):
        raise ValueError(f"expected points of shape (..., 3), got {pa.shape}")
    x, y, z = pa[..., 0], pa[..., 1], pa[..., 2]
    if case == "dx_zero":
        s = -x / g.r
        ok = np.abs(s) <= 1.0 + 1e-12
        a = np.arcsin(np.clip(s, -1.0, 1.0))
        t3 = np.stack([a, wrap(np.pi - a)], axis=-1)
        dx = np.zeros_like(t3)
        valid = np.stack([ok, ok], axis=-1)
    elif case == "dx_used":
        th = design_theta3(x) if theta3 is None else np.asarray(theta3, dtype=np.float64)
        t3 = np.broadcast_to(th, x.shape)[..., None]
        dx = x[..., None] + g.r * np.sin(t3)
        valid = np.isfinite(t3)
    else:
        raise ValueError(f"unknown case {case!r}: expected 'dx_zero' or 'dx_used'")
    dy = y[..., None] - g.r * np.cos(t3)
    dz = np.broadcast_to((z + g.h)[..., None], t3.shape)
    q = np.stack([dx, dy, t3, dz], axis=-1)
    valid = np.array(valid, dtype=bool)
    if lower is not None and upper is not None:
        valid &= within(q, lower, upper)
    return IKSolutions(q=np.where(valid[..., None], q, np.nan), valid=valid)


def ik_one(
    p: npt.ArrayLike,
    g: PPRP = PPRP(),
    case: Case | None = "dx_zero",
    theta3: float | None = None,
    lower: npt.ArrayLike | None = None,
    upper: npt.ArrayLike | None = None,
) -> list[FloatArray]:
    """Distinct solutions (each (4,)) for one point ``p`` (3,) m.

    With ``case`` None: every solution of both cases, the automatic choice first
    (:func:`auto_case`): ``dx_zero``'s twins where |x| <= r, then ``dx_used``'s.

    Raises :class:`Unreachable` with the reason: in case ``dx_zero`` the arm
    alone must cover x, so |x| > r cannot be reached; with limits given, every
    solution outside the joint limits.
    """
    pa = np.asarray(p, dtype=np.float64).reshape(3)
    if not np.all(np.isfinite(pa)):
        raise Unreachable(f"target {pa.tolist()} is not a finite point")
    if case is None:
        first = auto_case(pa, g)
        if first == "dx_used":
            return ik_one(pa, g, "dx_used", theta3, lower, upper)
        both = [ik(pa, g, "dx_zero"), ik(pa, g, "dx_used", theta3)]
        q = np.concatenate([x.q[x.valid] for x in both])
        return distinct_solutions(q, pa, lower, upper)
    if case == "dx_zero" and abs(pa[0]) > g.r * (1.0 + 1e-12):
        raise Unreachable(
            f"out of reach with dx fixed at 0: |x| = {abs(pa[0]):.3f} m exceeds the arm"
            f" radius r = {g.r:.3f} m by {abs(pa[0]) - g.r:.3f} m; use case 'dx_used'"
        )
    sols = ik(pa, g, case, theta3)
    return distinct_solutions(sols.q[sols.valid], pa, lower, upper)


def ik_near(
    p: npt.ArrayLike,
    q_prev: npt.ArrayLike,
    g: PPRP = PPRP(),
    case: Case = "dx_used",
    lower: npt.ArrayLike | None = None,
    upper: npt.ArrayLike | None = None,
) -> FloatArray:
    """The solution nearest ``q_prev`` (..., 4); (..., 4), NaN if none.

    ``dx_used`` keeps t3 at ``q_prev``'s value (pure carriage motion);
    ``dx_zero`` picks the nearer t3 twin. With limits, in-limit solutions win.
    """
    qp = np.asarray(q_prev, dtype=np.float64)
    sols = ik(p, g, case, qp[..., 2])
    cost = np.sum((sols.q - qp[..., None, :]) ** 2, axis=-1)
    if lower is not None and upper is not None:
        cost = cost + 1e6 * ~within(sols.q, lower, upper)
    cost = np.where(sols.valid, cost, np.inf)
    k = np.argmin(cost, axis=-1)
    return np.asarray(np.take_along_axis(sols.q, k[..., None, None], axis=-2)[..., 0, :])


def inverse_velocity(
    q: npt.ArrayLike,
    xdot: npt.ArrayLike,
    g: PPRP = PPRP(),
    t3_rate: npt.ArrayLike | None = None,
) -> tuple[FloatArray, FloatArray]:
    """Joint rates (..., 4) for tip velocity ``xdot`` (..., 3) m/s at ``q``.

    With ``t3_rate`` None: the minimum-norm solution qdot = J^T (J J^T)^-1 xdot.
    Its norm mixes m/s and rad/s (1 rad/s weighs as 1 m/s), which in practice
    favours turning t3. With ``t3_rate`` (rad/s) given: t3 turns at that rate and
    the carriages make up the rest (dx' = vx + r cos t3 w, dy' = vy + r sin t3 w).
    J always has rank 3 here, so there is no singularity; ``cond`` (...,) is
    returned for symmetry with :func:`kinematics.rrr.inverse_velocity`.
    """
    j = jacobian(q, g)
    v = np.asarray(xdot, dtype=np.float64)
    s = np.linalg.svd(j, compute_uv=False)
    cond = np.asarray(s[..., 0] / s[..., -1])
    if t3_rate is None:
        jjt = j @ np.swapaxes(j, -1, -2)
        lam = np.linalg.solve(jjt, np.broadcast_to(v, jjt.shape[:-1])[..., None])
        return np.asarray((np.swapaxes(j, -1, -2) @ lam)[..., 0]), cond
    t3 = _q(q)[..., 2]
    w = np.broadcast_to(np.asarray(t3_rate, dtype=np.float64), t3.shape)
    dx = v[..., 0] + g.r * np.cos(t3) * w
    dy = v[..., 1] + g.r * np.sin(t3) * w
    return np.stack(np.broadcast_arrays(dx, dy, w, v[..., 2]), axis=-1), cond


def workspace(
    g: PPRP,
    lower: npt.ArrayLike,
    upper: npt.ArrayLike,
    n: int,
    rng: np.random.Generator | None = None,
) -> FloatArray:
    """Magnet points (n, 3) m from joints drawn uniformly within the limits (4,)."""
    return fk(draw(lower, upper, n, rng), g)


def bounds(g: PPRP, lower: npt.ArrayLike, upper: npt.ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Exact axis-aligned box (min (3,), max (3,)) m of the reachable workspace.

    x spans dx +- r sin t3 and y spans dy + r cos t3 over the t3 interval; the
    extremes of sin and cos on [t_lo, t_hi] are at the ends or at multiples
    of pi/2 inside it.
    """
    lo = np.asarray(lower, dtype=np.float64)
    hi = np.asarray(upper, dtype=np.float64)
    k = np.arange(np.ceil(lo[2] / (np.pi / 2)), np.floor(hi[2] / (np.pi / 2)) + 1)
    t = np.concatenate([[lo[2], hi[2]], k * np.pi / 2])
    ox, oy = -g.r * np.sin(t), g.r * np.cos(t)
    mn = np.array([lo[0] + ox.min(), lo[1] + oy.min(), lo[3] - g.h])
    mx = np.array([hi[0] + ox.max(), hi[1] + oy.max(), hi[3] - g.h])
    return mn, mx
