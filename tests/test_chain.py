"""kinematics.chain: every joint origin, tested against the arms' own fk (the tip), the DH
product of kinematics.pprp (each frame origin) and the link lengths of the RRR arm."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from kinematics import chain, pprp, rrr
from kinematics.pprp import _T0, dh_transform

RRR_G = rrr.RRR()
PPRP_G = pprp.PPRP(r=0.1, h=0.05)

angles = st.floats(-3.0, 3.0, allow_nan=False)
metres = st.floats(-0.2, 0.2, allow_nan=False)


@settings(max_examples=200, deadline=None)
@given(arrays(np.float64, (7, 3), elements=angles))
def test_rrr_points_end_at_fk_and_keep_link_lengths(q: np.ndarray) -> None:
    pts = chain.rrr_points(q, RRR_G)
    assert pts.shape == (7, 4, 3)
    np.testing.assert_allclose(pts[:, -1], rrr.fk(q, RRR_G), atol=1e-12)
    np.testing.assert_allclose(pts[:, 0], 0.0)
    np.testing.assert_allclose(pts[:, 1], [[0.0, 0.0, RRR_G.l1]] * 7)
    np.testing.assert_allclose(np.linalg.norm(pts[:, 2] - pts[:, 1], axis=-1), RRR_G.l2)
    np.testing.assert_allclose(np.linalg.norm(pts[:, 3] - pts[:, 2], axis=-1), RRR_G.l3)


def test_rrr_elbow_at_a_known_pose() -> None:
    # shoulder straight up, base turned 90 degrees: the elbow is l2 above the shoulder
    pts = chain.rrr_points([np.pi / 2, np.pi / 2, 0.0], RRR_G)
    np.testing.assert_allclose(pts[2], [0.0, 0.0, RRR_G.l1 + RRR_G.l2], atol=1e-12)
    # shoulder level: the elbow lies l2 out along the base direction, at shoulder height
    pts = chain.rrr_points([np.pi / 2, 0.0, 0.0], RRR_G)
    np.testing.assert_allclose(pts[2], [0.0, RRR_G.l2, RRR_G.l1], atol=1e-12)


@settings(max_examples=200, deadline=None)
@given(metres, metres, angles, metres)
def test_pprp_points_are_the_dh_frame_origins(dx: float, dy: float, t3: float,
                                               dz: float) -> None:
    q = np.array([dx, dy, t3, dz])
    hp = np.pi / 2
    links = [dh_transform(0.0, dx, 0.0, -hp), dh_transform(-hp, dy, 0.0, hp),
             dh_transform(t3 + hp, 0.0, PPRP_G.r, 0.0),
             dh_transform(0.0, dz - PPRP_G.h, 0.0, 0.0)]
    frame = _T0.copy()
    origins = [frame[:3, 3]]
    for a in links:
        frame = frame @ a
        origins.append(frame[:3, 3])
    pts = chain.pprp_points(q, PPRP_G)
    np.testing.assert_allclose(pts, np.array(origins), atol=1e-12)
    np.testing.assert_allclose(pts[-1], pprp.fk(q, PPRP_G), atol=1e-12)


def test_vectorised_over_leading_axes() -> None:
    rng = np.random.default_rng(1)
    q = rng.uniform(-1, 1, size=(2, 5, 4))
    pts = chain.pprp_points(q, PPRP_G)
    assert pts.shape == (2, 5, 5, 3)
    np.testing.assert_allclose(pts[1, 3], chain.pprp_points(q[1, 3], PPRP_G))
    assert len(chain.PPRP_POINTS) == 5 and len(chain.RRR_POINTS) == 4
