"""A sample's derived fields (tip, tip velocity, tip force), computed for many samples at once.

They follow from the sample's joint readings and the arm's kinematics, so they need not be
computed at the poll rate when nobody reads them: the hub (app/telemetry/hub.py) computes them
when a sample is first read (a subscriber's batch, `GET /state`), for every sample of the batch
in one vectorised call. numpy's per-call overhead dominates one 3x3 Jacobian: a batch of 20
rbe3001 samples costs about 3 µs a sample against 66 µs one by one (bench/sample_cost.py).

The values are the same as the single-sample ones (`KinematicsModel.tip`, `jacobian`,
`tip_force`): the same forward kinematics, the tip velocity J @ qd (x, y, z rows), and the tip
force from J^T F = tau where cond(J) is within TIP_FORCE_MAX_COND (kinematics/singular.py: the
one rule), by a stacked solve for a square J and the pseudo-inverse (lstsq's minimum-norm
solution) otherwise.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Protocol

import numpy as np

from kinematics.singular import TIP_FORCE_MAX_COND, condition_number

#: A sample's joint readings: positions, velocities, torques (None: not sensed), joint units.
Readings = tuple[np.ndarray, np.ndarray, np.ndarray | None]


class Kinematics(Protocol):
    """What of an arm's model (app/arms/model.py `KinematicsModel`) the derivation uses."""

    def fk(self, q: np.ndarray) -> np.ndarray: ...

    def pitch(self, q: np.ndarray) -> np.ndarray | None: ...

    def jacobian(self, q: np.ndarray) -> np.ndarray: ...


def _jacobians(model: Kinematics, q: np.ndarray) -> np.ndarray:
    """(k, m, n) Jacobians of (k, n) joints: vectorised where the model's maths is (every
    built-in arm type's is), else one by one."""
    k, n = q.shape
    J = np.asarray(model.jacobian(q), dtype=float)
    if J.ndim == 3 and J.shape[0] == k and J.shape[2] == n:
        return J
    return np.stack([np.asarray(model.jacobian(q[i]), dtype=float) for i in range(k)])


def tip_forces(J: np.ndarray, tau: np.ndarray) -> np.ndarray:
    """(k, m) tip forces (N, and N m about a wrist's pitch axis) from (k, m, n) Jacobians and
    (k, n) joint torques; NaN rows where the singularity rule refuses one."""
    out = np.full(J.shape[:2], np.nan)
    ok = condition_number(J) <= TIP_FORCE_MAX_COND
    if not ok.any():
        return out
    Jt = np.swapaxes(J[ok], -1, -2)  # (k', n, m)
    t = tau[ok][..., None]
    if J.shape[1] == J.shape[2]:
        f = np.linalg.solve(Jt, t)
    else:
        f = np.linalg.pinv(Jt) @ t
    out[ok] = f[..., 0]
    return out


class Derivation:
    """`derive` for one arm, reusing the last values while the readings repeat (an arm at rest
    reads the same poll after poll: no kinematics at all then). `model()` gives the arm's
    model as it is now."""

    def __init__(self, model: Callable[[], Kinematics]) -> None:
        self.model = model
        #: (model, readings' key, (tip, tip velocity, tip force)) of the last sample derived,
        #: replaced whole: two readers deriving at once never pair one's key with the other's
        #: values.
        self._last: tuple[Kinematics, bytes, tuple[Any, Any, Any]] | None = None

    def __call__(self, items: list[tuple[dict[str, Any], Readings]]) -> None:
        model = self.model()
        last = self._last
        todo = []
        for sample, r in items:
            if last is not None and last[0] is model and last[1] == _key(r):
                sample["tip"], sample["tip_velocity"], sample["tip_force"] = last[2]
            else:
                todo.append((sample, r))
        derive(model, todo)
        if todo:
            sample, r = todo[-1]
            self._last = (model, _key(r),
                          (sample["tip"], sample["tip_velocity"], sample["tip_force"]))


def _key(r: Readings) -> bytes:
    return r[0].tobytes() + b"|" + r[1].tobytes() + b"|" + (b"-" if r[2] is None
                                                           else r[2].tobytes())


def derive(model: Kinematics, items: list[tuple[dict[str, Any], Readings]]) -> None:
    """Fill `tip`, `tip_velocity` and `tip_force` of each sample from its readings, all at once.
    A stale sample (velocities zero) gets them like any other, as before."""
    if not items:
        return
    k = len(items)
    q = np.array([r[0] for _, r in items], dtype=float)
    qd = np.array([r[1] for _, r in items], dtype=float)
    tips = np.asarray(model.fk(q), dtype=float).reshape(k, 3).tolist()
    pitch = model.pitch(q)
    pitches = None if pitch is None else np.asarray(pitch, dtype=float).reshape(k).tolist()
    J = _jacobians(model, q)
    v = np.einsum("kmn,kn->km", J, qd)[:, :3].tolist()
    forces: list[list[float] | None] = [None] * k
    sensed = [i for i, (_, r) in enumerate(items) if r[2] is not None]
    if sensed:
        tau = np.array([items[i][1][2] for i in sensed], dtype=float)
        f = tip_forces(J[sensed], tau)
        finite = np.all(np.isfinite(f), axis=1).tolist()
        rows = f[:, :3].tolist()
        for j, i in enumerate(sensed):
            if finite[j]:
                forces[i] = rows[j]
    for i, (sample, _) in enumerate(items):
        x, y, z = tips[i]
        tip = {"x": x, "y": y, "z": z}
        if pitches is not None:
            tip["pitch"] = pitches[i]
        sample["tip"] = tip
        vx, vy, vz = v[i]
        sample["tip_velocity"] = {"x": vx, "y": vy, "z": vz}
        f_i = forces[i]
        sample["tip_force"] = None if f_i is None else {"x": f_i[0], "y": f_i[1], "z": f_i[2]}
