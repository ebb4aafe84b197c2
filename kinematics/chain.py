"""Every joint origin of an arm, not only its tip: the points a safety envelope checks.

A keep-out zone that the elbow would sweep matters as much as one the tip would enter, so the
envelope checks the origin of every link frame along the chain. Each function takes joints
``q`` (..., n) and answers points (..., k, 3) in metres in the arm's base frame, in the order
of its ``*_POINTS`` names; the last point is the tip and equals the arm's ``fk``.

- RRR (rbe3001), ``q = (base, shoulder, elbow)`` rad: the base origin on the table, the
  shoulder axis ``l1`` above it, the elbow at the end of link 2, the tip.
- PPRP (angler), ``q = (dx, dy, t3, dz)``: the DH frame origins 0..4 of :mod:`kinematics.pprp`
  in closed form: the base, the x carriage, the column foot on the y carriage, the end of the
  t3 arm, the magnet (tip).

Vectorised over leading axes (ARCHITECTURE rule 7): no Python loop over points.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from kinematics.pprp import PPRP
from kinematics.pprp import _q as _q4
from kinematics.rrr import RRR
from kinematics.rrr import _q as _q3

__all__ = ["PPRP_POINTS", "RRR_POINTS", "pprp_points", "rrr_points"]

FloatArray = npt.NDArray[np.float64]

RRR_POINTS = ("base", "shoulder", "elbow", "tip")
PPRP_POINTS = ("base", "x_carriage", "column", "arm_end", "tip")


_RRR = RRR()
_PPRP = PPRP()


def rrr_points(q: npt.ArrayLike, g: RRR = _RRR) -> FloatArray:
    """Joint origins and tip (..., 4, 3) m of the RRR arm for ``q`` (..., 3) rad."""
    qa = _q3(q)
    q0, q1, q2 = qa[..., 0], qa[..., 1], qa[..., 2]
    c0, s0 = np.cos(q0), np.sin(q0)
    r_elbow = g.l2 * np.cos(q1)
    z_elbow = g.l1 + g.l2 * np.sin(q1)
    rho = r_elbow + g.l3 * np.sin(q1 - q2)
    z_tip = z_elbow - g.l3 * np.cos(q1 - q2)
    out = np.zeros(qa.shape[:-1] + (4, 3))
    out[..., 1, 2] = g.l1
    out[..., 2, 0], out[..., 2, 1], out[..., 2, 2] = c0 * r_elbow, s0 * r_elbow, z_elbow
    out[..., 3, 0], out[..., 3, 1], out[..., 3, 2] = c0 * rho, s0 * rho, z_tip
    return out


def pprp_points(q: npt.ArrayLike, g: PPRP = _PPRP) -> FloatArray:
    """Frame origins 0..4 (..., 5, 3) m of the PPRP arm for ``q`` (..., 4) (m, m, rad, m)."""
    qa = _q4(q)
    dx, dy, t3, dz = qa[..., 0], qa[..., 1], qa[..., 2], qa[..., 3]
    ax, ay = dx - g.r * np.sin(t3), dy + g.r * np.cos(t3)
    out = np.zeros(qa.shape[:-1] + (5, 3))
    out[..., 1, 0] = dx
    out[..., 2, 0], out[..., 2, 1] = dx, dy
    out[..., 3, 0], out[..., 3, 1] = ax, ay
    out[..., 4, 0], out[..., 4, 1], out[..., 4, 2] = ax, ay, dz - g.h
    return out
