"""Time scaling: jerk-limited joint moves and straight Cartesian lines.

Joint moves are planned by ruckig (the jerk-limited online trajectory
generator used by MoveIt and ros2_control), time-synchronised so every joint
arrives together. A straight line is a 1-DOF ruckig profile on the arc length
``s``, turned into joint samples by dense IK every ``dt`` and checked against
the joint limits before anything moves.

Both results expose the same surface (:class:`TrajectoryLike`): ``duration``
(s), ``sample(t) -> (q, qd, qdd)`` and ``sample_grid(dt)``, so the executor
treats them alike. Units: s, and rad or m per joint.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np
import numpy.typing as npt
import ruckig  # type: ignore[import-not-found, import-untyped, unused-ignore]

from kinematics.errors import KinematicsError, LimitViolation, TrajectoryError, Unreachable
from kinematics.limits import first_violation, unit

__all__ = [
    "IKFn",
    "JointTrajectory",
    "SampledTrajectory",
    "TrajectoryError",
    "TrajectoryLike",
    "plan_joint",
    "plan_line",
    "plan_stop",
    "ruckig_reason",
    "time_grid",
]

FloatArray = npt.NDArray[np.float64]
#: Most samples a straight line may have (IK runs at each, in order): 10 min at 100 Hz. A tiny
#: speed made ruckig plan a 1-DOF arc-length profile of 4.7e8 s (351 GiB of time grid).
MAX_LINE_SAMPLES = 60_000
Samples = tuple[FloatArray, FloatArray, FloatArray]
IKFn = Callable[[FloatArray, FloatArray | None], FloatArray]
"""``ik_fn(p (3,) m, q_prev (n,) or None) -> q (n,)``: the branch continuous with
``q_prev``; NaN or raising :class:`KinematicsError` when ``p`` has no solution."""
FKFn = Callable[[FloatArray], FloatArray]


class TrajectoryLike(Protocol):
    """What the motion executor needs from any trajectory."""

    @property
    def duration(self) -> float: ...

    def sample(self, t: npt.ArrayLike) -> Samples: ...

    def sample_grid(self, dt: float) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]: ...


def time_grid(duration: float, dt: float) -> FloatArray:
    """Times 0, dt, 2 dt, ... ending exactly at ``duration``, (m,) s, m >= 1."""
    if not dt > 0:
        raise ValueError(f"dt must be positive, got {dt}")
    m = int(np.ceil(duration / dt - 1e-9)) + 1
    return np.asarray(np.minimum(np.arange(m) * dt, duration), dtype=np.float64)


@dataclass(eq=False)
class JointTrajectory:
    """A ruckig trajectory over ``dofs`` joints; ``duration`` in s."""

    traj: Any = field(repr=False)
    dofs: int
    duration: float

    def sample(self, t: npt.ArrayLike) -> Samples:
        """Position, velocity, acceleration at times ``t`` (...,) s, each (..., n).

        Times are clipped to [0, duration]; one ruckig evaluation per time
        (about 0.5 us each, fine for tens of thousands of samples).
        """
        ta = np.clip(np.asarray(t, dtype=np.float64), 0.0, self.duration)
        flat = ta.reshape(-1)
        out = np.array([self.traj.at_time(float(ti)) for ti in flat], dtype=np.float64)
        out = out.reshape(ta.shape + (3, self.dofs))
        return out[..., 0, :], out[..., 1, :], out[..., 2, :]

    def sample_grid(self, dt: float) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        """``(t (m,), q, qd, qdd (m, n))`` on :func:`time_grid`."""
        t = time_grid(self.duration, dt)
        return (t, *self.sample(t))


@dataclass(frozen=True, eq=False)
class SampledTrajectory:
    """Dense samples: ``times`` (m,) s increasing from 0; ``q``, ``qd``, ``qdd`` (m, n)."""

    times: FloatArray
    q: FloatArray
    qd: FloatArray
    qdd: FloatArray

    @property
    def duration(self) -> float:
        return float(self.times[-1])

    def sample(self, t: npt.ArrayLike) -> Samples:
        """Linear interpolation at ``t`` (...,) s (clipped), each (..., n)."""
        ta = np.clip(np.asarray(t, dtype=np.float64), 0.0, self.duration)
        if self.times.size == 1:
            shape = ta.shape + self.q.shape[1:]
            return (np.broadcast_to(self.q[0], shape).copy(), np.zeros(shape), np.zeros(shape))
        i = np.clip(np.searchsorted(self.times, ta, side="right") - 1, 0, self.times.size - 2)
        w = ((ta - self.times[i]) / (self.times[i + 1] - self.times[i]))[..., None]

        def lerp(a: FloatArray) -> FloatArray:
            return np.asarray(a[i] + w * (a[i + 1] - a[i]))

        return lerp(self.q), lerp(self.qd), lerp(self.qdd)

    def sample_grid(self, dt: float) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        t = time_grid(self.duration, dt)
        return (t, *self.sample(t))


def _vec(name: str, v: npt.ArrayLike, n: int, positive: bool = False) -> FloatArray:
    a = np.broadcast_to(np.asarray(v, dtype=np.float64), (n,)).copy()
    if not np.all(np.isfinite(a)):
        raise KinematicsError(f"{name} must be finite, got {a.tolist()}")
    if positive and not np.all(a > 0):
        raise KinematicsError(f"{name} must be positive, got {a.tolist()}")
    return a


#: What each of ruckig's error results means, in words a caller can act on. The Python
#: binding's `Result` enum lacks some of them (-101 raised `ValueError: -101 is not a valid
#: Result`), so results are handled by number.
RUCKIG_ERRORS: dict[int, str] = {
    -1: "ruckig failed to calculate a trajectory",
    -100: "the input is invalid (limits, positions or durations out of range)",
    -101: f"the move would last longer than ruckig's limit of {7.6e3:.0f} s: ask for a higher"
          " speed or a shorter move",
    -102: "the positional limits cannot be kept",
    -104: "a velocity, acceleration or jerk limit is zero",
    -110: "the execution time of a joint could not be calculated (the limits are too far apart"
          " in scale, e.g. a speed fraction far too small)",
    -111: "the joints could not be synchronised to arrive together",
}

_RESULT_NUMBER = re.compile(r"(-?\d+) is not a valid")


def ruckig_reason(code: int) -> str:
    """A person's reading of ruckig result `code` (any negative number is an error)."""
    return RUCKIG_ERRORS.get(code, f"ruckig returned error {code}")


def _calculate(n: int, inp: Any, what: str) -> Any:
    """Run ruckig offline on `inp` and answer the trajectory, or raise :class:`TrajectoryError`
    with the result's meaning for every result that is not Working/Finished, known or not."""
    traj = ruckig.Trajectory(n)
    try:
        result = ruckig.Ruckig(n).calculate(inp, traj)
    except ruckig.RuckigError as exc:
        raise TrajectoryError(f"{what}: {exc}", -1) from None
    except ValueError as exc:  # a result number the binding's enum does not list
        m = _RESULT_NUMBER.search(str(exc))
        code = int(m.group(1)) if m else -1
        raise TrajectoryError(f"{what}: {ruckig_reason(code)}", code) from None
    code = int(result)
    if code < 0:
        raise TrajectoryError(f"{what}: {ruckig_reason(code)}", code)
    return traj


def plan_joint(
    q0: npt.ArrayLike,
    q1: npt.ArrayLike,
    vmax: npt.ArrayLike,
    amax: npt.ArrayLike,
    jmax: npt.ArrayLike,
    *,
    v0: npt.ArrayLike | None = None,
    a0: npt.ArrayLike | None = None,
    duration: float | None = None,
    speed: float = 1.0,
) -> JointTrajectory:
    """Time-optimal jerk-limited move from ``q0`` to rest at ``q1`` (n,).

    ``vmax``, ``amax``, ``jmax`` (n,) or scalar: rad or m per s, s^2, s^3.
    ``speed`` in (0, 1] scales ``vmax``. ``v0``/``a0`` (n,) start from a moving
    state (replanning a "replace" request from the current sample keeps q, qd
    and qdd continuous). ``duration`` (s) stretches the move to at least that
    long; a duration shorter than the fastest feasible move raises
    :class:`KinematicsError` naming both.
    """
    a_start = np.atleast_1d(np.asarray(q0, dtype=np.float64))
    n = a_start.size
    if not 0.0 < speed <= 1.0:
        raise KinematicsError(f"speed must be in (0, 1], got {speed}")
    inp = ruckig.InputParameter(n)
    inp.current_position = _vec("q0", a_start, n).tolist()
    inp.target_position = _vec("q1", q1, n).tolist()
    inp.current_velocity = _vec("v0", 0.0 if v0 is None else v0, n).tolist()
    inp.current_acceleration = _vec("a0", 0.0 if a0 is None else a0, n).tolist()
    inp.max_velocity = (_vec("vmax", vmax, n, True) * speed).tolist()
    inp.max_acceleration = _vec("amax", amax, n, True).tolist()
    inp.max_jerk = _vec("jmax", jmax, n, True).tolist()
    if duration is not None:
        if not (np.isfinite(duration) and duration >= 0):
            raise KinematicsError(f"duration must be finite and >= 0 s, got {duration}")
        inp.minimum_duration = float(duration)
    traj = _calculate(n, inp, "no trajectory within the limits")
    if duration is not None and traj.duration > duration + 1e-9:
        raise KinematicsError(
            f"requested duration {duration:.3f} s is shorter than the fastest move within"
            f" the limits, {traj.duration:.3f} s"
        )
    return JointTrajectory(traj=traj, dofs=n, duration=float(traj.duration))


def plan_stop(
    q0: npt.ArrayLike,
    v0: npt.ArrayLike,
    a0: npt.ArrayLike,
    amax: npt.ArrayLike,
    jmax: npt.ArrayLike,
    vmax: npt.ArrayLike,
) -> JointTrajectory:
    """Bring a moving state (q0, v0, a0) to rest as fast as the acceleration and jerk limits
    allow: ruckig's velocity interface with a target velocity of zero. Where the joints end is
    whatever braking needs; the caller clips to the joint limits. Used to cancel a motion
    ("decelerates, holds") and to stop before a new straight line."""
    a_start = np.atleast_1d(np.asarray(q0, dtype=np.float64))
    n = a_start.size
    inp = ruckig.InputParameter(n)
    inp.control_interface = ruckig.ControlInterface.Velocity
    inp.current_position = _vec("q0", a_start, n).tolist()
    inp.current_velocity = _vec("v0", v0, n).tolist()
    inp.current_acceleration = _vec("a0", a0, n).tolist()
    inp.target_velocity = [0.0] * n
    inp.target_acceleration = [0.0] * n
    # ruckig needs a velocity limit that the current state does not exceed
    vlim = np.maximum(_vec("vmax", vmax, n, True), np.abs(np.asarray(inp.current_velocity)))
    inp.max_velocity = vlim.tolist()
    inp.max_acceleration = np.maximum(_vec("amax", amax, n, True),
                                      np.abs(np.asarray(inp.current_acceleration))).tolist()
    inp.max_jerk = _vec("jmax", jmax, n, True).tolist()
    traj = _calculate(n, inp, "no stopping trajectory")
    return JointTrajectory(traj=traj, dofs=n, duration=float(traj.duration))


def _where(k: int, m: int, p: FloatArray, s: float, length: float) -> str:
    return (f"point {k} of {m} at ({p[0]:.4f}, {p[1]:.4f}, {p[2]:.4f}) m,"
            f" {s:.4f} m of {length:.4f} m along the line")


def _dense_ik(
    pts: FloatArray, s: FloatArray, length: float, ik_fn: IKFn, q_start: FloatArray | None,
    names: Sequence[str], lower: npt.ArrayLike, upper: npt.ArrayLike, kinds: Sequence[str],
) -> FloatArray:
    """IK at every point, each continuous with the previous; raises at the first failure.

    Sequential by nature (each branch choice depends on the one before), so
    this is the one loop over points; it stops at the first unreachable point
    after checking the points before it against the limits.
    """
    m = pts.shape[0]
    qs: list[FloatArray] = []
    q_prev = q_start
    for k in range(m):
        reason = ""
        try:
            qk = np.asarray(ik_fn(pts[k], q_prev), dtype=np.float64)
        except KinematicsError as exc:
            qk, reason = np.full(len(names), np.nan), str(exc)
        if not np.all(np.isfinite(qk)):
            bad = first_violation(np.array(qs), names, lower, upper, kinds) if qs else None
            if bad is not None:
                j = bad[0]
                raise LimitViolation(f"line refused at {_where(j, m, pts[j], s[j], length)}: "
                                     + "; ".join(bad[1]))
            raise Unreachable(f"line refused at {_where(k, m, pts[k], s[k], length)}: "
                              + (reason or "no IK solution"))
        qs.append(qk)
        q_prev = qk
    return np.array(qs)


def plan_line(
    p0: npt.ArrayLike,
    p1: npt.ArrayLike,
    ik_fn: IKFn,
    fk_fn: FKFn,
    vmax_tip: float,
    amax_tip: float,
    jmax_tip: float,
    dt: float,
    joint_vmax: npt.ArrayLike,
    lower: npt.ArrayLike,
    upper: npt.ArrayLike,
    names: Sequence[str],
    kinds: Sequence[str],
    *,
    speed: float = 1.0,
    q_start: npt.ArrayLike | None = None,
    retries: int = 4,
    path_tol: float = 1e-6,
) -> tuple[SampledTrajectory, FloatArray]:
    """Straight tip line ``p0`` -> ``p1`` (3,) m, rest to rest; returns (joints, tip (m, 3)).

    The arc length follows a jerk-limited profile (tip limits in m/s, m/s^2,
    m/s^3; ``speed`` scales ``vmax_tip``), sampled every ``dt`` s; IK at every
    sample starts from ``q_start`` (the current joints, a branch hint). The
    plan is refused before anything moves: :class:`Unreachable` or
    :class:`LimitViolation` naming the first offending point, joint, limit and
    margin. If a joint would exceed ``joint_vmax`` (n,), the tip speed is
    lowered and the line retimed, up to ``retries`` times, before refusing.
    A joint stepping more than 10 ``joint_vmax`` ``dt`` between samples is a
    discontinuity (singularity or branch change) and is refused at once.
    ``tip`` is FK of the joint samples, on the segment to ``path_tol`` m.
    """
    a, b = np.asarray(p0, dtype=np.float64).reshape(3), np.asarray(p1, dtype=np.float64).reshape(3)
    length = float(np.linalg.norm(b - a))
    u = (b - a) / length if length > 0 else np.zeros(3)
    qv = np.asarray(joint_vmax, dtype=np.float64)
    qs0 = None if q_start is None else np.asarray(q_start, dtype=np.float64)
    vt = float(vmax_tip) * speed
    if not 0.0 < speed <= 1.0:
        raise KinematicsError(f"speed must be in (0, 1], got {speed}")
    for attempt in range(retries + 1):
        if length > 0:
            prof = plan_joint([0.0], [length], vt, amax_tip, jmax_tip)
            if prof.duration / dt > MAX_LINE_SAMPLES:  # IK at every sample: bound the work
                raise TrajectoryError(
                    f"the line would last {prof.duration:.4g} s, {prof.duration / dt:.3g} samples"
                    f" of {dt * 1e3:g} ms; a line may have at most {MAX_LINE_SAMPLES}: ask for a"
                    " higher speed", 0)
            t, s, _, _ = prof.sample_grid(dt)
            s = s[:, 0]
        else:
            t, s = np.zeros(1), np.zeros(1)
        pts = a + s[:, None] * u
        q = _dense_ik(pts, s, length, ik_fn, qs0, names, lower, upper, kinds)
        bad = first_violation(q, names, lower, upper, kinds)
        if bad is not None:
            k = bad[0]
            raise LimitViolation(f"line refused at {_where(k, q.shape[0], pts[k], s[k], length)}: "
                                 + "; ".join(bad[1]))
        tip = np.asarray(fk_fn(q), dtype=np.float64)
        miss = np.linalg.norm(tip - pts, axis=-1)
        if np.any(miss > path_tol):
            k = int(np.argmax(miss > path_tol))
            raise Unreachable(f"line refused at {_where(k, q.shape[0], pts[k], s[k], length)}:"
                              f" IK misses the line by {miss[k]:.3g} m")
        if t.size < 2:
            z = np.zeros_like(q)
            return SampledTrajectory(t, q, z, z.copy()), tip
        step = np.abs(np.diff(q, axis=0))
        jump = step > 10.0 * qv * dt
        if np.any(jump):
            k, j = (int(v) for v in np.argwhere(jump)[0])
            raise Unreachable(
                f"line refused at {_where(k, q.shape[0], pts[k], s[k], length)}: {names[j]}"
                f" jumps by {step[k, j]:.3g} {unit(kinds[j])} to the next point; the line"
                " crosses a singularity or the IK changes branch"
            )
        qd = np.gradient(q, t, axis=0)
        qd[0] = qd[-1] = 0.0  # the arc-length profile starts and ends at rest
        ratio = np.abs(qd) / qv
        worst = float(ratio.max())
        if worst <= 1.0:
            return SampledTrajectory(t, q, qd, np.gradient(qd, t, axis=0)), tip
        if attempt < retries:
            vt *= 0.95 / worst
            continue
        k, j = (int(v) for v in np.unravel_index(int(np.argmax(ratio)), ratio.shape))
        un = unit(kinds[j])
        raise LimitViolation(
            f"line refused at {_where(k, q.shape[0], pts[k], s[k], length)}: {names[j]}"
            f" would need {abs(qd[k, j]):.3g} {un}/s, above its limit {qv[j]:.3g} {un}/s, even"
            f" with the tip slowed to {vt:.3g} m/s"
        )
    raise AssertionError("unreachable")  # pragma: no cover
