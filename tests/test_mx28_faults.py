"""The simulated MX-28 as the e-manual documents it: the Alert bit, Hardware Error Status and
the Shutdown register, REBOOT, power cycles and supply voltage (docs/hardware.md, "Dynamixel
MX-28"). Driven through the bus's bytes and through the public DynamixelSDK over a pty."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
from dynamixel_sdk import COMM_SUCCESS, PacketHandler, PortHandler

from app.arms.dynamixel.sim_bus import DynamixelBus
from protocol import dynamixel as dxl
from protocol import mx28
from protocol.dynamixel import ErrorCode, Packet
from tests.test_dynamixel_sim import patient, sdk_over_pty

H = bytes.fromhex
ALERT = 0x80
TURN = 4096


def _one(bus: DynamixelBus, packet: bytes, now: float = 0.0) -> Packet:
    parser = dxl.Parser()
    for _, data in bus.receive(packet, now):
        parser.feed(data)
    [p] = list(parser)
    assert isinstance(p, Packet)
    return p


def _raw(bus: DynamixelBus, packet: bytes, now: float = 0.0) -> bytes:
    [(_, data)] = bus.receive(packet, now)
    return data


# Alert bit and Hardware Error Status ----------------------------------------------------------

def test_alert_bit_in_every_status_packet_while_faulted() -> None:
    bus = DynamixelBus()
    bus.inject_hardware_error(1, "overload")
    # PING, READ and WRITE replies all carry 0x80; error number 0 (the instruction succeeded)
    assert _raw(bus, dxl.ping(1)) == H("FFFFFD00 01 0700 55 80 1E002D 80C4")
    assert _raw(bus, dxl.read(1, 70, 1)) == H("FFFFFD00 01 0500 55 80 20 9921")
    assert _raw(bus, dxl.write(1, 65, b"\x01")) == H("FFFFFD00 01 0400 55 80 A28F")
    [p] = [_one(bus, dxl.sync_read(70, 1, [1]))]
    assert (p.error, p.params) == (ALERT, b"\x20")
    # an error number and the alert bit together: a refused write while faulted
    assert _one(bus, dxl.write(1, 132, dxl.to_bytes(0, 4))).error == ALERT | ErrorCode.ACCESS
    # the other servos are healthy
    assert _one(bus, dxl.read(2, 70, 1)) == Packet(2, 0x55, b"\x00", 0)


@pytest.mark.parametrize(("name", "bit"), sorted(mx28.HARDWARE_ERRORS.items()))
def test_every_hardware_error_bit_injectable_by_name(name: str, bit: int) -> None:
    bus = DynamixelBus()
    assert _one(bus, dxl.write(1, 64, b"\x01")).error == 0
    bus.inject_hardware_error(1, name)
    p = _one(bus, dxl.read(1, 64, 7))  # Torque Enable .. Hardware Error Status
    assert p.error == ALERT and p.params[70 - 64] == bit
    shutdown = bool(bit & mx28.SHUTDOWN_DEFAULT)  # overheating, electrical shock, overload
    assert p.params[0] == (0 if shutdown else 1)
    assert mx28.hardware_error_names(p.params[70 - 64]) == [name]


def test_unknown_fault_name_is_refused_naming_the_valid_ones() -> None:
    with pytest.raises(ValueError, match="overload"):
        DynamixelBus().inject_hardware_error(1, "melted")


def test_shutdown_register_decides_which_errors_turn_torque_off() -> None:
    bus = DynamixelBus()
    assert _one(bus, dxl.write(1, 63, b"\x01")).error == 0  # Shutdown: input voltage only
    _one(bus, dxl.write(1, 64, b"\x01"))
    bus.inject_hardware_error(1, "overload")
    assert bus.servo(1).torque  # type: ignore[union-attr]
    bus.inject_hardware_error(1, "input_voltage")
    assert not bus.servo(1).torque  # type: ignore[union-attr]
    assert _one(bus, dxl.read(1, 70, 1)).params == b"\x21"


def test_supply_outside_voltage_limits_raises_input_voltage_error() -> None:
    bus = DynamixelBus()
    _one(bus, dxl.write(1, 64, b"\x01"))
    bus.set_supply_voltage(9.0, ids=[1])  # below Min Voltage Limit 9.5 V
    p = _one(bus, dxl.read(1, 144, 2), 0.1)
    assert (p.error, dxl.from_bytes(p.params, False)) == (ALERT, 90)
    assert _one(bus, dxl.read(1, 70, 1), 0.1).params == b"\x01"
    assert bus.servo(1).torque  # type: ignore[union-attr]  # not a default shutdown bit
    bus.set_supply_voltage(12.0)
    # latched: the error stays until REBOOT, which clears it (the supply is good again)
    assert _one(bus, dxl.read(1, 70, 1), 0.2).params == b"\x01"
    _one(bus, dxl.reboot(1), 0.3)
    assert _one(bus, dxl.read(1, 70, 1), 0.4) == Packet(1, 0x55, b"\x00", 0)


def test_overheating_from_temperature_shuts_down() -> None:
    bus = DynamixelBus()
    _one(bus, dxl.write(2, 64, b"\x01"))
    bus.set_temperature(81.0, ids=[2])  # Temperature Limit 80 C
    p = _one(bus, dxl.read(2, 64, 1), 0.1)
    assert (p.error, p.params) == (ALERT, b"\x00")
    assert _one(bus, dxl.read(2, 146, 1), 0.1).params == bytes([81])
    assert _one(bus, dxl.read(2, 70, 1), 0.1).params == b"\x04"


# torque refused after a shutdown, until REBOOT -----------------------------------------------

def test_torque_cannot_be_turned_on_after_shutdown_until_reboot() -> None:
    bus = DynamixelBus()
    _one(bus, dxl.write(1, 64, b"\x01"))
    bus.inject_hardware_error(1, "overload")
    # the write is ignored: the status carries only the alert bit, Torque Enable stays 0
    assert _one(bus, dxl.write(1, 64, b"\x01")).error == ALERT
    assert _one(bus, dxl.read(1, 64, 1)).params == b"\x00"
    # a write spanning Torque Enable and LED changes nothing either
    assert _one(bus, dxl.write(1, 64, b"\x01\x01")).error == ALERT
    assert _one(bus, dxl.read(1, 64, 2)).params == b"\x00\x00"
    # clearing the shutdown bit afterwards does not help: REBOOT is the only way
    assert _one(bus, dxl.write(1, 63, b"\x00")).error == ALERT
    assert _one(bus, dxl.write(1, 64, b"\x01")).error == ALERT
    assert _one(bus, dxl.read(1, 64, 1)).params == b"\x00"
    # sync write and REG_WRITE/ACTION are refused alike, silently
    assert bus.receive(dxl.sync_write(64, 1, {1: b"\x01"}), 0.0) == []
    _one(bus, dxl.reg_write(1, 64, b"\x01"))
    assert _one(bus, dxl.action(1)).error == ALERT
    assert not bus.servo(1).torque  # type: ignore[union-attr]
    # other RAM writes are still taken
    assert _one(bus, dxl.write(1, 116, dxl.to_bytes(1000, 4))).error == ALERT
    assert _one(bus, dxl.reboot(1)) == Packet(1, 0x55, b"", 0)
    assert _one(bus, dxl.write(1, 64, b"\x01")) == Packet(1, 0x55, b"", 0)
    assert _one(bus, dxl.read(1, 64, 1)).params == b"\x01"


def test_torque_refusal_can_answer_result_fail() -> None:
    bus = DynamixelBus()
    bus.set_torque_refusal(ErrorCode.RESULT_FAIL)
    bus.inject_hardware_error(3, 0x10)
    assert _one(bus, dxl.write(3, 64, b"\x01")).error == ALERT | ErrorCode.RESULT_FAIL
    assert _one(bus, dxl.read(3, 64, 1)).params == b"\x00"


# REBOOT, power cycle, brown-out ---------------------------------------------------------------

def _extended_at(bus: DynamixelBus, id: int, goal: int, t: float) -> float:
    _one(bus, dxl.write(id, 11, b"\x04"), t)
    _one(bus, dxl.write(id, 64, b"\x01"), t)
    _one(bus, dxl.write(id, 112, dxl.to_bytes(200, 4)), t)
    _one(bus, dxl.write(id, 116, dxl.to_bytes(goal, 4)), t)
    for k in range(1, 2000):
        bus.advance(t + k * 0.01)
        if _one(bus, dxl.read(id, 132, 4), t + k * 0.01).params == dxl.to_bytes(goal, 4):
            return t + k * 0.01
    raise AssertionError("never arrived")


def test_reboot_restores_ram_defaults_and_folds_extended_position() -> None:
    bus = DynamixelBus()
    goal = 2048 + 3 * TURN + 100
    t = _extended_at(bus, 1, goal, 0.0)
    _one(bus, dxl.write(1, 65, b"\x01"), t)
    bus.inject_hardware_error(1, "electrical_shock")
    assert _one(bus, dxl.reboot(1), t) == Packet(1, 0x55, b"", 0)
    s = bus.servo(1)
    assert s is not None
    assert (s.get("torque_enable"), s.get("led"), s.get("hardware_error_status")) == (0, 0, 0)
    assert (s.get("profile_velocity"), s.get("profile_acceleration")) == (0, 0)
    assert s.get("operating_mode") == 4  # EEPROM kept
    assert s.get("present_position") == goal % TURN == 2148  # the 3 turns are lost
    assert s.get("goal_position") == 2148
    bus.advance(t + 1.0)
    assert s.get("present_position") == 2148  # torque off: it does not move


def test_fold_keeps_the_homing_offset() -> None:
    bus = DynamixelBus()
    _one(bus, dxl.write(1, 20, dxl.to_bytes(-1000, 4)))  # Homing Offset: present 2048 -> 1048
    assert _one(bus, dxl.read(1, 132, 4)).params == dxl.to_bytes(1048, 4)
    goal = 1048 + 2 * TURN + 7
    t = _extended_at(bus, 1, goal, 0.0)
    _one(bus, dxl.reboot(1), t)
    # the absolute angle within one turn (2055), then the offset: 1055
    assert _one(bus, dxl.read(1, 132, 4), t).params == dxl.to_bytes(1055, 4)


def test_mode_change_to_position_folds_present_position() -> None:
    bus = DynamixelBus()
    t = _extended_at(bus, 2, 2048 - 2 * TURN - 48, 0.0)
    _one(bus, dxl.write(2, 64, b"\x00"), t)
    assert _one(bus, dxl.read(2, 132, 4), t).params == dxl.to_bytes(2048 - 2 * TURN - 48, 4)
    _one(bus, dxl.write(2, 11, b"\x03"), t)
    assert _one(bus, dxl.read(2, 132, 4), t).params == dxl.to_bytes(2000, 4)


def test_power_cycle_and_brown_out_lose_ram_silently() -> None:
    bus = DynamixelBus()
    t = _extended_at(bus, 1, 2048 + 5 * TURN, 0.0)
    _extended_at(bus, 2, 2048 - TURN - 1, t)
    bus.brown_out(ids=[1])
    s1, s2 = bus.servo(1), bus.servo(2)
    assert s1 is not None and s2 is not None
    assert (s1.get("torque_enable"), s1.get("present_position"), s1.get("profile_velocity")) \
        == (0, 2048, 0)
    assert (s2.get("torque_enable"), s2.get("present_position")) == (1, 2048 - TURN - 1)
    bus.power_cycle()
    assert (s2.get("torque_enable"), s2.get("present_position")) == (0, 2047)
    assert _one(bus, dxl.ping(2)).error == 0  # no alert: a power cycle leaves no trace


# through DynamixelSDK over a pseudo-terminal --------------------------------------------------

@pytest.fixture()
def sdk(tmp_path: Path) -> Iterator[tuple[PortHandler, PacketHandler, DynamixelBus]]:
    with sdk_over_pty(DynamixelBus(ids=(1, 2), operating_modes={1: 4}), tmp_path / "ttyDXL") as sdk:
        yield sdk


def test_sdk_sees_alert_reads_hardware_error_and_is_refused_torque(
        sdk: tuple[PortHandler, PacketHandler, DynamixelBus]) -> None:
    port, ph, bus = sdk
    assert patient(ph.write1ByteTxRx, port, 1, 64, 1) == (COMM_SUCCESS, 0)
    bus.inject_hardware_error(1, "overload")
    assert patient(ph.ping, port, 1) == (30, COMM_SUCCESS, ALERT)
    assert patient(ph.read1ByteTxRx, port, 1, 70) == (0x20, COMM_SUCCESS, ALERT)
    assert patient(ph.read1ByteTxRx, port, 1, 64) == (0, COMM_SUCCESS, ALERT)
    assert patient(ph.write1ByteTxRx, port, 1, 64, 1) == (COMM_SUCCESS, ALERT)
    assert patient(ph.read1ByteTxRx, port, 1, 64) == (0, COMM_SUCCESS, ALERT)
    assert "Hardware error" in ph.getRxPacketError(ALERT)
    assert patient(ph.ping, port, 2) == (30, COMM_SUCCESS, 0)
    assert patient(ph.reboot, port, 1) == (COMM_SUCCESS, 0)
    assert patient(ph.read1ByteTxRx, port, 1, 70) == (0, COMM_SUCCESS, 0)
    assert patient(ph.write1ByteTxRx, port, 1, 64, 1) == (COMM_SUCCESS, 0)
    assert patient(ph.read1ByteTxRx, port, 1, 64) == (1, COMM_SUCCESS, 0)


def test_sdk_reboot_folds_multi_turn_position(
        sdk: tuple[PortHandler, PacketHandler, DynamixelBus]) -> None:
    port, ph, bus = sdk
    s = bus.servo(1)
    assert s is not None
    assert patient(ph.write1ByteTxRx, port, 1, 64, 1) == (COMM_SUCCESS, 0)
    s.motion.reset(2048.0 + 4 * TURN + 300)  # the carriage wound 4 turns out
    s.set("goal_position", 2048 + 4 * TURN + 300)
    s.motion.new_goal(2048 + 4 * TURN + 300, 0, 0)
    assert patient(ph.read4ByteTxRx, port, 1, 132) == (2048 + 4 * TURN + 300, COMM_SUCCESS, 0)
    assert patient(ph.write4ByteTxRx, port, 1, 112, 100) == (COMM_SUCCESS, 0)
    assert patient(ph.reboot, port, 1) == (COMM_SUCCESS, 0)
    assert patient(ph.read4ByteTxRx, port, 1, 132) == (2348, COMM_SUCCESS, 0)
    assert patient(ph.read4ByteTxRx, port, 1, 112) == (0, COMM_SUCCESS, 0)
    assert patient(ph.read1ByteTxRx, port, 1, 64) == (0, COMM_SUCCESS, 0)
