"""RBE3001 RRR kinematics: seeds on paper, round trips, derivatives, refusals."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from kinematics import rrr
from kinematics.errors import KinematicsError, Singular, Unreachable

G = rrr.RRR()
L1, L2, L3 = G.l1, G.l2, G.l3
LO = np.array([-1.5708, -0.35, -1.2])  # app/arms/rbe3001/rbe3001.toml
HI = np.array([1.5708, 1.75, 2.4])
N = 5000
seeds = st.integers(0, 2**32 - 1)


def test_defaults_are_the_design_inches() -> None:
    assert (G.l1, G.l2, G.l3) == pytest.approx((8 * 0.0254, 6.5 * 0.0254, 8.125 * 0.0254))


@pytest.mark.parametrize(
    ("q", "p"),
    [
        # q = 0: rho = L2 cos0 + L3 sin0 = L2; z = L1 + 0 - L3 cos0 = 0.2032 - 0.206375
        ((0.0, 0.0, 0.0), (0.1651, 0.0, -0.003175)),
        # (0, pi/2, pi/2): rho = L2*0 + L3 sin0 = 0; z = L1 + L2 - L3 = 0.161925
        ((0.0, np.pi / 2, np.pi / 2), (0.0, 0.0, 0.161925)),
        # (pi/2, 0, -pi/2): rho = L2 + L3 sin(pi/2) = 0.371475 along +y; z = L1
        ((np.pi / 2, 0.0, -np.pi / 2), (0.0, 0.371475, 0.2032)),
        # (pi, 0, 0): rho = L2, pointing along -x; z as for q = 0
        ((np.pi, 0.0, 0.0), (-0.1651, 0.0, -0.003175)),
    ],
)
def test_fk_seed_values(q: tuple[float, float, float], p: tuple[float, float, float]) -> None:
    assert rrr.fk(q, G) == pytest.approx(p, abs=1e-12)


def test_jacobian_seed_at_zero() -> None:
    # q = 0: rho = L2, drho/dq1 = L3 cos0 = L3, drho/dq2 = -L3, dz/dq1 = rho, dz/dq2 = -L3 sin0
    expected = [[0.0, L3, -L3], [L2, 0.0, 0.0], [0.0, L2, 0.0]]
    np.testing.assert_allclose(rrr.jacobian([0.0, 0.0, 0.0], G), expected, atol=1e-15)


def _joints(seed: int, n: int = N) -> np.ndarray:
    return np.random.default_rng(seed).uniform(LO, HI, size=(n, 3))


@settings(max_examples=20, deadline=None)
@given(seeds)
def test_fk_of_every_ik_solution_is_the_target(seed: int) -> None:
    q = _joints(seed)
    p = rrr.fk(q, G)
    sols = rrr.ik(p, G)
    assert sols.q.shape == (N, 4, 3) and sols.valid.shape == (N, 4)
    assert sols.valid.all()  # the arm reaches its own FK points on every branch
    back = rrr.fk(sols.q, G)
    assert np.max(np.abs(back - p[:, None, :])) < 1e-9
    assert np.all((sols.q > -np.pi) & (sols.q <= np.pi))
    dist = np.linalg.norm(rrr.wrap(sols.q - q[:, None, :]), axis=-1).min(axis=-1)
    assert np.quantile(dist, 0.999) < 1e-6  # the original joints are among the branches


@settings(max_examples=10, deadline=None)
@given(seeds)
def test_jacobian_matches_central_differences(seed: int) -> None:
    q = np.random.default_rng(seed).uniform(-np.pi, np.pi, size=(N, 3))
    h = 1e-6
    fd = np.stack(
        [(rrr.fk(q + h * e, G) - rrr.fk(q - h * e, G)) / (2 * h) for e in np.eye(3)], axis=-1
    )
    np.testing.assert_allclose(rrr.jacobian(q, G), fd, atol=1e-8)


@pytest.mark.parametrize("lead", [(), (5,), (2, 3)])
def test_shapes_broadcast(lead: tuple[int, ...]) -> None:
    q = np.random.default_rng(1).uniform(LO, HI, size=lead + (3,))
    p = rrr.fk(q, G)
    assert p.shape == lead + (3,)
    assert rrr.jacobian(q, G).shape == lead + (3, 3)
    sols = rrr.ik(p, G)
    assert sols.q.shape == lead + (4, 3) and sols.valid.shape == lead + (4,)
    assert rrr.ik_near(p, q, G).shape == lead + (3,)
    qd, cond = rrr.inverse_velocity(q, np.ones(3), G)
    assert qd.shape == lead + (3,) and cond.shape == lead
    assert rrr.tip_force(q, np.ones(lead + (3,)), G).shape == lead + (3,)


def test_ik_limits_mark_out_of_limit_branches_invalid() -> None:
    q = _joints(3, 2000)
    sols = rrr.ik(rrr.fk(q, G), G, LO, HI)
    assert sols.valid.any(axis=-1).all()
    inside = sols.q[sols.valid]
    assert np.all((inside >= LO - 1e-9) & (inside <= HI + 1e-9))
    assert np.isnan(sols.q[~sols.valid]).all()


def test_ik_near_follows_the_previous_branch() -> None:
    q = _joints(4, 1000)
    near = rrr.ik_near(rrr.fk(q, G), q + 1e-3, G)
    np.testing.assert_allclose(near, q, atol=1e-6)


def test_unreachable_far_point_says_out_of_reach() -> None:
    msg = r"out of reach: 0\.520 m from the shoulder, reach is 0\.371"
    with pytest.raises(Unreachable, match=msg):
        rrr.ik_one([0.52, 0.0, L1], G)
    assert not rrr.ik([0.52, 0.0, L1], G).valid.any()


def test_unreachable_inner_hole() -> None:
    # |L2 - L3| = 0.041275 m: a point 0.02 m from the shoulder cannot be reached
    with pytest.raises(Unreachable, match=r"inside the inner hole: 0\.020 m .* 0\.041 m"):
        rrr.ik_one([0.0, 0.02, L1], G)


def test_unreachable_is_a_value_error() -> None:
    assert issubclass(Unreachable, KinematicsError) and issubclass(KinematicsError, ValueError)


def test_every_solution_outside_limits() -> None:
    # straight behind the base: only q0 = pi (or the flip, which bends shoulder past its limit)
    with pytest.raises(Unreachable, match="outside the joint limits"):
        rrr.ik_one([-0.3, 0.0, 0.1], G, LO, HI)


def test_base_axis_picks_q0_zero() -> None:
    sols = rrr.ik_one([0.0, 0.0, 0.161925], G)
    assert sols[0][0] == 0.0
    assert any(np.allclose(s, [0.0, np.pi / 2, np.pi / 2], atol=1e-7) for s in sols)
    for s in sols:
        np.testing.assert_allclose(rrr.fk(s, G), [0.0, 0.0, 0.161925], atol=1e-12)


@settings(max_examples=10, deadline=None)
@given(seeds)
def test_inverse_velocity_inverts_j_qdot(seed: int) -> None:
    rng = np.random.default_rng(seed)
    q, qdot = _joints(seed), rng.normal(size=(N, 3))
    xdot = np.einsum("...ij,...j->...i", rrr.jacobian(q, G), qdot)
    got, cond = rrr.inverse_velocity(q, xdot, G, max_cond=1e3)
    ok = cond <= 1e3
    assert ok.mean() > 0.9
    np.testing.assert_allclose(got[ok], qdot[ok], atol=1e-7 * 1e3)
    assert np.isnan(got[~ok]).all()


def test_singular_configurations() -> None:
    stretched = [0.3, 0.2, -np.pi / 2]  # q2 = -pi/2: L3 continues along L2
    on_axis = [0.0, np.pi / 2, np.pi / 2]  # tip on the base axis: q0 does nothing
    qd, cond = rrr.inverse_velocity([stretched, on_axis], [0.01, 0.0, 0.0], G)
    assert np.isnan(qd).all() and np.all(cond > 1e4)
    with pytest.raises(Singular, match="condition number") as info:
        rrr.inverse_velocity_one(on_axis, [0.01, 0.0, 0.0], G)
    assert info.value.cond > 1e4
    assert np.isnan(rrr.tip_force(stretched, [1.0, 1.0, 1.0], G)).all()
    with pytest.raises(Singular, match="condition number"):
        rrr.tip_force_one(stretched, [1.0, 1.0, 1.0], G)


def test_inverse_velocity_one_matches_batch() -> None:
    q, xd = np.array([0.2, 0.6, 0.4]), np.array([0.01, -0.02, 0.03])
    batch, _ = rrr.inverse_velocity(q, xd, G)
    np.testing.assert_allclose(rrr.inverse_velocity_one(q, xd, G), batch)


@settings(max_examples=10, deadline=None)
@given(seeds)
def test_tip_force_balances_torques(seed: int) -> None:
    q, tau = _joints(seed), np.random.default_rng(seed + 1).normal(size=(N, 3))
    f = rrr.tip_force(q, tau, G, max_cond=1e3)
    ok = np.isfinite(f).all(axis=-1)
    assert ok.mean() > 0.9
    jt_f = np.einsum("...ji,...j->...i", rrr.jacobian(q, G), f)  # J^T F
    np.testing.assert_allclose(jt_f[ok], tau[ok], atol=1e-9)


def test_tip_force_seed() -> None:
    # q = 0: J^T = [[0, L2, 0], [L3, 0, L2], [-L3, 0, 0]]; a pure downward tip force -1 N
    # loads the shoulder only: tau = J^T (0, 0, -1) = (0, -L2, 0)
    np.testing.assert_allclose(rrr.tip_force_one([0, 0, 0], [0.0, -L2, 0.0], G), [0, 0, -1],
                               atol=1e-12)


def test_workspace_and_bounds() -> None:
    rng = np.random.default_rng(7)
    pts = rrr.workspace(G, LO, HI, 20_000, rng)
    assert pts.shape == (20_000, 3)
    d = np.linalg.norm(pts - [0.0, 0.0, L1], axis=-1)
    assert np.all((d <= L2 + L3 + 1e-12) & (d >= abs(L2 - L3) - 1e-12))
    lo, hi = rrr.bounds(G, LO, HI, rng=rng)
    assert np.all(pts >= lo - 5e-3) and np.all(pts <= hi + 5e-3)
    # highest tip: dz/dq1 > 0 up to the shoulder limit 1.75 and -cos(q1 - q2) grows with
    # q1 - q2 up to pi, so the elbow sits at its lower limit -1.2: z = L1 + L2 sin 1.75
    # - L3 cos 2.95 = 0.2032 + 0.16246 + 0.20245 = 0.5681 m
    assert hi[2] == pytest.approx(L1 + L2 * np.sin(1.75) - L3 * np.cos(2.95), abs=1e-9)



def test_a_sampled_workspace_draws_within_the_limits_and_adds_their_corners() -> None:
    from kinematics.limits import corners, draw

    lo, hi = [-1.0, 0.0, 2.0, -0.5], [1.0, 0.1, 3.0, 0.5]
    q = draw(lo, hi, 5000, np.random.default_rng(2))
    assert q.shape == (5000, 4)
    assert np.all((q >= lo) & (q <= hi))
    assert np.allclose(q.min(axis=0), lo, atol=0.01) and np.allclose(q.max(axis=0), hi, atol=0.01)
    c = corners(lo, hi)
    assert c.shape == (16, 4)
    assert {tuple(row) for row in c} == {(a, b, d, e) for a in (-1.0, 1.0) for b in (0.0, 0.1)
                                         for d in (2.0, 3.0) for e in (-0.5, 0.5)}
    # the box of rrr's workspace is that of its draws and corners through FK
    pts = rrr.fk(np.concatenate([draw(LO, HI, 100, np.random.default_rng(3)), corners(LO, HI)]), G)
    lo3, hi3 = rrr.bounds(G, LO, HI, 100, np.random.default_rng(3))
    assert np.array_equal(lo3, pts.min(axis=0)) and np.array_equal(hi3, pts.max(axis=0))

def test_limit_messages_survive_infinite_values() -> None:
    from kinematics.limits import violations

    msgs = violations([np.inf, 0.0, -np.inf], ["base", "shoulder", "elbow"],
                      [-1.0, -1.0, -1.0], [1.0, 1.0, 1.0])
    assert msgs[0].startswith("base inf rad is above its limit")
    assert msgs[1].startswith("elbow -inf rad is below its limit")
