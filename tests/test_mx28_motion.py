"""The simulated MX-28's speed as the datasheet says: never faster than the no-load speed at
the supplied voltage (e-manual specifications: 50 rpm at 11.1 V, 55 at 12 V, 67 at 14.8 V),
Velocity Limit as the ceiling of Profile Velocity and Goal Velocity, Moving / Moving Status /
Moving Threshold as documented, and Present PWM agreeing with the motion."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
from dynamixel_sdk import COMM_SUCCESS, PacketHandler, PortHandler

from app.arms.dynamixel.sim_bus import DynamixelBus
from app.arms.dynamixel.sim_motion import Motion
from protocol import dynamixel as dxl
from protocol import mx28
from protocol.dynamixel import ErrorCode
from tests.test_dynamixel_sim import patient, sdk_over_pty

RPM = 0.229  # rpm per raw velocity unit


def _w(bus: DynamixelBus, id: int, address: int, value: int, size: int, t: float = 0.0) -> int:
    [(_, data)] = bus.receive(dxl.write(id, address, dxl.to_bytes(value, size)), t)
    parser = dxl.Parser()
    parser.feed(data)
    [p] = list(parser)
    return p.error  # type: ignore[union-attr]


def _run(bus: DynamixelBus, id: int, t0: float, seconds: float, item: str) -> list[int]:
    s = bus.servo(id)
    assert s is not None
    out = []
    for k in range(1, int(seconds / 0.01) + 1):
        bus.advance(t0 + k * 0.01)
        out.append(s.get(item))
    return out


@pytest.mark.parametrize(("volts", "rpm"), [(11.1, 50.0), (12.0, 55.0), (14.8, 67.0)])
def test_position_move_never_faster_than_no_load_speed(volts: float, rpm: float) -> None:
    bus = DynamixelBus(operating_modes={1: 4})
    bus.set_supply_voltage(volts)
    assert _w(bus, 1, 44, 380, 4) == 0  # Velocity Limit as before firmware V42 (default 230)
    assert _w(bus, 1, 64, 1, 1) == 0
    assert _w(bus, 1, 112, 380, 4) == 0  # Profile Velocity 87 rpm: more than the motor can
    assert _w(bus, 1, 116, 2048 + 4 * 4096, 4) == 0
    speeds = _run(bus, 1, 0.0, 2.0, "present_velocity")
    assert max(speeds) == round(rpm / RPM)
    s = bus.servo(1)
    assert s is not None
    # the profile runs ahead at Profile Velocity; the motor lags it: following error
    assert s.get("velocity_trajectory") == 380
    assert s.get("moving_status") & mx28.FOLLOWING_ERROR
    assert s.get("present_pwm") == 885  # full duty at full speed: the PWM model agrees
    _run(bus, 1, 2.0, 4.0, "present_velocity")
    assert s.get("present_position") == 2048 + 4 * 4096
    assert s.get("moving_status") & 0x0F == mx28.IN_POSITION


def test_pwm_limit_scales_the_cap_and_velocity_and_pwm_modes_obey_it() -> None:
    bus = DynamixelBus(operating_modes={1: 1, 2: 16, 3: 4})
    assert _w(bus, 3, 36, 442, 2) == 0  # PWM Limit: half duty
    assert _w(bus, 1, 44, 380, 4) == 0  # Velocity Limit as before firmware V42 (default 230)
    for i in (1, 2, 3):
        assert _w(bus, i, 64, 1, 1) == 0
    assert _w(bus, 1, 104, 380, 4) == 0  # Goal Velocity at the Velocity Limit
    assert _w(bus, 2, 100, 885, 2) == 0  # Goal PWM full
    assert _w(bus, 3, 116, 100_000, 4) == 0  # step: Profile Velocity 0
    bus.advance(1.0)
    s1, s2, s3 = bus.servo(1), bus.servo(2), bus.servo(3)
    assert s1 is not None and s2 is not None and s3 is not None
    assert s1.get("present_velocity") == round(55.0 / RPM)
    assert s2.get("present_velocity") == round(55.0 / RPM)
    assert s3.get("present_velocity") == round(55.0 / 2 * 442 / 442.5 / RPM)
    bus.set_supply_voltage(14.8, ids=[2])
    bus.advance(2.0)
    assert s2.get("present_velocity") == round(67.0 / RPM)
    assert s2.get("present_pwm") == 885


def test_velocity_limit_is_the_ceiling_of_profile_and_goal_velocity() -> None:
    bus = DynamixelBus(operating_modes={2: 1})
    # Profile Velocity 231 > Velocity Limit 230 (its default from firmware V42): data limit
    # error, nothing changes
    assert _w(bus, 1, 112, 231, 4) == ErrorCode.DATA_LIMIT
    assert bus.servo(1).get("profile_velocity") == 0  # type: ignore[union-attr]
    assert _w(bus, 1, 112, 230, 4) == 0
    assert _w(bus, 2, 104, -231, 4) == ErrorCode.DATA_LIMIT
    assert _w(bus, 2, 104, -230, 4) == 0
    # lower the limit (EEPROM, torque off): the ceiling moves with it
    assert _w(bus, 1, 44, 200, 4) == 0
    assert _w(bus, 1, 112, 201, 4) == ErrorCode.DATA_LIMIT
    assert _w(bus, 1, 112, 200, 4) == 0


def test_profile_velocity_left_above_a_lowered_limit_is_capped_by_it() -> None:
    bus = DynamixelBus()
    assert _w(bus, 1, 112, 150, 4) == 0
    assert _w(bus, 1, 44, 100, 4) == 0  # Velocity Limit below the Profile Velocity in place
    assert _w(bus, 1, 64, 1, 1) == 0
    assert _w(bus, 1, 116, 4000, 4) == 0
    assert max(_run(bus, 1, 0.0, 1.0, "present_velocity")) == 100


@pytest.mark.parametrize(("pv", "pa", "goal", "kind"), [
    (0, 0, 3000, mx28.PROFILE_STEP),
    (100, 0, 3000, mx28.PROFILE_RECTANGULAR),
    (100, 20, 2100, mx28.PROFILE_TRIANGULAR),
    (100, 20, 4000, mx28.PROFILE_TRAPEZOIDAL),
])
def test_moving_status_profile_type_ongoing_and_in_position(
        pv: int, pa: int, goal: int, kind: int) -> None:
    bus = DynamixelBus()
    s = bus.servo(1)
    assert s is not None
    assert s.get("moving_status") == 0  # torque off: no controller, nothing to report
    assert _w(bus, 1, 108, pa, 4) == 0 and _w(bus, 1, 112, pv, 4) == 0
    assert _w(bus, 1, 64, 1, 1) == 0
    assert s.get("moving_status") & 0x0F == mx28.IN_POSITION  # holding where it stands
    assert _w(bus, 1, 116, goal, 4) == 0
    bus.advance(0.05)
    status = s.get("moving_status")
    assert status & mx28.PROFILE_TYPE_MASK == kind
    assert not status & mx28.IN_POSITION
    if pv:
        assert status & mx28.PROFILE_ONGOING
    moving = _run(bus, 1, 0.05, 6.0, "moving")
    assert moving[0] == 1 or pa, "a move without a ramp is at speed at once"
    assert 1 in moving and moving[-1] == 0
    assert s.get("present_position") == goal
    assert s.get("moving_status") & 0x0F == mx28.IN_POSITION


def test_moving_threshold_decides_the_moving_flag() -> None:
    bus = DynamixelBus()
    assert _w(bus, 1, 24, 50, 4) == 0  # Moving Threshold 50 units
    assert _w(bus, 1, 112, 40, 4) == 0  # slower than the threshold
    assert _w(bus, 1, 64, 1, 1) == 0
    assert _w(bus, 1, 116, 3000, 4) == 0
    moving = _run(bus, 1, 0.0, 0.5, "moving")
    speeds = _run(bus, 1, 0.5, 0.1, "present_velocity")
    assert set(speeds) == {40} and set(moving) == {0}
    assert bus.servo(1).get("moving_status") & mx28.PROFILE_ONGOING  # type: ignore[union-attr]


def test_torque_off_mid_move_stops_and_reports_nothing_moving() -> None:
    bus = DynamixelBus()
    assert _w(bus, 1, 64, 1, 1) == 0
    assert _w(bus, 1, 116, 4000, 4) == 0
    bus.advance(0.2)
    bus.inject_hardware_error(1, "overload")
    bus.advance(0.3)
    s = bus.servo(1)
    assert s is not None
    at = s.get("present_position")
    bus.advance(1.0)
    assert s.get("present_position") == at < 4000
    assert (s.get("present_velocity"), s.get("moving"), s.get("moving_status")) == (0, 0, 0)
    assert s.get("present_pwm") == 0


# through DynamixelSDK over a pseudo-terminal --------------------------------------------------

@pytest.fixture()
def sdk(tmp_path: Path) -> Iterator[tuple[PortHandler, PacketHandler, DynamixelBus]]:
    with sdk_over_pty(DynamixelBus(ids=(1,), operating_modes={1: 4}), tmp_path / "ttyDXL") as sdk:
        yield sdk


def test_sdk_velocity_limit_refusal_and_speed_cap(
        sdk: tuple[PortHandler, PacketHandler, DynamixelBus]) -> None:
    port, ph, bus = sdk
    assert patient(ph.write4ByteTxRx, port, 1, 112, 231) == (COMM_SUCCESS, ErrorCode.DATA_LIMIT)
    assert patient(ph.read4ByteTxRx, port, 1, 112) == (0, COMM_SUCCESS, 0)
    # Velocity Limit as before firmware V42 (default 230), so the profile can outrun the motor
    assert patient(ph.write4ByteTxRx, port, 1, 44, 380) == (COMM_SUCCESS, 0)
    assert patient(ph.write4ByteTxRx, port, 1, 112, 380) == (COMM_SUCCESS, 0)
    assert patient(ph.write1ByteTxRx, port, 1, 64, 1) == (COMM_SUCCESS, 0)
    assert patient(ph.write4ByteTxRx, port, 1, 116, 2048 + 20 * 4096) == (COMM_SUCCESS, 0)
    speeds, statuses = [], []
    for _ in range(40):  # the profile asks 380 units (87 rpm) at once (rectangular)
        # one READ of Moving Status (123) .. Present Velocity (128-131)
        data, result, error = patient(ph.readTxRx, port, 1, 123, 9)
        assert (result, error, len(data)) == (COMM_SUCCESS, 0, 9)
        statuses.append(data[0])
        speeds.append(dxl.from_bytes(bytes(data[5:9]), True))
    assert max(speeds) == round(55.0 / RPM) == 240  # never faster than 55 rpm at 12 V
    assert all(st & mx28.PROFILE_TYPE_MASK == mx28.PROFILE_RECTANGULAR for st in statuses)
    assert all(st & mx28.PROFILE_ONGOING for st in statuses)
    assert statuses[-1] & mx28.FOLLOWING_ERROR  # the motor falls behind the profile


class _Integrating(Motion):
    """The motion without the at-rest shortcut: every step integrated (the reference)."""

    @property
    def at_rest(self) -> bool:
        return False


def _table(bus: DynamixelBus, t: float) -> bytes:
    """Every servo's whole RAM area (64..146) as one SYNC_READ answers it at time `t`."""
    ids = [s.id for s in bus.servos]
    return b"".join(d for _, d in bus.receive(dxl.sync_read(64, 83, ids), t))


def test_the_at_rest_shortcut_sends_the_same_bytes_as_integrating() -> None:
    """A servo at rest skips its 1 kHz integration (most of an idle simulator's cost): the
    bytes it answers (positions, velocities, loads, PWM, Moving Status, trajectories) are the
    same as integrating every step, at rest, through a move and after torque off."""
    fast, ref = DynamixelBus(), DynamixelBus()
    for s in ref.servos:
        m = _Integrating()
        m.reset(s.motion.pos)
        s.motion = m
    assert all(s.motion.at_rest for s in fast.servos)  # fresh servos rest on their goal
    rested = 0
    t = 0.0
    # Goal PWM 100 caps the motor below the profile: the trajectory ends before the motor
    # does (on its goal, the motor still lagging), then full duty again.
    script = {0.1: (64, 1, 1), 0.2: (112, 60, 4), 0.21: (108, 20, 4), 0.3: (116, 2600, 4),
              1.5: (116, 1900, 4), 1.51: (100, 100, 2), 2.5: (100, 885, 2),
              2.8: (64, 0, 1), 3.0: (64, 1, 1), 3.1: (116, 2048, 4)}
    for k in range(2000):
        t = round(k * 0.002, 6)
        for when, (address, value, size) in script.items():
            if abs(t - when) < 1e-9:
                assert _w(fast, 2, address, value, size, t) == _w(ref, 2, address, value, size, t)
        assert _table(fast, t) == _table(ref, t), f"t={t}"
        rested += fast.servo(2).motion.at_rest  # type: ignore[union-attr]
    assert 0 < rested < 2000  # the shortcut was taken, and servo 2 moved too
    # the servos that never moved skipped their whole step (nothing they read had changed)
    # and still answered the same bytes as the reference above
    assert all(s._rest is not None for s in fast.servos if s.id != 2)
    assert all(s._rest is None for s in ref.servos)
    s = fast.servo(2)
    assert s is not None and s.get("present_position") == 2048
