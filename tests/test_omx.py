"""OpenManipulator-X kinematics: poses worked on paper, round trips on every branch,
the Jacobian against finite differences, the position-only IK rule, refusals."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from kinematics import omx
from kinematics.errors import Singular, Unreachable

G = omx.OMX()
LO, HI = np.array(omx.LOWER), np.array(omx.UPPER)
N = 5000
seeds = st.integers(0, 2**32 - 1)


def test_dimensions_are_the_e_manual_ones() -> None:
    # e-manual "Dimension": 77 mm base to shoulder, 128 + 24 offset, 124, 126 mm
    assert G.h == pytest.approx(0.0765)
    assert (G.a2z, G.a2x, G.l3, G.l4) == (0.128, 0.024, 0.124, 0.126)
    assert G.l2 == pytest.approx(math.hypot(0.024, 0.128))
    # "Reach 380 mm": joint 2 axis to the tip with the arm stretched, plus the 12 mm offset
    assert G.bx + G.l2 + G.l3 + G.l4 == pytest.approx(0.392, abs=0.015)
    assert omx.IDS == (11, 12, 13, 14, 15)


@pytest.mark.parametrize(
    ("q", "pose"),
    [
        # init pose, all zero: inverted L, tip at x 12 + 24 + 124 + 126, z 17 + 59.5 + 128
        ((0.0, 0.0, 0.0, 0.0), (0.286, 0.0, 0.2045, 0.0)),
        # waist a quarter turn: the same reach along +y, the 12 mm offset stays on x
        ((math.pi / 2, 0.0, 0.0, 0.0), (0.012, 0.274, 0.2045, 0.0)),
        # wrist down a quarter turn: tool hangs 126 mm under joint 4, pitch -pi/2
        ((0.0, 0.0, 0.0, math.pi / 2), (0.160, 0.0, 0.2045 - 0.126, -math.pi / 2)),
        # shoulder tipped so link 2 is horizontal (q1 = beta): everything straight forward
        ((0.0, G.beta, -G.beta, 0.0), (0.012 + G.l2 + 0.25, 0.0, 0.0765, 0.0)),
        # the ROBOTIS controller's home pose (0, -1.05, 0.35, 0.70): pitch 0 (sum is 0)
        (omx.HOME, (0.012 + G.l2 * math.cos(G.beta + 1.05) + G.l3 * math.cos(0.70) + G.l4,
                    0.0, 0.0765 + G.l2 * math.sin(G.beta + 1.05) + G.l3 * math.sin(0.70),
                    0.0)),
    ],
)
def test_fk_known_poses(q: tuple[float, ...], pose: tuple[float, ...]) -> None:
    assert omx.fk(q, G) == pytest.approx(pose, abs=1e-12)


def test_home_pose_in_numbers() -> None:
    x, y, z, pitch = omx.fk(omx.HOME, G)
    assert (x, y, z, pitch) == pytest.approx((0.1338, 0.0, 0.2409, 0.0), abs=1e-4)


def test_fk_rejects_wrong_shape() -> None:
    with pytest.raises(ValueError, match=r"\(\.\.\., 4\)"):
        omx.fk([0.0, 0.0, 0.0])


def test_joint_origins_end_at_the_tip_and_keep_link_lengths() -> None:
    q = np.random.default_rng(1).uniform(LO, HI, size=(N, 4))
    pts = omx.joint_origins(q, G)
    assert pts.shape == (N, len(omx.POINTS), 3)
    np.testing.assert_allclose(pts[:, -1], omx.fk(q, G)[:, :3], atol=1e-12)
    seg = np.linalg.norm(np.diff(pts, axis=1), axis=-1)
    np.testing.assert_allclose(seg[:, 2], G.l2, atol=1e-12)
    np.testing.assert_allclose(seg[:, 3], G.l3, atol=1e-12)
    np.testing.assert_allclose(seg[:, 4], G.l4, atol=1e-12)
    np.testing.assert_allclose(pts[:, 2], np.broadcast_to([0.012, 0.0, 0.0765], (N, 3)))


def _round_trip(q: np.ndarray) -> None:
    pose = omx.fk(q, G)
    sols = omx.ik(pose, G)
    assert sols.valid.any(axis=-1).all()
    back = omx.fk(np.where(sols.valid[..., None], sols.q, 0.0), G)
    err = np.abs(back - pose[:, None, :])
    err[..., 3] = np.abs(omx.wrap(back[..., 3] - pose[:, None, 3]))
    assert np.max(np.where(sols.valid[..., None], err, 0.0)) < 1e-9
    # the original configuration is one of the branches
    d = np.abs(omx.wrap(sols.q - q[:, None, :])).max(axis=-1)
    assert np.nanmin(d, axis=-1).max() < 1e-7


def test_round_trip_thousands_within_limits() -> None:
    _round_trip(np.random.default_rng(7).uniform(LO, HI, size=(N, 4)))


def test_round_trip_whole_circle_every_branch() -> None:
    q = np.random.default_rng(8).uniform(-np.pi, np.pi, size=(N, 4))
    _round_trip(q)
    sols = omx.ik(omx.fk(q, G), G)
    # away from the boundary of the annulus all four branches exist and are distinct
    assert sols.valid.all(axis=-1).mean() > 0.5
    for k in range(4):
        assert sols.valid[:, k].sum() > N // 3


def test_branches_are_what_their_names_say() -> None:
    pose = omx.fk([0.3, -0.9, 1.2, 0.9], G)
    sols = omx.ik(pose, G)
    assert sols.valid.all()
    q = sols.q
    assert q[0] == pytest.approx([0.3, -0.9, 1.2, 0.9], abs=1e-12)  # elbow up, facing it
    assert q[0, 0] == pytest.approx(0.3) and q[1, 0] == pytest.approx(0.3)
    assert abs(omx.wrap(q[2, 0] - 0.3 - math.pi)) < 1e-12
    elbow = omx.joint_origins(q, G)[:, 3]
    shoulder, wrist = omx.joint_origins(q, G)[:, 2], omx.joint_origins(q, G)[:, 4]
    # elbow up: the elbow lies above the shoulder-wrist line (unflipped branch)
    t = (elbow[:, 0] - shoulder[:, 0]) / (wrist[:, 0] - shoulder[:, 0])
    line_z = shoulder[:, 2] + t * (wrist[:, 2] - shoulder[:, 2])
    assert elbow[0, 2] > line_z[0] and elbow[1, 2] < line_z[1]


def test_limits_mark_branches_invalid() -> None:
    q = np.array([0.2, -0.5, 0.3, 0.4])
    sols = omx.ik(omx.fk(q, G), G, LO, HI)
    assert sols.valid.sum() >= 1
    assert np.isnan(sols.q[~sols.valid]).all()
    assert np.all(sols.q[sols.valid] >= LO - 1e-9) and np.all(sols.q[sols.valid] <= HI + 1e-9)


def test_ik_one_refuses_with_reasons() -> None:
    with pytest.raises(Unreachable, match="out of reach"):
        omx.ik_one([0.6, 0.0, 0.1, 0.0], G)
    # tool pointing up with the wrist point on the shoulder axis: closer than |L2 - L3|
    with pytest.raises(Unreachable, match="too close"):
        omx.ik_one([0.012, 0.0, G.h + G.l4, math.pi / 2], G)
    with pytest.raises(Unreachable, match="not a finite"):
        omx.ik_one([math.nan, 0.0, 0.1, 0.0], G)
    # reachable, but only leaning back over the base far beyond joint 2's limit
    with pytest.raises(Unreachable, match="joint limits"):
        omx.ik_one(omx.fk([0.0, -2.6, 0.3, 0.0], G), G, LO, HI)


def test_ik_near_tracks_a_branch() -> None:
    q0 = np.array([0.1, -0.3, 0.4, 0.5])
    path = omx.fk(q0 + np.linspace(0, 0.2, 50)[:, None] * np.array([1, 1, -1, 0.5]), G)
    q = q0
    for pose in path:
        q = omx.ik_near(pose, q, G, LO, HI)
        assert omx.fk(q, G) == pytest.approx(pose, abs=1e-9)
    assert q == pytest.approx(q0 + 0.2 * np.array([1, 1, -1, 0.5]), abs=1e-9)


def test_jacobian_against_finite_differences() -> None:
    q = np.random.default_rng(3).uniform(-np.pi, np.pi, size=(500, 4))
    j = omx.jacobian(q, G)
    h = 1e-6
    for k in range(4):
        dq = np.zeros(4)
        dq[k] = h
        num = (omx.fk(q + dq, G) - omx.fk(q - dq, G)) / (2 * h)
        num[:, 3] = omx.wrap(omx.fk(q + dq, G)[:, 3] - omx.fk(q - dq, G)[:, 3]) / (2 * h)
        np.testing.assert_allclose(j[..., k], num, atol=1e-8)


def test_inverse_velocity_and_singular() -> None:
    q = np.array([0.2, -0.6, 0.4, 0.3])
    xdot = np.array([0.01, -0.02, 0.005, 0.1])
    qdot = omx.inverse_velocity(q, xdot, G)
    np.testing.assert_allclose(omx.jacobian(q, G) @ qdot, xdot, atol=1e-12)
    # stretched straight: shoulder, elbow and wrist in one line
    with pytest.raises(Singular) as e:
        omx.inverse_velocity([0.0, G.beta, -G.beta, 0.0], xdot, G)
    assert e.value.cond > 1e4


def test_ik_position_default_rule_and_preference() -> None:
    # a point straight out at shoulder height: the line from the shoulder is horizontal
    pitch, sols = omx.ik_position([0.3, 0.0, G.h], G, LO, HI)
    assert pitch == pytest.approx(0.0, abs=1e-12)
    for q in sols:
        assert omx.fk(q, G)[:3] == pytest.approx([0.3, 0.0, G.h], abs=1e-9)
    # asked for the tool pointing down, a point low in front gets exactly that
    pitch, sols = omx.ik_position([0.2, 0.05, 0.05], G, LO, HI, prefer=-math.pi / 2)
    assert pitch == pytest.approx(-math.pi / 2, abs=1e-12)
    assert all(omx.fk(q, G) == pytest.approx([0.2, 0.05, 0.05, -math.pi / 2], abs=1e-9)
               for q in sols)
    # a preference that cannot be met moves to the nearest pitch that can (within 0.25 deg)
    far = [0.012 + 0.37, 0.0, G.h]
    pitch, sols = omx.ik_position(far, G, LO, HI, prefer=-math.pi / 2)
    assert -math.pi / 2 < pitch < 0.0
    assert not omx.ik(np.array([*far, pitch - math.radians(0.3)]), G, LO, HI).valid.any()
    assert omx.fk(sols[0], G)[:3] == pytest.approx(far, abs=1e-9)
    with pytest.raises(Unreachable, match="no pitch"):
        omx.ik_position([0.5, 0.0, 0.1], G, LO, HI)


@settings(max_examples=200, deadline=None)
@given(st.floats(-np.pi, np.pi), st.floats(-2.05, np.pi / 2), st.floats(-np.pi / 2, 1.53),
       st.floats(-1.8, 2.0))
def test_property_round_trip(q0: float, q1: float, q2: float, q3: float) -> None:
    q = np.array([q0, q1, q2, q3])
    pose = omx.fk(q, G)
    sols = omx.ik_one(pose, G)
    assert sols
    for s in sols:
        back = omx.fk(s, G)
        assert back[:3] == pytest.approx(pose[:3], abs=1e-9)
        assert abs(omx.wrap(back[3] - pose[3])) < 1e-9


@settings(max_examples=100, deadline=None)
@given(seeds)
def test_property_ik_position_reaches_workspace_points(seed: int) -> None:
    pose = omx.workspace(G, LO, HI, 1, np.random.default_rng(seed))[0]
    pitch, sols = omx.ik_position(pose[:3], G, LO, HI)
    assert sols
    for s in sols:
        assert np.all(s >= LO - 1e-9) and np.all(s <= HI + 1e-9)
        assert omx.fk(s, G) == pytest.approx([*pose[:3], pitch], abs=1e-9)


def test_workspace_and_bounds() -> None:
    rng = np.random.default_rng(5)
    pts = omx.workspace(G, LO, HI, 2000, rng)
    assert pts.shape == (2000, 4)
    lo, hi = omx.bounds(G, LO, HI, 5000, np.random.default_rng(6))
    assert np.all(pts[:, :3] >= lo - 0.05) and np.all(pts[:, :3] <= hi + 0.05)
    # reach from the waist axis never exceeds the stretched arm
    rho = np.hypot(pts[:, 0] - G.bx, pts[:, 1])
    assert rho.max() <= G.l2 + G.l3 + G.l4 + 1e-12
    assert hi[2] <= G.h + G.l2 + G.l3 + G.l4
