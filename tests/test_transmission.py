"""Transmission: known tick counts from the design, round trips, velocity units."""

from __future__ import annotations

import tomllib
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from kinematics.transmission import RPM_PER_UNIT, Transmission

PROFILES = Path(__file__).resolve().parents[1] / "app" / "arms" / "angler"


def angler() -> Transmission:
    joints = tomllib.loads((PROFILES / "angler.toml").read_text())["joints"]
    return Transmission.from_joint_tables(joints)


def test_known_ticks() -> None:
    t = Transmission.from_joints([4096] * 3, [0] * 3, [1] * 3, [None, 0.008, 0.1257])
    # pi rad = half a revolution = 2048; 8 mm = one screw turn = 4096; 0.1257 m = one winch turn
    np.testing.assert_allclose(t.to_ticks([np.pi, 0.008, 0.1257]), [2048, 4096, 4096], atol=1e-9)
    np.testing.assert_allclose(t.from_ticks([2048, 4096, 4096]), [np.pi, 0.008, 0.1257])
    np.testing.assert_allclose(t.to_ticks([-np.pi / 2, 0.002, 0.0]), [-1024, 1024, 0], atol=1e-9)


def test_profile_offsets_and_kinds() -> None:
    t = angler()
    np.testing.assert_allclose(t.per_rev, [0.008, 0.008, 2 * np.pi, 0.1257])
    # theta3 0 at tick 0, 45 deg at 512 (the design's MATLAB, issue 24); x 1 mm = 512 ticks,
    # negated (the design's MATLAB wiring)
    np.testing.assert_allclose(t.to_ticks([0.001, 0.0, 0.0, 0.0]), [-512, 0, 0, 0], atol=1e-9)
    np.testing.assert_array_equal(t.to_ticks_int([0.001, 0.0, np.pi / 4, 0.0]), [-512, 0, 512, 0])
    np.testing.assert_array_equal(t.to_ticks_int([0.0, 0.0, -np.pi / 2, 0.0]), [0, 0, -1024, 0])


def test_sign_reverses_about_the_offset() -> None:
    t = Transmission.from_joints([4096, 4096], [100, 100], [1, -1])
    np.testing.assert_allclose(t.to_ticks([np.pi, np.pi]), [2148, -1948])
    np.testing.assert_allclose(t.velocity_to_ticks([np.pi, np.pi]), [2048, -2048])


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 2**32 - 1))
def test_round_trips(seed: int) -> None:
    rng = np.random.default_rng(seed)
    n = 4
    t = Transmission.from_joints(
        rng.integers(1, 1 << 16, n), rng.normal(0, 1000, n), rng.choice([-1, 1], n),
        [None if k else float(rng.uniform(0.001, 0.2)) for k in rng.integers(0, 2, n)],
    )
    q = rng.normal(size=(5000, n))
    np.testing.assert_allclose(t.from_ticks(t.to_ticks(q)), q, atol=1e-9)
    np.testing.assert_allclose(t.velocity_from_ticks(t.velocity_to_ticks(q)), q, atol=1e-12)
    np.testing.assert_allclose(t.velocity_from_rpm_units(t.velocity_to_rpm_units(q)), q, atol=1e-12)
    # a velocity in ticks/s is the tick change over one second at that rate
    # (atol: the difference of two tick counts near the offset, up to ~4,000, keeps about
    # 1e-12 ticks of absolute precision, not 1e-9 of relative for a tiny q)
    np.testing.assert_allclose(t.velocity_to_ticks(q), t.to_ticks(q) - t.to_ticks(0 * q),
                               rtol=1e-9, atol=1e-9)


def test_dynamixel_velocity_units() -> None:
    t = angler()
    # one unit = 0.229 rpm: revolute 0.229 * 2 pi / 60 rad/s; screw 0.229 * 0.008 / 60 m/s
    one = t.velocity_from_rpm_units([1, 1, 1, 1])
    per_rev = np.array([-0.008, -0.008, 2 * np.pi, 0.1257])  # x, y negated (wiring)
    np.testing.assert_allclose(one, per_rev * RPM_PER_UNIT / 60)
    # 0.05 m/s on the x screw = 6.25 rev/s = 375 rpm = 1637.55 units, negated (wiring)
    assert t.velocity_to_rpm_units([0.05, 0, 0, 0])[0] == pytest.approx(-375 / 0.229)


@pytest.mark.parametrize("lead", [(), (7,), (2, 3)])
def test_shapes_broadcast(lead: tuple[int, ...]) -> None:
    t = angler()
    q = np.zeros(lead + (4,))
    for f in (t.to_ticks, t.from_ticks, t.velocity_to_ticks, t.velocity_from_ticks,
              t.velocity_to_rpm_units, t.velocity_from_rpm_units):
        assert f(q).shape == lead + (4,)


def test_rejects_bad_parameters() -> None:
    with pytest.raises(ValueError, match="sign"):
        Transmission.from_joints([4096], [0], [0])
    with pytest.raises(ValueError, match="ticks_per_rev"):
        Transmission.from_joints([0], [0], [1])
    with pytest.raises(ValueError, match="lead_m"):
        Transmission.from_joints([4096], [0], [1], [-0.008])
    with pytest.raises(ValueError, match="2 joint values"):
        Transmission.from_joints([4096, 4096], [0], [1, 1])
