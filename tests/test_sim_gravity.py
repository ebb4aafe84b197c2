"""Gravity on a simulated arm's joints whose servos' torque is off
(app/arms/dynamixel/sim_gravity.py): the simulated bus of an arm made from its profile, run on
its own clock, read as the driver reads it (each servo's Present Position and Velocity).

- An OpenManipulator-X whose servos have held torque folds once it is off: the shoulder comes
  down onto its stop, the elbow and the wrist swing, the waist (about the vertical) stays; the
  arm's weight ends lower; nothing is faster than the cap; it comes to rest.
- It starts resting where it is (torque off since power-up: nothing falls), and nothing falls
  while something holds it.
- The angler's z winch pays out at its cap (0.1 m/s) to its lower limit; x, y and theta3 stay.
- Through the server: a shutdown of the angler's z servo (an overload, torque off by the
  servo itself) lets the load down, and the server's samples show it."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from _wait import held_still

from app.arms import arm_type, model_for
from app.arms.dynamixel import sim_gravity
from app.arms.loading import load_profile
from app.service import ArmService
from protocol import mx28
from tests.conftest import make_settings, running_client

STEP_S = 0.002  # the device's clock between two looks (a poll's period at 500 Hz)


class Arm:
    """A simulated bus of `name`'s profile, its clock run by hand."""

    def __init__(self, name: str) -> None:
        self.profile = load_profile(name)
        self.model = model_for(self.profile)
        self.bus: Any = arm_type(name).simulator(self.profile)
        self.servos = [self.bus.servo(j.motor_id) for j in self.profile.joints]
        self.now = 0.0
        self.bus.advance(self.now)

    def q(self) -> np.ndarray:
        """Where the servos say the joints are (Present Position, through the transmission)."""
        return np.asarray(self.model.transmission.from_ticks(
            [float(s.get("present_position")) for s in self.servos]))

    def qd(self) -> np.ndarray:
        """Present Velocity, rad/s or m/s."""
        ticks = [s.get("present_velocity") * mx28.VEL_TICKS_PER_UNIT for s in self.servos]
        return np.asarray(self.model.transmission.velocity_from_ticks(ticks))

    def torque(self, on: bool) -> None:
        for s in self.servos:
            s.set("torque_enable", int(on))

    def run(self, seconds: float) -> list[tuple[np.ndarray, np.ndarray]]:
        """(positions, velocities) after each step of `seconds` of the device's clock."""
        out = []
        for _ in range(round(seconds / STEP_S)):
            self.now += STEP_S
            self.bus.advance(self.now)
            out.append((self.q(), self.qd()))
        return out

    def height(self, q: np.ndarray) -> float:
        """The summed height of the body points after the base (the model's kinematics)."""
        return float(np.sum(np.asarray(self.model.joint_origins(q))[1:, 2]))


def test_an_openmanipulator_x_folds_once_its_torque_goes_off() -> None:
    arm = Arm("openmanipulator_x")
    start = arm.q()
    arm.torque(True)
    arm.run(0.1)
    np.testing.assert_allclose(arm.q(), start, atol=1e-9)  # holding
    arm.torque(False)
    seen = arm.run(4.0)
    qs = np.array([q for q, _ in seen])
    speeds = np.abs(np.array([v for _, v in seen]))
    rest = qs[-1]
    assert np.all(qs[:, 0] == start[0])  # the waist turns about the vertical: no fall
    np.testing.assert_allclose(rest[1], arm.model.upper[1], atol=1e-3)  # onto its stop
    assert np.all(speeds[:, 1:].max(axis=0) > 0.1), speeds.max(axis=0)  # each one moved
    assert speeds.max() <= sim_gravity.MAX_SPEED["revolute"] * 1.01  # never faster
    assert arm.height(rest) < arm.height(start) - 0.05
    assert np.all(arm.qd() == 0.0) and np.allclose(arm.run(0.2)[-1][0], rest)  # at rest
    # on again: it holds where it fell (the driver writes the goal first; here the motor's)
    for s in arm.servos:
        s.set("goal_position", s.get("present_position"))
    arm.torque(True)
    np.testing.assert_allclose(arm.run(0.2)[-1][0], rest, atol=1e-3)


def test_it_starts_resting_and_nothing_falls_while_it_is_held() -> None:
    arm = Arm("openmanipulator_x")
    start = arm.q()
    assert not any(s.torque for s in arm.servos)  # as at power-up
    arm.run(1.0)
    np.testing.assert_allclose(arm.q(), start, atol=1e-9)  # resting where it came to rest
    arm.torque(True)
    arm.run(0.05)
    arm.bus.gravity.held = True  # the world's hand on it (app/sim/hand.py)
    arm.torque(False)
    arm.run(1.0)
    np.testing.assert_allclose(arm.q(), start, atol=1e-9)
    arm.bus.gravity.held = False  # let go
    arm.run(0.2)
    assert arm.q()[1] > start[1] + 0.1


def test_the_anglers_winch_pays_out_at_its_cap_to_its_lower_limit() -> None:
    arm = Arm("angler")
    start = arm.q()
    z = arm.profile.joint_names.index("z")
    assert start[z] > arm.model.lower[z] + 0.03
    arm.torque(True)
    arm.run(0.02)
    arm.torque(False)
    arm.run(0.2)
    q = arm.q()
    cap = sim_gravity.MAX_SPEED["prismatic"]
    # 0.2 s at the cap (the first step after torque off starts the fall), to a tick
    tick = float(np.max(np.abs(arm.model.transmission.from_ticks([1.0] * 4)
                               - arm.model.transmission.from_ticks([0.0] * 4))))
    assert abs((start[z] - q[z]) - cap * (0.2 - STEP_S)) <= 2 * tick, (start[z], q[z])
    assert arm.qd()[z] == pytest.approx(-cap, rel=0.02)
    others = [k for k in range(4) if k != z]
    np.testing.assert_allclose(q[others], start[others], atol=1e-9)
    arm.run(2.0)
    assert arm.q()[z] == pytest.approx(arm.model.lower[z], abs=tick)
    assert arm.qd()[z] == 0.0


async def test_a_shutdown_of_the_anglers_winch_lets_its_load_down() -> None:
    """An overload shuts the z servo down (Shutdown's default bits: torque off by the servo);
    the server reads the load going down to the winch's lower limit, as from hardware."""
    async with running_client(make_settings()) as (app, _c):  # (the angler among the sims)
        angler: ArmService = app.state.services["angler"]
        here = np.asarray(await held_still(lambda: angler.positions, 1e-4))
        z = angler.profile.joint_names.index("z")
        assert here[z] > angler.model.lower[z] + 0.03
        bus = angler.driver.link.device
        servo = bus.servo(angler.profile.joints[z].motor_id)
        bus.inject_hardware_error(servo.id, "overload")
        assert not servo.torque
        rest = np.asarray(await held_still(lambda: angler.positions, 1e-4))
        assert rest[z] == pytest.approx(angler.model.lower[z], abs=1e-3)
        others = [k for k in range(4) if k != z]
        np.testing.assert_allclose(rest[others], here[others], atol=1e-4)
