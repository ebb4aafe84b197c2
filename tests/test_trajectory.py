"""Trajectories: limits on samples, endpoints, replanning, straight lines and refusals."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from kinematics import pprp, rrr
from kinematics import trajectory as tr
from kinematics.errors import KinematicsError, LimitViolation, Unreachable

seeds = st.integers(0, 2**32 - 1)
DT = 1e-3
REL = 1e-6

G = rrr.RRR()
LO = np.array([-1.5708, -0.35, -1.2])
HI = np.array([1.5708, 1.75, 2.4])
NAMES, KINDS = ["base", "shoulder", "elbow"], ["revolute"] * 3
VJ = np.array([1.5, 1.5, 1.5])


def check_limits(traj: tr.TrajectoryLike, vmax: np.ndarray, amax: np.ndarray,
                 jmax: np.ndarray) -> None:
    t, q, qd, qdd = traj.sample_grid(DT)
    assert np.all(np.abs(qd) <= vmax * (1 + REL) + 1e-12)
    assert np.all(np.abs(qdd) <= amax * (1 + REL) + 1e-12)
    # jerk is piecewise constant: a difference quotient averages two values within the bound
    jerk = np.diff(qdd, axis=0) / np.diff(t)[:, None]
    assert np.all(np.abs(jerk) <= jmax * (1 + REL) + 1e-9)


@settings(max_examples=30, deadline=None)
@given(seeds)
def test_joint_move_limits_and_endpoints(seed: int) -> None:
    rng = np.random.default_rng(seed)
    q0, q1 = rng.uniform(LO, HI), rng.uniform(LO, HI)
    v, a, j = rng.uniform(0.5, 2, 3), rng.uniform(2, 8, 3), rng.uniform(20, 80, 3)
    speed = float(rng.uniform(0.2, 1.0))
    traj = tr.plan_joint(q0, q1, v, a, j, speed=speed)
    check_limits(traj, v * speed, a, j)
    q, qd, qdd = traj.sample(np.array([0.0, traj.duration]))
    np.testing.assert_allclose(q, [q0, q1], atol=1e-9)
    np.testing.assert_allclose(qd, 0.0, atol=1e-9)
    np.testing.assert_allclose(qdd, 0.0, atol=1e-9)


def test_seed_duration_velocity_limited() -> None:
    # 1 rad at v=1, a=2, j=10: jerk phase a/j = 0.2 s, cruise; T = d/v + v/a + a/j = 1.7 s
    traj = tr.plan_joint([0.0], [1.0], 1.0, 2.0, 10.0)
    assert traj.duration == pytest.approx(1.7, abs=1e-9)
    assert traj.sample(0.85)[1][0] == pytest.approx(1.0, abs=1e-9)


def test_speed_scales_velocity() -> None:
    fast = tr.plan_joint([0.0], [1.0], 1.0, 2.0, 10.0)
    slow = tr.plan_joint([0.0], [1.0], 1.0, 2.0, 10.0, speed=0.5)
    assert slow.duration > fast.duration
    assert np.abs(slow.sample_grid(DT)[2]).max() == pytest.approx(0.5, rel=1e-6)
    with pytest.raises(KinematicsError, match="speed"):
        tr.plan_joint([0.0], [1.0], 1.0, 2.0, 10.0, speed=1.5)


def test_requested_duration() -> None:
    traj = tr.plan_joint([0.0, 0.0], [1.0, -0.2], 1.0, 2.0, 10.0, duration=3.0)
    assert traj.duration == pytest.approx(3.0)
    np.testing.assert_allclose(traj.sample(3.0)[0], [1.0, -0.2], atol=1e-9)
    with pytest.raises(KinematicsError, match=r"requested duration 0\.500 s .* 1\.700 s"):
        tr.plan_joint([0.0], [1.0], 1.0, 2.0, 10.0, duration=0.5)


def test_bad_limits_are_refused() -> None:
    with pytest.raises(KinematicsError, match="vmax must be positive"):
        tr.plan_joint([0.0], [1.0], 0.0, 2.0, 10.0)


@settings(max_examples=20, deadline=None)
@given(seeds)
def test_replan_from_moving_state_is_continuous(seed: int) -> None:
    rng = np.random.default_rng(seed)
    v, a, j = np.full(3, 1.5), np.full(3, 6.0), np.full(3, 60.0)
    first = tr.plan_joint(rng.uniform(LO, HI), rng.uniform(LO, HI), v, a, j)
    ts = float(rng.uniform(0.1, 0.9)) * first.duration
    q, qd, qdd = first.sample(ts)
    second = tr.plan_joint(q, rng.uniform(LO, HI), v, a, j, v0=qd, a0=qdd)
    q2, qd2, qdd2 = second.sample(0.0)
    np.testing.assert_allclose(q2, q, atol=1e-12)
    np.testing.assert_allclose(qd2, qd, atol=1e-12)
    np.testing.assert_allclose(qdd2, qdd, atol=1e-12)
    check_limits(second, v, a, j)


def test_sample_shapes() -> None:
    traj = tr.plan_joint([0.0, 1.0], [1.0, 0.0], 1.0, 2.0, 10.0)
    assert traj.sample(0.3)[0].shape == (2,)
    assert traj.sample(np.zeros((4, 5)))[2].shape == (4, 5, 2)
    t, q, _, _ = traj.sample_grid(0.01)
    assert t[0] == 0.0 and t[-1] == traj.duration and q.shape == (t.size, 2)
    np.testing.assert_allclose(traj.sample(99.0)[0], [1.0, 0.0], atol=1e-12)  # clipped


def test_sampled_trajectory_interpolates() -> None:
    t = np.array([0.0, 1.0, 3.0])
    q = np.array([[0.0, 1.0], [1.0, 1.0], [5.0, 0.0]])
    s = tr.SampledTrajectory(t, q, q * 2, q * 3)
    qa, qda, _ = s.sample(np.array([0.5, 2.0, 10.0]))
    np.testing.assert_allclose(qa, [[0.5, 1.0], [3.0, 0.5], [5.0, 0.0]])
    np.testing.assert_allclose(qda, 2 * qa)
    assert s.duration == 3.0 and s.sample(0.5)[0].shape == (2,)


def rrr_ik(p: np.ndarray, q_prev: np.ndarray | None) -> np.ndarray:
    """Branch continuous with q_prev; the reason from ik_one when there is none."""
    q = rrr.ik_near(p, np.zeros(3) if q_prev is None else q_prev, G)
    if np.isnan(q).any():
        rrr.ik_one(p, G)
    return q


def rrr_fk(q: np.ndarray) -> np.ndarray:
    return rrr.fk(q, G)


def line(p0: object, p1: object, vj: object = VJ, **kw: object) -> tuple[tr.SampledTrajectory,
                                                                          np.ndarray]:
    q0 = rrr.ik_near(p0, [0.4, 0.6, 0.3], G, LO, HI)
    return tr.plan_line(p0, p1, rrr_ik, rrr_fk, 0.1, 0.5, 5.0, 0.005, vj, LO, HI, NAMES, KINDS,
                        q_start=q0, **kw)  # type: ignore[arg-type]


@settings(max_examples=10, deadline=None)
@given(seeds)
def test_line_stays_on_the_segment(seed: int) -> None:
    rng = np.random.default_rng(seed)
    p0 = rrr.fk(rng.uniform([-0.5, 0.6, 0.0], [0.5, 1.2, 0.6]), G)
    p1 = p0 + rng.uniform(-0.05, 0.05, 3)
    traj, tip = line(p0, p1)
    d = p1 - p0
    s = (tip - p0) @ d / (d @ d)
    off = np.linalg.norm(tip - p0 - s[:, None] * d, axis=-1)
    assert off.max() < 1e-6 and s.min() > -1e-9 and s.max() < 1 + 1e-9
    assert np.all(np.diff(s) >= -1e-12)  # no backtracking
    np.testing.assert_allclose(tip[[0, -1]], [p0, p1], atol=1e-9)
    np.testing.assert_allclose(traj.qd[[0, -1]], 0.0)
    speed = np.linalg.norm(np.diff(tip, axis=0), axis=-1) / np.diff(traj.times)
    assert speed.max() <= 0.1 * (1 + 1e-3)
    assert np.all(np.abs(traj.qd) <= VJ)


def test_line_through_a_limit_names_the_joint() -> None:
    # from x > 0 to x < 0 at y = 0.1: the base angle atan2(y, x) passes 1.5708 rad midway
    with pytest.raises(LimitViolation, match=r"point \d+ of \d+ at .*: base 1\.57\d* rad is above"
                                             r" its limit 1\.57\d* rad by"):
        line([0.2, 0.1, 0.2], [-0.2, 0.1, 0.2])


def test_line_out_of_reach_names_the_point_and_reason() -> None:
    # wide limits so reach, not a joint limit, is the first problem on the way out
    msg = r"point \d+ .* out of reach: 0\.37\d m from the shoulder"
    with pytest.raises(Unreachable, match=msg):
        tr.plan_line([0.2, 0.1, 0.2], [0.5, 0.1, 0.2], rrr_ik, rrr_fk, 0.1, 0.5, 5.0, 0.005, VJ,
                     [-4, -4, -4], [4, 4, 4], NAMES, KINDS, q_start=[0.46, 0.9, 0.4])


def test_line_past_a_joint_limit_before_reach_reports_the_limit() -> None:
    # the same line with the real limits: the elbow hits -1.2 rad before the reach runs out
    with pytest.raises(LimitViolation, match=r"elbow -1\.2\d* rad is below its limit -1\.2"):
        line([0.2, 0.1, 0.2], [0.5, 0.1, 0.2])


def test_line_slows_down_for_joint_velocity_then_refuses() -> None:
    slow = np.array([0.3, 0.3, 0.3])
    fast, _ = line([0.2, 0.1, 0.2], [0.2, -0.1, 0.2])
    traj, _ = line([0.2, 0.1, 0.2], [0.2, -0.1, 0.2], vj=slow)
    assert traj.duration > fast.duration and np.all(np.abs(traj.qd) <= slow)
    msg = r"base would need .* rad/s, above its limit 0\.3 rad/s"
    with pytest.raises(LimitViolation, match=msg):
        line([0.2, 0.1, 0.2], [0.2, -0.1, 0.2], vj=slow, retries=0)


def test_line_beside_the_base_axis_is_a_discontinuity() -> None:
    # 1 mm beside the axis q0 = atan2(y, x) turns by ~pi within a few mm: d q0/ds = 1/y
    # = 1000 rad/m, i.e. 100 rad/s at 0.1 m/s; slowing down cannot fix a step like that
    with pytest.raises(Unreachable, match="base jumps by .* singularity"):
        tr.plan_line([0.05, 0.001, 0.35], [-0.05, 0.001, 0.35], rrr_ik, rrr_fk, 0.1, 0.5, 5.0,
                     0.005, VJ, [-4, -4, -4], [4, 4, 4], NAMES, KINDS, q_start=[0.0, 1.2, 1.0])


def test_line_through_the_base_axis_keeps_q0_and_leans_over() -> None:
    # exactly through the axis the continuous branch keeps q0 = 0 and swings the arm over
    traj, tip = tr.plan_line([0.05, 0.0, 0.35], [-0.05, 0.0, 0.35], rrr_ik, rrr_fk, 0.1, 0.5,
                             5.0, 0.005, VJ, [-4, -4, -4], [4, 4, 4], NAMES, KINDS,
                             q_start=[0.0, 1.2, 1.0])
    np.testing.assert_allclose(traj.q[:, 0], 0.0, atol=1e-12)
    np.testing.assert_allclose(tip[-1], [-0.05, 0.0, 0.35], atol=1e-9)


def test_angler_line_carriages_only() -> None:
    g = pprp.PPRP()
    lo, hi = np.array([-0.075, -0.075, -1.5708, 0.0]), np.array([0.075, 0.075, 1.5708, 0.14])
    names, kinds = ["x", "y", "theta3", "z"], ["prismatic", "prismatic", "revolute", "prismatic"]

    def ik(p: np.ndarray, q_prev: np.ndarray | None) -> np.ndarray:
        return pprp.ik_near(p, np.zeros(4) if q_prev is None else q_prev, g, "dx_used")

    def fk(q: np.ndarray) -> np.ndarray:
        return pprp.fk(q, g)

    vj = np.array([0.05, 0.05, 2.0, 0.05])
    traj, tip = tr.plan_line([0.0, 0.1, 0.0], [0.05, 0.12, 0.05], ik, fk, 0.04, 0.2, 2.0, 0.01,
                             vj, lo, hi, names, kinds, q_start=[0, 0, 0, 0.05])
    np.testing.assert_allclose(traj.q[:, 2], 0.0)  # theta3 held; the carriages do the work
    np.testing.assert_allclose(traj.q[-1], [0.05, 0.02, 0.0, 0.1], atol=1e-12)
    with pytest.raises(LimitViolation, match=r"x 0\.07\d+ m is above its limit 0\.07\d+ m by"):
        tr.plan_line([0.0, 0.1, 0.0], [0.1, 0.1, 0.0], ik, fk, 0.04, 0.2, 2.0, 0.01, vj, lo, hi,
                     names, kinds, q_start=[0, 0, 0, 0.05])


def test_plan_stop_brakes_to_rest_within_limits() -> None:
    from kinematics.trajectory import plan_stop

    q0, v0, a0 = np.array([0.1, -0.2, 0.3]), np.array([1.0, -0.5, 0.0]), np.array([0.0, 2.0, 0.0])
    amax, jmax, vmax = np.array([6.0] * 3), np.array([60.0] * 3), np.array([1.5] * 3)
    tr = plan_stop(q0, v0, a0, amax, jmax, vmax)
    t = np.linspace(0, tr.duration, 400)
    q, qd, qdd = tr.sample(t)
    np.testing.assert_allclose(q[0], q0, atol=1e-12)
    np.testing.assert_allclose(qd[0], v0, atol=1e-12)
    np.testing.assert_allclose(qd[-1], 0.0, atol=1e-9)
    np.testing.assert_allclose(qdd[-1], 0.0, atol=1e-9)
    assert np.all(np.abs(qdd) <= amax + 1e-6)
    # braking from 1 rad/s at 6 rad/s^2 takes at least 1/6 s and moves forward
    assert tr.duration >= 1.0 / 6.0 and q[-1][0] > q0[0]


# ---------------------------------------------------------------- every ruckig result typed


@pytest.mark.parametrize("speed", [1e-12, 1e-9, 1e-6, 3e-5])
def test_a_tiny_speed_is_a_typed_error_with_a_reason(speed: float) -> None:
    """ruckig answers -101 (the move would last over 7.6e3 s), which its Python enum does not
    list: that was `ValueError: -101 is not a valid Result`, a 502 at the API."""
    with pytest.raises(tr.TrajectoryError) as info:
        tr.plan_joint([0.0, 0.0, 0.0], [1.0, 0.5, 0.2], VJ, 5.0, 50.0, speed=speed)
    assert info.value.ruckig_code == -101
    assert "longer than" in str(info.value) and "speed" in str(info.value)
    assert isinstance(info.value, KinematicsError)


def test_every_ruckig_error_number_has_a_reason() -> None:
    for code in (-1, -100, -101, -102, -104, -110, -111):
        assert "ruckig returned" not in tr.ruckig_reason(code)
    assert tr.ruckig_reason(-999) == "ruckig returned error -999"


def test_a_line_too_slow_to_sample_is_refused_before_any_ik() -> None:
    """1e-9 of the tip speed: ruckig plans a 4.7e8 s arc (no -101 for one DOF); sampling it
    every 10 ms wanted 351 GiB."""
    calls = []

    def ik(p: np.ndarray, q: np.ndarray | None) -> np.ndarray:
        calls.append(p)
        return np.asarray(rrr_ik(p, q))

    with pytest.raises(tr.TrajectoryError, match="at most 60000"):
        tr.plan_line([0.2, 0.1, 0.2], [0.25, 0.1, 0.2], ik, rrr_fk, 0.1, 0.5, 5.0, 0.01, VJ,
                     LO, HI, NAMES, KINDS, speed=1e-9)
    assert calls == []
