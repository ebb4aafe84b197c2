"""ROBOTIS OpenManipulator-X (RM-X52-TNM): four revolute joints and a gripper.

Sources: the ROBOTIS e-manual, https://emanual.robotis.com/docs/en/platform/openmanipulator_x/
("Specification" page, sections "Hardware Specification" (reach 380 mm, 46 rpm joints,
XM430-W350-T actuators) and "Dimension" (the side-view drawing: 77 mm from the base to the
shoulder axis, 128 mm up and 24 mm forward to the elbow, 124 mm elbow to wrist, 126 mm
wrist to the gripper's tip)), and the kinematic chain ROBOTIS ships for it (open_manipulator
``open_manipulator_x.cpp`` ``addJoint``, which the e-manual's controller pages use): joint 1
(about z) sits 12 mm forward and 17 mm up from the base origin, joint 2 (about y) 59.5 mm
above joint 1, joint 3 (about y) at (24, 0, 128) mm from joint 2, joint 4 (about y) 124 mm
along from joint 3, the tool 126 mm along from joint 4; limits (rad) joint 1 [-pi, pi],
joint 2 [-2.05, pi/2], joint 3 [-pi/2, 1.53], joint 4 [-1.8, 2.0]; ids 11..14, gripper 15.

Joint order ``q = (q0 waist, q1 shoulder, q2 elbow, q3 wrist)`` rad; positions are metres in
the base frame (x forward, z up). Joints 2..4 turn about +y, so a positive angle tips the
link forward and down. In the arm's vertical plane (``r`` along the arm, ``z`` up) the link
angles from the horizontal are::

    s1 = beta - q1          # link 2 (shoulder -> elbow), beta = atan2(128, 24)
    s2 = -(q1 + q2)         # link 3 (elbow -> wrist)
    s3 = -(q1 + q2 + q3)    # the tool (wrist -> tip): this is the PITCH
    r  = L2 cos s1 + L3 cos s2 + L4 cos s3          L2 = hypot(24, 128) mm
    z  = H + L2 sin s1 + L3 sin s2 + L4 sin s3      H = 17 + 59.5 mm
    x  = BX + r cos q0,   y = r sin q0               BX = 12 mm

``pitch`` (API.md "Wrist pitch") is ``s3``: the tool's angle from the horizontal in the
arm's vertical plane, positive with the tool pointing up, measured along the arm's own
``r`` axis (the direction ``q0``). With every joint at 0 the arm stands as an inverted L:
tip at (286, 0, 204.5) mm, pitch 0.

IK branches (for a target ``x, y, z, pitch``): two base branches (``q0`` and ``q0 + pi``
with the reach negated, leaning back over the base; the pitch is then measured along the
flipped ``r`` axis, so FK reports the same pitch) times two elbow branches (``t = s2 - s1``
negative: elbow up; positive: elbow down). Everything is vectorised over leading axes;
geometry is :class:`OMX`, limits are arguments (they come from the profile).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from kinematics.errors import Singular, Unreachable
from kinematics.limits import corners, distinct_solutions, draw, within
from kinematics.rrr import wrap

__all__ = [
    "IDS",
    "LOWER",
    "OMX",
    "POINTS",
    "UPPER",
    "IKSolutions",
    "bounds",
    "fk",
    "ik",
    "ik_near",
    "ik_one",
    "ik_position",
    "inverse_velocity",
    "jacobian",
    "joint_origins",
    "workspace",
    "wrap",
]

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]

#: joint limits (rad) of joints 1..4, ROBOTIS open_manipulator_x ``addJoint``
LOWER = (-math.pi, -2.05, -math.pi / 2.0, -1.8)
UPPER = (math.pi, math.pi / 2.0, 1.53, 2.0)
#: gripper joint range, m (each finger from the middle), ROBOTIS ``addTool``
GRIPPER_MIN, GRIPPER_MAX = -0.010, 0.010
#: Dynamixel ids: joints 1..4 then the gripper (OpenManipulator-X defaults)
IDS = (11, 12, 13, 14, 15)
#: the names of :func:`joint_origins`' points, base first, tip last
POINTS = ("base", "waist", "shoulder", "elbow", "wrist", "tip")
#: the e-manual's pose "home" of the ROBOTIS controller (rad) and its init pose (all zero)
HOME = (0.0, -1.05, 0.35, 0.70)
INIT = (0.0, 0.0, 0.0, 0.0)

_TOL = 1e-12  # slack on the reach boundary, relative to the link lengths
_PITCHES = 1441  # pitch candidates of ik_position over (-pi, pi]: a 0.25 deg grid


@dataclass(frozen=True)
class OMX:
    """Geometry in metres; defaults are ROBOTIS's (see the module docstring)."""

    bx: float = 0.012  # joint 1 axis forward of the base origin
    bz: float = 0.017  # joint 1 frame above the base origin
    d1: float = 0.0595  # joint 2 axis above joint 1's frame
    a2x: float = 0.024  # joint 3 forward of joint 2 (arm upright)
    a2z: float = 0.128  # joint 3 above joint 2 (arm upright)
    l3: float = 0.124  # joint 3 to joint 4
    l4: float = 0.126  # joint 4 to the tool tip

    @property
    def h(self) -> float:
        """Height of the shoulder axis above the base origin, m (76.5 mm, ~77)."""
        return self.bz + self.d1

    @property
    def l2(self) -> float:
        """Shoulder axis to elbow axis, m (hypot(24, 128) mm = 130.2 mm)."""
        return math.hypot(self.a2x, self.a2z)

    @property
    def beta(self) -> float:
        """Angle of link 2 above the horizontal at q1 = 0, rad (atan2(128, 24))."""
        return math.atan2(self.a2z, self.a2x)


@dataclass(frozen=True)
class IKSolutions:
    """Every IK branch: ``q`` (..., 4, 4) rad, NaN where ``valid`` (..., 4) is False.

    Branch order: (base, elbow) = (q0, up), (q0, down), (q0 + pi, up), (q0 + pi, down).
    """

    q: FloatArray
    valid: BoolArray


def _q(q: npt.ArrayLike) -> FloatArray:
    qa = np.asarray(q, dtype=np.float64)
    if qa.shape[-1:] != (4,):
        raise ValueError(f"expected joints of shape (..., 4), got {qa.shape}")
    return qa


def _angles(qa: FloatArray, g: OMX) -> tuple[FloatArray, FloatArray, FloatArray]:
    q1, q2, q3 = qa[..., 1], qa[..., 2], qa[..., 3]
    return g.beta - q1, -(q1 + q2), -(q1 + q2 + q3)


def fk(q: npt.ArrayLike, g: OMX = OMX()) -> FloatArray:
    """Tip position and pitch (..., 4) = (x, y, z m, pitch rad) for joints (..., 4) rad."""
    qa = _q(q)
    s1, s2, s3 = _angles(qa, g)
    r = g.l2 * np.cos(s1) + g.l3 * np.cos(s2) + g.l4 * np.cos(s3)
    z = g.h + g.l2 * np.sin(s1) + g.l3 * np.sin(s2) + g.l4 * np.sin(s3)
    q0 = qa[..., 0]
    return np.stack([g.bx + r * np.cos(q0), r * np.sin(q0), z, wrap(s3)], axis=-1)


def joint_origins(q: npt.ArrayLike, g: OMX = OMX()) -> FloatArray:
    """The points of :data:`POINTS` (..., 6, 3) m for ``q`` (..., 4) rad: the base origin,
    joint 1's frame, the shoulder, elbow and wrist axes and the tip (= ``fk[..., :3]``)."""
    qa = _q(q)
    s1, s2, s3 = _angles(qa, g)
    c0, s0 = np.cos(qa[..., 0]), np.sin(qa[..., 0])
    r_e, z_e = g.l2 * np.cos(s1), g.h + g.l2 * np.sin(s1)
    r_w, z_w = r_e + g.l3 * np.cos(s2), z_e + g.l3 * np.sin(s2)
    r_t, z_t = r_w + g.l4 * np.cos(s3), z_w + g.l4 * np.sin(s3)
    out = np.zeros(qa.shape[:-1] + (6, 3))
    out[..., 1, 0], out[..., 1, 2] = g.bx, g.bz
    out[..., 2, 0], out[..., 2, 2] = g.bx, g.h
    for k, (r, z) in enumerate(((r_e, z_e), (r_w, z_w), (r_t, z_t)), start=3):
        out[..., k, 0], out[..., k, 1], out[..., k, 2] = g.bx + c0 * r, s0 * r, z
    return out


def jacobian(q: npt.ArrayLike, g: OMX = OMX()) -> FloatArray:
    """Analytic d(fk)/dq, (..., 4, 4): rows x, y, z (m), pitch (rad); columns q0..q3."""
    qa = _q(q)
    s1, s2, s3 = _angles(qa, g)
    c0, s0 = np.cos(qa[..., 0]), np.sin(qa[..., 0])
    r = g.l2 * np.cos(s1) + g.l3 * np.cos(s2) + g.l4 * np.cos(s3)
    dr3 = g.l4 * np.sin(s3)
    dr2 = g.l3 * np.sin(s2) + dr3
    dr1 = g.l2 * np.sin(s1) + dr2
    dz3 = -g.l4 * np.cos(s3)
    dz2 = -g.l3 * np.cos(s2) + dz3
    dz1 = -g.l2 * np.cos(s1) + dz2
    zero, one = np.zeros_like(r), np.ones_like(r)
    rows = [
        np.stack([-s0 * r, c0 * dr1, c0 * dr2, c0 * dr3], axis=-1),
        np.stack([c0 * r, s0 * dr1, s0 * dr2, s0 * dr3], axis=-1),
        np.stack([zero, dz1, dz2, dz3], axis=-1),
        np.stack([zero, -one, -one, -one], axis=-1),
    ]
    return np.stack(rows, axis=-2)


def _target(p: npt.ArrayLike) -> FloatArray:
    pa = np.asarray(p, dtype=np.float64)
    if pa.shape[-1:] != (4,):
        raise ValueError(f"expected (x, y, z, pitch) of shape (..., 4), got {pa.shape}")
    return pa


def ik(
    p: npt.ArrayLike,
    g: OMX = OMX(),
    lower: npt.ArrayLike | None = None,
    upper: npt.ArrayLike | None = None,
) -> IKSolutions:
    """Every joint solution for targets ``p`` (..., 4) = (x, y, z m, pitch rad).

    Four branches (see :class:`IKSolutions`), angles wrapped to (-pi, pi]. On the waist
    axis (x = BX, y = 0) q0 is free; we pick q0 = 0 (and pi for the flipped pair). With
    ``lower`` and ``upper`` (4,) given, solutions outside them are marked invalid too.
    """
    pa = _target(p)
    dx, y, z, pitch = pa[..., 0] - g.bx, pa[..., 1], pa[..., 2], pa[..., 3]
    rho = np.hypot(dx, y)
    q0 = np.arctan2(y, dx)
    base = np.stack([q0, q0, q0 + np.pi, q0 + np.pi], axis=-1)
    reach = np.stack([rho, rho, -rho, -rho], axis=-1)
    s3 = pitch[..., None]
    wr = reach - g.l4 * np.cos(s3)  # wrist in the arm plane, from the shoulder
    wz = (z - g.h)[..., None] - g.l4 * np.sin(s3)
    c = (wr**2 + wz**2 - g.l2**2 - g.l3**2) / (2.0 * g.l2 * g.l3)
    ok = np.abs(c) <= 1.0 + _TOL
    t = np.arccos(np.clip(c, -1.0, 1.0)) * np.array([-1.0, 1.0, -1.0, 1.0])
    s1 = np.arctan2(wz, wr) - np.arctan2(g.l3 * np.sin(t), g.l2 + g.l3 * np.cos(t))
    s2 = s1 + t
    q1 = g.beta - s1
    q2 = -s2 - q1
    q3 = s2 - s3
    q = np.stack([wrap(base), wrap(q1), wrap(q2), wrap(q3)], axis=-1)
    valid = ok & np.isfinite(q).all(axis=-1)
    if lower is not None and upper is not None:
        valid &= within(q, lower, upper)
    return IKSolutions(q=np.where(valid[..., None], q, np.nan), valid=valid)


def ik_one(
    p: npt.ArrayLike,
    g: OMX = OMX(),
    lower: npt.ArrayLike | None = None,
    upper: npt.ArrayLike | None = None,
) -> list[FloatArray]:
    """Distinct solutions (each (4,) rad) for one target ``p`` (4,) = (x, y, z, pitch).

    Raises :class:`Unreachable` with the reason: the wrist point (the target less the tool
    along the pitch) farther from the shoulder than L2 + L3 or closer than |L2 - L3|, or,
    with limits given, every solution outside the joint limits.
    """
    pa = np.asarray(p, dtype=np.float64).reshape(4)
    if not np.all(np.isfinite(pa)):
        raise Unreachable(f"target {pa.tolist()} is not a finite point and pitch")
    sols = ik(pa, g)
    if not sols.valid.any():
        rho = math.hypot(pa[0] - g.bx, pa[1])
        wz = pa[2] - g.h - g.l4 * math.sin(pa[3])
        ds = [math.hypot(r - g.l4 * math.cos(pa[3]), wz) for r in (rho, -rho)]
        outer, inner = g.l2 + g.l3, abs(g.l2 - g.l3)
        if min(ds) > outer * (1.0 + _TOL):
            raise Unreachable(
                f"out of reach at pitch {pa[3]:.3f} rad: the wrist would be {min(ds):.3f} m"
                f" from the shoulder, L2 + L3 is {outer:.3f} m"
            )
        d = max(x for x in ds if x <= outer * (1.0 + _TOL))
        raise Unreachable(
            f"too close at pitch {pa[3]:.3f} rad: the wrist would be {d:.4f} m from the"
            f" shoulder, the arm cannot fold closer than |L2 - L3| = {inner:.4f} m"
        )
    return distinct_solutions(sols.q[sols.valid], pa[:3], lower, upper)


def ik_position(
    p: npt.ArrayLike,
    g: OMX = OMX(),
    lower: npt.ArrayLike | None = None,
    upper: npt.ArrayLike | None = None,
    prefer: float | None = None,
) -> tuple[float, list[FloatArray]]:
    """IK of a position alone: ``(pitch, solutions)`` for ``p`` (3,) = (x, y, z) m.

    The rule: the pitch is the one nearest ``prefer`` for which a solution facing the
    target exists (waist turned towards it, not the flipped branches), within the limits
    when given; only if no pitch has one are the flipped branches used. ``prefer``
    defaults to the elevation of the target seen from the shoulder axis,
    ``atan2(z - H, rho)``: the tool continues the line from the shoulder, which leaves
    the wrist straight for a far target, points the tool down at a point low near the
    base and up at one overhead. Candidates are ``prefer`` itself and a 0.25 deg grid
    over (-pi, pi]; the answer is exact for the pitch returned (FK(IK) = p).
    Raises :class:`Unreachable` when no pitch reaches the point.
    """
    pa = np.asarray(p, dtype=np.float64).reshape(3)
    if not np.all(np.isfinite(pa)):
        raise Unreachable(f"target {pa.tolist()} is not a finite point")
    rho = math.hypot(pa[0] - g.bx, pa[1])
    want = math.atan2(pa[2] - g.h, rho) if prefer is None else float(prefer)
    grid = np.linspace(-np.pi, np.pi, _PITCHES)[1:]
    cand = np.concatenate([[want], want + wrap(grid - want)])
    targets = np.concatenate([np.broadcast_to(pa, (cand.size, 3)), cand[:, None]], axis=1)
    valid = ik(targets, g, lower, upper).valid
    front = valid[:, :2].any(axis=-1)  # facing the target (q0 towards it)
    ok = front if front.any() else valid.any(axis=-1)
    if not ok.any():
        reach = g.l2 + g.l3 + g.l4
        raise Unreachable(
            f"out of reach: ({pa[0]:.3f}, {pa[1]:.3f}, {pa[2]:.3f}) m is reached at no"
            f" pitch{' within the joint limits' if lower is not None else ''}"
            f" (reach from the shoulder {reach:.3f} m)"
        )
    dist = np.where(ok, np.abs(wrap(cand - want)), np.inf)
    best = float(wrap(cand[int(np.argmin(dist))]))
    sols = ik_one((*pa, best), g, lower, upper)
    if front.any() and rho > 0.0:
        q0 = math.atan2(pa[1], pa[0] - g.bx)
        sols = [s for s in sols if abs(float(wrap(s[0] - q0))) < 1e-9] or sols
    return best, sols


def ik_near(
    p: npt.ArrayLike,
    q_prev: npt.ArrayLike,
    g: OMX = OMX(),
    lower: npt.ArrayLike | None = None,
    upper: npt.ArrayLike | None = None,
) -> FloatArray:
    """The solution for ``p`` (..., 4) nearest ``q_prev`` (..., 4), unwrapped next to it.

    Nearness is the wrapped joint distance, so tracking a path stays on one branch; with
    limits given, in-limit solutions are preferred. NaN where unreachable.
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


def inverse_velocity(
    q: npt.ArrayLike, xdot: npt.ArrayLike, g: OMX = OMX(), max_cond: float = 1e4
) -> FloatArray:
    """Joint rates (4,) rad/s giving ``xdot`` (4,) = (m/s, m/s, m/s, rad/s) at one ``q``.

    Solves J qdot = xdot with the mixed-unit 4x4 Jacobian; raises :class:`Singular` when
    its condition number exceeds ``max_cond`` (stretched or folded arm, wrist on the
    waist axis).
    """
    j = jacobian(np.reshape(q, 4), g)
    s = np.linalg.svd(j, compute_uv=False)
    cond = float(s[0] / s[-1]) if s[-1] > 0 else math.inf
    if not cond <= max_cond:
        raise Singular(
            f"singular: Jacobian condition number {cond:.3g} exceeds {max_cond:.3g}; move"
            " away from full stretch, full fold or the waist axis",
            cond,
        )
    return np.asarray(np.linalg.solve(j, np.reshape(np.asarray(xdot, dtype=np.float64), 4)))


def workspace(
    g: OMX,
    lower: npt.ArrayLike,
    upper: npt.ArrayLike,
    n: int,
    rng: np.random.Generator | None = None,
) -> FloatArray:
    """Tip positions and pitches (n, 4) from joints drawn uniformly within the limits (4,)."""
    return fk(draw(lower, upper, n, rng), g)


def bounds(
    g: OMX,
    lower: npt.ArrayLike,
    upper: npt.ArrayLike,
    n: int = 20_000,
    rng: np.random.Generator | None = None,
) -> tuple[FloatArray, FloatArray]:
    """Axis-aligned box (min (3,), max (3,)) m of the reachable tip positions, from ``n``
    samples plus the 16 joint-limit corners (a slight inner approximation)."""
    pts = fk(np.concatenate([draw(lower, upper, n, rng), corners(lower, upper)]), g)[:, :3]
    return pts.min(axis=0), pts.max(axis=0)
