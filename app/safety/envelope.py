"""The safety envelope of one arm: keep-out boxes, a floor plane and a speed override.

Every planned motion is checked along its whole trajectory, at the executor's control rate,
through the position of every joint origin and of the tip (the model's `joint_origins`), before
anything moves; so is every pass-through position command, on the path the device takes from
the measured position to its target (`check_path`: app/safety/guard.py `passthrough_path`, the
straight joint-space line for a PID step, each servo ramping at its own pace). A body point is
inside a zone when it lies in the box grown by its margin on every side (the tip's margin is
the tool's size, `tool_margin` in the profile's `[safety]`; the other points use
`body_margin`), and below the floor when its height is under `floor_z` plus that margin. A hit
is refused with 422 `keep_out` naming the zone (or `floor`), the body point, where it would be
and when.

The check is one vectorised pass over (time, body point, zone): no Python loop over points
(bench/envelope.py prints the rate). `speed_override` scales the velocity, acceleration and jerk
limits of motions planned after it changes (app/motion/executor.py asks `scaled`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal

import numpy as np

from app.config import SafetyConfig, SafetySettings
from app.errors import KeepOut
from kinematics.trajectory import time_grid

if TYPE_CHECKING:
    from app.arms.model import KinematicsModel

#: Joint-space resolution of a pass-through path check: rad for revolute, m for prismatic
#: joints. 2 mrad moves the rbe3001's 0.37 m reach by under 1 mm, and the sampled path is
#: at most MAX_PATH_POINTS long (a full-range sweep of the rbe3001's shoulder is ~1000).
PATH_STEP = {"revolute": 0.002, "prismatic": 0.0005}
MAX_PATH_POINTS = 4000


def path_fractions(delta: np.ndarray, kinds: Sequence[str]) -> np.ndarray:
    """Fractions 0..1 (N, 1) of a joint-space move `delta` (n,) sampled at PATH_STEP per
    joint, at most MAX_PATH_POINTS of them: where a path check looks."""
    step = np.array([PATH_STEP[k] for k in kinds])
    n = int(np.clip(np.ceil(np.max(np.abs(delta) / step)), 1, MAX_PATH_POINTS - 1))
    return np.linspace(0.0, 1.0, n + 1)[:, None]


@dataclass(frozen=True)
class _Compiled:
    """The settings as arrays, swapped in as one reference: a planner on another thread (the
    control thread) sees the old zones or the new ones, never half of each."""

    names: tuple[str, ...]
    lo: np.ndarray  # (B, Z, 3) each zone's min, grown by each body point's margin, m
    hi: np.ndarray  # (B, Z, 3)
    floor: np.ndarray | None  # (B,) floor_z plus each body point's margin, m

    @property
    def active(self) -> bool:
        return bool(self.names) or self.floor is not None


@dataclass(frozen=True)
class Hit:
    """The first point of a path inside a zone: which zone (or "floor"), which body point, where
    (m, base frame), at which sample index and time (s; or fraction of a pass-through path)."""

    zone: str
    body: str
    point: np.ndarray
    index: int
    t: float


class ArmSafety:
    """The envelope of one arm: the profile's settings until an instructor changes them."""

    def __init__(self, model: KinematicsModel, profile: SafetyConfig) -> None:
        self.model = model
        self.profile = profile
        self.bodies = model.points
        self.source: Literal["profile", "stored"] = "profile"
        self.settings: SafetySettings = SafetySettings(
            zones=profile.zones, floor_z=profile.floor_z, speed_override=profile.speed_override)
        margins = np.full(len(self.bodies), profile.body_margin)
        margins[-1] = profile.tool_margin
        self.margins = margins
        self._c = self._compile(self.settings)

    # ------------------------------------------------------------ settings

    def apply(self, settings: SafetySettings, source: Literal["profile", "stored"]) -> None:
        self._c = self._compile(settings)
        self.settings, self.source = settings, source

    def _compile(self, settings: SafetySettings) -> _Compiled:
        zones = settings.zones
        lo = np.array([[z.min.x, z.min.y, z.min.z] for z in zones]).reshape(-1, 3)
        hi = np.array([[z.max.x, z.max.y, z.max.z] for z in zones]).reshape(-1, 3)
        m = self.margins[:, None, None]
        floor = settings.floor_z
        return _Compiled(tuple(z.name for z in zones), lo[None, :, :] - m, hi[None, :, :] + m,
                         None if floor is None else floor + self.margins)

    def preview(self, settings: SafetySettings) -> ArmSafety:
        """A copy with other settings, to check them before they apply."""
        other = ArmSafety(self.model, self.profile)
        other.apply(settings, "stored")
        return other

    @property
    def speed_override(self) -> float:
        return self.settings.speed_override

    def scaled(self, *limits: np.ndarray | float) -> tuple[np.ndarray, ...]:
        """Velocity, acceleration and jerk limits (or Cartesian ones) times the override."""
        k = self.settings.speed_override
        return tuple(np.asarray(v, dtype=float) * k for v in limits)

    @property
    def active(self) -> bool:
        return self._c.active

    # ------------------------------------------------------------ geometry

    def points(self, q: np.ndarray) -> np.ndarray:
        """Body points (..., B, 3) m for joints q (..., n)."""
        return self.model.joint_origins(q)

    def first_hit(self, q: np.ndarray, t: np.ndarray) -> Hit | None:
        """The earliest of the poses q (T, n), at times t (T,), with a body point inside a
        zone or below the floor; None if there is none.

        Vectorised over time; the loop is over the (body point, zone) pairs whose boxes overlap
        (the path's bounding box against the grown zone, all pairs compared at once) and the
        body points that go below the floor: in the usual case, zones away from the path, the
        check is one min and max per body point and no loop."""
        c = self._c  # one snapshot for the whole check
        if not c.active:
            return None
        p = self.points(np.asarray(q, dtype=float).reshape(-1, self.model.n))  # (T, B, 3)
        lo_all, hi_all = p.min(axis=0), p.max(axis=0)  # (B, 3) the path's bounding boxes
        low = (lo_all[:, 2] < c.floor if c.floor is not None
               else np.zeros(p.shape[1], dtype=bool))  # (B,) below the floor somewhere
        near = (np.all(lo_all[:, None, :] <= c.hi, axis=-1)
                & np.all(hi_all[:, None, :] >= c.lo, axis=-1))  # (B, Z) boxes that overlap
        best: tuple[int, int, str] | None = None  # (time index, body, zone)
        for b in np.flatnonzero(low | near.any(axis=1)).tolist():
            x, y, z = p[:, b, 0], p[:, b, 1], p[:, b, 2]
            if low[b] and c.floor is not None:
                i = int(np.argmax(z < c.floor[b]))
                best = min(best, (i, b, "floor")) if best else (i, b, "floor")
            for j in np.flatnonzero(near[b]).tolist():
                name, lo, hi = c.names[j], c.lo[b, j], c.hi[b, j]
                # narrow the candidates axis by axis: each pass looks only at what is left
                cand = np.flatnonzero((x >= lo[0]) & (x <= hi[0]))
                for k, axis in ((1, y), (2, z)):
                    if cand.size:
                        v = axis[cand]
                        cand = cand[(v >= lo[k]) & (v <= hi[k])]
                if cand.size:
                    i = int(cand[0])
                    if best is None or (i, b) < best[:2]:
                        best = (i, b, name)
        if best is None:
            return None
        i, b, zone = best
        return Hit(zone, self.bodies[b], p[i, b].copy(), i, float(np.asarray(t)[i]))

    # ------------------------------------------------------------ checks

    def check_trajectory(self, traj: object, dt: float) -> None:
        """Every setpoint the executor will command (times 0, dt, ... duration): 422
        `keep_out` at the first one with a body point inside a zone or below the floor."""
        if not self.active:
            return
        # traj: a JointTrajectory or a SampledTrajectory (duration, sample), duck-typed
        t = time_grid(float(traj.duration), dt)  # type: ignore[attr-defined]  # see above
        q = np.asarray(traj.sample(t)[0], dtype=np.float64)  # type: ignore[attr-defined]  # ditto
        hit = self.first_hit(q, t)
        if hit is not None:
            raise KeepOut(self._describe(hit, q[hit.index], f"{hit.t:.2f} s into the motion"))

    def check_joint_path(self, q0: np.ndarray | None, q1: np.ndarray) -> None:
        """A target q1 and the straight joint-space path to it from q0 (None: the target
        alone), sampled at PATH_STEP."""
        q1 = np.asarray(q1, dtype=float)
        if q0 is None:
            self.check_path(q1[None, :], "to the commanded position")
            return
        q0 = np.asarray(q0, dtype=float)
        s = path_fractions(q1 - q0, self.model.kinds)
        self.check_path(q0 + s * (q1 - q0), "along the straight joint-space path to the "
                        "commanded position")

    def check_path(self, q: np.ndarray, what: str) -> None:
        """A joint path (N, n) sampled finely enough (PATH_STEP): 422 `keep_out` at its first
        pose with a body point inside a zone or below the floor."""
        if not self.active:
            return
        q = np.asarray(q, dtype=float).reshape(-1, self.model.n)
        s = np.linspace(0.0, 1.0, len(q))
        hit = self.first_hit(q, s)
        if hit is not None:
            raise KeepOut(self._describe(hit, q[hit.index], f"{hit.t:.0%} of the way {what}"))

    def check_pose(self, q: np.ndarray, what: str) -> None:
        hit = self.first_hit(np.asarray(q, dtype=float)[None, :], np.zeros(1))
        if hit is not None:
            raise KeepOut(self._describe(hit, np.asarray(q, dtype=float), what))

    def _describe(self, hit: Hit, q: np.ndarray, when: str) -> str:
        p = ", ".join(f"{v:.3f}" for v in hit.point)
        joints = ", ".join(f"{n} {v:.3f}" for n, v in zip(self.model.names, q, strict=True))
        margin = self.margins[self.bodies.index(hit.body)]
        grown = f" (grown by its {margin:g} m margin)" if margin > 0 else ""
        if hit.zone == "floor":
            where = (f"below the floor z = {self.settings.floor_z:g} m{grown}")
        else:
            where = f"inside keep-out zone '{hit.zone}'{grown}"
        return f"the {hit.body} would be {where} at ({p}) m, {when} (joints {joints})"
