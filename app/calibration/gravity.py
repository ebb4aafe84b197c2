"""The gravity fit: the joint torques that gravity puts on an arm, as a model with a term per
link, fitted to torques measured at rest at a few poses.

Model. Each body point of the arm (a joint origin after the base, and the tip:
`KinematicsModel.joint_origins`) carries an unknown weight w_k (N). Holding it against gravity
takes, at joint j, the torque w_k * dz_k/dq_j (the virtual work of lifting the point: N m for a
revolute joint, N for a prismatic one), so

    tau(q) = B(q) w + b,    B[j, k] = dz_k/dq_j (q)

with b a constant per joint (the sensor's zero error, which a tare would otherwise take). A
link of mass m with its centre of mass at a fraction f along it is a weight (1 - f) m g at its
near point and f m g at its far one, so one term per body point covers every link whose mass
sits on the line between its joints (the rbe3001's links and claw exactly). B comes from
central differences of `joint_origins`, one vectorised call per pose; the fit is linear least
squares over every joint of every pose.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from app.arms.model import KinematicsModel
from kinematics.singular import condition_number

#: Central-difference step, rad or m: far above float64 rounding at these lengths, far below
#: any curvature that matters (the error is O(h^2), about 1e-9 of the lever).
STEP = 1e-5


def basis(model: KinematicsModel, q: np.ndarray) -> np.ndarray:
    """B(q), (n, P): d z_k / d q_j for every body point k after the base, one q (n,)."""
    q = np.asarray(q, dtype=float)
    n = q.shape[0]
    qs = np.concatenate([q + STEP * np.eye(n), q - STEP * np.eye(n)])
    z = np.asarray(model.joint_origins(qs), dtype=float)[:, 1:, 2]  # (2n, P)
    return np.asarray((z[:n] - z[n:]) / (2.0 * STEP))


@dataclass
class GravityFit:
    """The fitted weights per body point (N), the constant per joint (N m or N), and how
    well they fit (the RMS of the residual torques, the largest residual)."""

    weights: list[float]
    bias: list[float]
    poses: list[list[float]]
    rms: float
    worst: float
    time: float = field(default_factory=time.time)

    def torques(self, model: KinematicsModel, q: np.ndarray) -> np.ndarray:
        """The torques gravity (and the constant) put on the joints at q, (n,)."""
        return np.asarray(basis(model, q) @ np.asarray(self.weights) + np.asarray(self.bias))

    def to_json(self) -> dict[str, Any]:
        return {"weights": self.weights, "bias": self.bias, "poses": self.poses,
                "rms": self.rms, "worst": self.worst, "time": self.time}

    @classmethod
    def from_json(cls, data: dict[str, Any], n: int) -> GravityFit:
        """A stored fit; ValueError if it does not fit an arm of `n` joints."""
        fit = cls(weights=[float(v) for v in data["weights"]],
                  bias=[float(v) for v in data["bias"]],
                  poses=[[float(v) for v in p] for p in data.get("poses", [])],
                  rms=float(data["rms"]), worst=float(data["worst"]),
                  time=float(data["time"]))
        if len(fit.bias) != n:
            raise ValueError(f"a stored gravity fit for {len(fit.bias)} joints, not {n}")
        return fit


def fit(model: KinematicsModel, poses: np.ndarray, torques: np.ndarray) -> GravityFit:
    """Least squares over every joint of every pose: `poses` (m, n) joint values, `torques`
    (m, n) the torques measured at rest there (raw: no gravity, no tare taken off)."""
    poses = np.asarray(poses, dtype=float)
    torques = np.asarray(torques, dtype=float)
    m, n = poses.shape
    rows = [np.hstack([basis(model, q), np.eye(n)]) for q in poses]
    a = np.vstack(rows)  # (m n, P + n)
    y = torques.reshape(-1)
    x, *_ = np.linalg.lstsq(a, y, rcond=None)
    resid = a @ x - y
    p = a.shape[1] - n
    return GravityFit(weights=[float(v) for v in x[:p]], bias=[float(v) for v in x[p:]],
                      poses=poses.tolist(), rms=float(np.sqrt(np.mean(resid**2))),
                      worst=float(np.max(np.abs(resid))))


#: A default pose's Jacobian condition number stays under this: near a singularity a torque
#: error of one ADC step is a large tip force, and the fit is meant for the working poses.
POSE_COND_MAX = 8.0


def default_poses(model: KinematicsModel, home: np.ndarray, lower: np.ndarray,
                  upper: np.ndarray) -> np.ndarray:
    """A few poses that tell the terms apart: home, and each joint gravity acts on (one whose
    motion lifts some body point) at a quarter of its range from either end, the others at
    home; a pose whose Jacobian's condition number is over POSE_COND_MAX comes back halfway
    towards home (up to four times). A joint about a vertical axis (the rbe3001's base) lifts
    nothing and is left at home."""
    home = np.asarray(home, dtype=float)
    b = basis(model, home)
    poses = [home]
    for j in range(home.shape[0]):
        if np.allclose(b[j], 0.0, atol=1e-6):
            continue
        span = upper[j] - lower[j]
        for v in (lower[j] + 0.25 * span, upper[j] - 0.25 * span):
            q = home.copy()
            q[j] = v
            for _ in range(4):
                if condition_number(model.jacobian(q)) <= POSE_COND_MAX:
                    break
                q[j] = (q[j] + home[j]) / 2.0
            poses.append(q)
    return np.array(poses)
