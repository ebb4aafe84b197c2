"""Angler PPRP kinematics: DH product vs closed form, IK cases, velocities, bounds."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from kinematics import pprp
from kinematics.errors import Unreachable

G = pprp.PPRP()
R, H = G.r, G.h
LO = np.array([-0.075, -0.075, -1.5708, 0.0])  # app/arms/angler/angler.toml
HI = np.array([0.075, 0.075, 1.5708, 0.14])
N = 5000
seeds = st.integers(0, 2**32 - 1)


def closed_form(q: np.ndarray) -> np.ndarray:
    dx, dy, t3, dz = np.moveaxis(q, -1, 0)
    return np.stack([dx - R * np.sin(t3), dy + R * np.cos(t3), dz - H], axis=-1)


def _joints(seed: int, n: int = N) -> np.ndarray:
    return np.random.default_rng(seed).uniform(LO, HI, size=(n, 4))


@settings(max_examples=10, deadline=None)
@given(seeds)
def test_dh_product_equals_closed_form(seed: int) -> None:
    q = np.random.default_rng(seed).uniform(-3, 3, size=(N, 4))
    np.testing.assert_allclose(pprp.fk(q, G), closed_form(q), atol=1e-12)
    rot = pprp.fk_pose(q, G)[..., :3, :3]
    eye = np.broadcast_to(np.eye(3), rot.shape)
    np.testing.assert_allclose(rot @ np.swapaxes(rot, -1, -2), eye, atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(rot), 1.0, atol=1e-12)


@pytest.mark.parametrize(
    ("q", "p"),
    [
        ((0, 0, 0, 0), (0.0, 0.1, -0.05)),  # arm along +y, magnet h below the carriage
        ((0, 0, np.pi / 2, 0), (-0.1, 0.0, -0.05)),  # t3 = 90 deg turns the arm to -x
        ((0.05, -0.02, -np.pi / 2, 0.1), (0.15, -0.02, 0.05)),  # 0.05 + r, -0.02, 0.1 - h
    ],
)
def test_fk_seed_values(q: tuple[float, ...], p: tuple[float, ...]) -> None:
    assert pprp.fk(q, G) == pytest.approx(p, abs=1e-15)


def test_dh_transform_single_rows() -> None:
    # Rz(pi/2) then a = 1 along the new x: origin at (0, 1, 0); d = 2 along z
    t = pprp.dh_transform(np.pi / 2, 2.0, 1.0, 0.0)
    np.testing.assert_allclose(t[:3, 3], [0.0, 1.0, 2.0], atol=1e-15)


@settings(max_examples=10, deadline=None)
@given(seeds)
def test_jacobian_matches_central_differences(seed: int) -> None:
    q = np.random.default_rng(seed).uniform(-3, 3, size=(N, 4))
    h = 1e-6
    fd = np.stack(
        [(pprp.fk(q + h * e, G) - pprp.fk(q - h * e, G)) / (2 * h) for e in np.eye(4)], axis=-1
    )
    np.testing.assert_allclose(pprp.jacobian(q, G), fd, atol=1e-8)


@settings(max_examples=20, deadline=None)
@given(seeds)
def test_ik_dx_zero_round_trip(seed: int) -> None:
    q = _joints(seed)
    q[:, 0] = 0.0
    p = pprp.fk(q, G)
    sols = pprp.ik(p, G, "dx_zero")
    assert sols.q.shape == (N, 2, 4) and sols.valid.all()
    np.testing.assert_allclose(pprp.fk(sols.q, G), np.broadcast_to(p[:, None], (N, 2, 3)),
                               atol=1e-9)
    assert np.all(sols.q[..., 0] == 0.0)
    dist = np.abs(sols.q - q[:, None]).max(axis=-1).min(axis=-1)
    assert dist.max() < 1e-9  # t3 in [-pi/2, pi/2] is the asin branch


@settings(max_examples=20, deadline=None)
@given(seeds)
def test_ik_dx_used_recovers_joints_and_any_point(seed: int) -> None:
    q = _joints(seed)
    p = pprp.fk(q, G)
    sols = pprp.ik(p, G, "dx_used", theta3=q[:, 2])
    assert sols.q.shape == (N, 1, 4) and sols.valid.all()
    np.testing.assert_allclose(sols.q[:, 0], q, atol=1e-12)
    # dx_zero reaches only |x| <= r; every valid solution still maps back
    z = pprp.ik(p, G, "dx_zero")
    assert np.array_equal(z.valid[:, 0], np.abs(p[:, 0]) <= R + 1e-12 * R)
    back = pprp.fk(z.q[z.valid], G)
    np.testing.assert_allclose(back, np.repeat(p[:, None], 2, axis=1)[z.valid], atol=1e-9)


@pytest.mark.parametrize("lead", [(), (5,), (2, 3)])
def test_shapes_broadcast(lead: tuple[int, ...]) -> None:
    q = np.random.default_rng(2).uniform(LO, HI, size=lead + (4,))
    p = pprp.fk(q, G)
    assert p.shape == lead + (3,) and pprp.fk_pose(q, G).shape == lead + (4, 4)
    assert pprp.jacobian(q, G).shape == lead + (3, 4)
    assert pprp.ik(p, G).q.shape == lead + (2, 4)
    assert pprp.ik(p, G, "dx_used", 0.3).q.shape == lead + (1, 4)
    assert pprp.ik_near(p, q, G).shape == lead + (4,)
    qd, cond = pprp.inverse_velocity(q, np.ones(3), G)
    assert qd.shape == lead + (4,) and cond.shape == lead


def test_ik_one_reasons() -> None:
    with pytest.raises(Unreachable, match=r"\|x\| = 0\.150 m exceeds the arm radius r = 0\.100 m"):
        pprp.ik_one([0.15, 0.0, 0.0], G)
    assert len(pprp.ik_one([0.15, 0.0, 0.0], G, "dx_used", 0.0)) == 1
    with pytest.raises(Unreachable, match="outside the joint limits"):
        pprp.ik_one([0.0, 0.3, 0.0], G, "dx_used", 0.0, LO, HI)  # dy = 0.2 > 0.075
    # x = -r: t3 = pi/2 exactly, both twins coincide and are reported once
    assert len(pprp.ik_one([-R, 0.0, 0.0], G)) == 1


def test_ik_seed() -> None:
    # x = 0.05 = -r sin t3 -> t3 = -pi/6; dy = y - r cos t3 = 0.02 - 0.0866; dz = z + h
    (a, b) = pprp.ik_one([0.05, 0.02, 0.03], G)
    np.testing.assert_allclose(a, [0.0, 0.02 - 0.1 * np.cos(np.pi / 6), -np.pi / 6, 0.08])
    np.testing.assert_allclose(b, [0.0, 0.02 + 0.1 * np.cos(np.pi / 6), -5 * np.pi / 6, 0.08])


@settings(max_examples=10, deadline=None)
@given(seeds)
def test_inverse_velocity_min_norm_and_fixed_t3(seed: int) -> None:
    rng = np.random.default_rng(seed)
    q, v = _joints(seed), rng.normal(size=(N, 3))
    j = pprp.jacobian(q, G)
    qd, cond = pprp.inverse_velocity(q, v, G)
    np.testing.assert_allclose(np.einsum("...ij,...j->...i", j, qd), v, atol=1e-12)
    np.testing.assert_allclose(qd, np.einsum("...ij,...j->...i", np.linalg.pinv(j), v), atol=1e-12)
    assert np.all(np.isfinite(cond))
    w = rng.normal(size=N)
    qd2, _ = pprp.inverse_velocity(q, v, G, t3_rate=w)
    np.testing.assert_allclose(np.einsum("...ij,...j->...i", j, qd2), v, atol=1e-12)
    np.testing.assert_array_equal(qd2[:, 2], w)
    assert np.all(np.linalg.norm(qd, axis=-1) <= np.linalg.norm(qd2, axis=-1) + 1e-12)


def test_bounds_are_exact_and_contain_the_workspace() -> None:
    lo, hi = pprp.bounds(G, LO, HI)
    # t3 in [-pi/2, pi/2]: -r sin t3 spans [-r, r]; r cos t3 spans [0, r]
    np.testing.assert_allclose(lo, [-0.175, -0.075, -0.05], atol=1e-4)
    np.testing.assert_allclose(hi, [0.175, 0.175, 0.09], atol=1e-12)
    pts = pprp.workspace(G, LO, HI, 20_000, np.random.default_rng(3))
    assert np.all(pts >= lo - 1e-12) and np.all(pts <= hi + 1e-12)


# ------------------------------------------------ the design document's IK cases


def test_design_case_two_turns_the_arm_to_minus_or_plus_90_degrees() -> None:
    # px > 0: dx = px - r, theta3 = asin((dx - px) / r) = -90 deg; px < 0: dx = px + r, +90 deg
    [q] = pprp.ik_one([0.12, 0.04, -0.02], G, "dx_used")
    np.testing.assert_allclose(q, [0.12 - R, 0.04, -np.pi / 2, -0.02 + H], atol=1e-12)
    [q] = pprp.ik_one([-0.13, 0.01, 0.0], G, "dx_used")
    np.testing.assert_allclose(q, [-0.13 + R, 0.01, np.pi / 2, H], atol=1e-12)
    # a theta3 given still wins (the IK route's `theta3`)
    [q] = pprp.ik_one([0.12, 0.04, -0.02], G, "dx_used", 0.3)
    assert q[2] == pytest.approx(0.3)


def test_the_documented_point_is_reachable_within_the_profile_limits() -> None:
    p = np.array([0.12, 0.04, -0.02])
    assert pprp.auto_case(p, G) == "dx_used"  # |px| > r
    sols = pprp.ik_one(p, G, None, None, LO, HI)
    assert len(sols) == 1
    np.testing.assert_allclose(pprp.fk(sols[0], G), p, atol=1e-12)


def test_automatic_case_lists_both_cases_design_choice_first() -> None:
    p = np.array([0.03, 0.05, 0.01])
    assert pprp.auto_case(p, G) == "dx_zero"  # |px| < r: dx = 0
    sols = pprp.ik_one(p, G, None)
    assert len(sols) == 3  # the two dx = 0 twins, then case two
    assert sols[0][0] == 0.0 and sols[1][0] == 0.0
    assert sols[2][2] == pytest.approx(-np.pi / 2)
    for q in sols:
        np.testing.assert_allclose(pprp.fk(q, G), p, atol=1e-12)


@settings(max_examples=10, deadline=None)
@given(seeds)
def test_fk_of_ik_is_the_point_in_every_case(seed: int) -> None:
    p = pprp.workspace(G, LO, HI, 200, np.random.default_rng(seed))
    for case in ("dx_zero", "dx_used"):
        sols = pprp.ik(p, G, case)  # type: ignore[arg-type]
        for k in range(sols.q.shape[-2]):
            ok = sols.valid[:, k]
            np.testing.assert_allclose(pprp.fk(sols.q[ok, k], G), p[ok], atol=1e-12)
