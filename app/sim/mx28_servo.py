"""One simulated MX-28 (Protocol 2.0 firmware): its control table and its motion.

The control table is a bytearray laid out as the e-manual's
(https://emanual.robotis.com/docs/en/dxl/mx/mx-28-2/), initialised to its defaults. Writes
are checked as the firmware does: read-only items and EEPROM items with torque on give the
access error, values outside an item's range the data range error, values beyond a limit
item (position limits in position mode, Velocity/PWM/Acceleration Limit) the data limit error,
and partial writes of an item the data length error. A refused write changes nothing.

Motion is a kinematic model with perfect tracking: the profile (trapezoid under Profile
Velocity and Profile Acceleration, or Velocity Limit and Acceleration Limit where those are 0)
is integrated in steps of at most 1 ms, and Present Position follows it exactly. Present Load
(0.1 % units) is a simple model: proportional to acceleration plus Coulomb friction. Drive
Mode (reverse, time-based profile) is not modelled. Everything is deterministic.
"""

from __future__ import annotations

import math

from protocol import mx28
from protocol.dynamixel import CLEAR_MULTI_TURN, ErrorCode, from_bytes, to_bytes

#: ticks/s per raw unit of velocity (0.229 rpm)
VEL_UNIT = 0.229 * mx28.TICKS_PER_REV / 60.0
#: ticks/s^2 per raw unit of acceleration (214.577 rev/min^2)
ACC_UNIT = 214.577 * mx28.TICKS_PER_REV / 3600.0
#: integration step, s
STEP_S = 0.001
#: Present Load model, 0.1 % units: per raw acceleration unit, and Coulomb friction while moving
LOAD_PER_ACC = 0.05
FRICTION_LOAD = 40
#: Present Input Voltage (0.1 V) and Present Temperature (C) of a healthy servo on a 12 V supply
SUPPLY_V = 120
TEMPERATURE_C = 35
FIRMWARE_VERSION = 45
BAUD_CODES = {0: 9600, 1: 57_600, 2: 115_200, 3: 1_000_000, 4: 2_000_000, 5: 3_000_000,
              6: 4_000_000, 7: 4_500_000}
POSITION, EXTENDED, VELOCITY, PWM = 3, 4, 1, 16
_MODES = (VELOCITY, POSITION, EXTENDED, PWM)
_GAINS = ("velocity_i_gain", "velocity_p_gain", "position_d_gain", "position_i_gain",
          "position_p_gain", "feedforward_2nd_gain", "feedforward_1st_gain")


def _span(*names: str) -> slice:
    items = [mx28.TABLE[n] for n in names]
    return slice(min(i.address for i in items), max(i.address + i.size for i in items))


#: The items `_publish` reads (torque enable, moving threshold, goal position) and writes.
_PUB_READS_A = _span("torque_enable")
_PUB_READS_B = _span("moving_threshold")
_PUB_READS_C = _span("goal_position")
_PUB_WRITES = _span("present_position", "position_trajectory", "present_velocity",
                    "velocity_trajectory", "present_load", "present_pwm", "present_input_voltage",
                    "present_temperature", "moving", "moving_status")


class Mx28Servo:
    """A servo on the bus. `read`/`write` return ErrorCode values (0: success)."""

    def __init__(self, id: int, operating_mode: int = POSITION, baud_code: int = 1) -> None:
        self.mem = bytearray(mx28.TABLE_END)
        self.pos = 0.0  # profile (= present) position, ticks, in the reported frame
        self.vel = 0.0  # ticks/s
        self.acc = 0.0  # ticks/s^2 during the last step
        self.registered: tuple[int, bytes] | None = None
        self._published: tuple[object, ...] | None = None  # `_publish`'s inputs and outputs
        self._eeprom_defaults(keep_id=False, keep_baud=False)
        self.set("id", id)
        self.set("baud_rate", baud_code)
        self.set("operating_mode", operating_mode)
        self._ram_defaults()
        self.pos = 2048.0
        self._publish(0.0)

    # raw access ---------------------------------------------------------------------------
    def get(self, name: str) -> int:
        it = mx28.TABLE[name]
        return from_bytes(bytes(self.mem[it.address:it.address + it.size]), it.signed)

    def set(self, name: str, value: int) -> None:
        it = mx28.TABLE[name]
        self.mem[it.address:it.address + it.size] = to_bytes(value, it.size)

    @property
    def id(self) -> int:
        return self.mem[mx28.TABLE["id"].address]

    @property
    def torque(self) -> bool:
        return bool(self.get("torque_enable"))

    @property
    def alert(self) -> bool:
        return self.get("hardware_error_status") != 0

    def _eeprom_defaults(self, keep_id: bool, keep_baud: bool) -> None:
        keep = {"id": self.mem[7], "baud_rate": self.mem[8]}
        for it in mx28.TABLE.values():
            if it.area == "eeprom":
                self.set(it.name, it.default if it.default is not None else 0)
        self.set("firmware_version", FIRMWARE_VERSION)
        if keep_id:
            self.set("id", keep["id"])
        if keep_baud:
            self.set("baud_rate", keep["baud_rate"])

    def _ram_defaults(self) -> None:
        for it in mx28.TABLE.values():
            if it.area == "ram":
                self.set(it.name, it.default if it.default is not None else 0)
        self.set("goal_pwm", self.get("pwm_limit"))
        self.set("goal_position", round(self.pos))
        self.registered = None

    # instructions -------------------------------------------------------------------------
    def read(self, address: int, length: int) -> tuple[int, bytes]:
        if length == 0 or address + length > len(self.mem):
            return ErrorCode.ACCESS, b""
        return 0, bytes(self.mem[address:address + length])

    def check_write(self, address: int, data: bytes) -> int:
        """The error a write would cause (0: none), without changing anything."""
        end = address + len(data)
        if not data or end > len(self.mem):
            return ErrorCode.ACCESS
        touched = [it for it in mx28.TABLE.values()
                   if it.address < end and address < it.address + it.size]
        for it in touched:
            if it.address < address or it.address + it.size > end:
                return ErrorCode.DATA_LENGTH
            if not it.writable or (it.area == "eeprom" and self.torque):
                return ErrorCode.ACCESS
        for it in touched:
            off = it.address - address
            value = from_bytes(data[off:off + it.size], it.signed)
            if not it.min_raw <= value <= it.max_raw or (
                    it.name == "operating_mode" and value not in _MODES):
                return ErrorCode.DATA_RANGE
            if self._beyond_limit(it.name, value):
                return ErrorCode.DATA_LIMIT
        return 0

    def _beyond_limit(self, name: str, value: int) -> bool:
        if name == "goal_position" and self.get("operating_mode") == POSITION:
            return not self.get("min_position_limit") <= value <= self.get("max_position_limit")
        limit = {"goal_velocity": "velocity_limit", "goal_pwm": "pwm_limit",
                 "profile_acceleration": "acceleration_limit"}.get(name)
        return limit is not None and abs(value) > self.get(limit)

    def write(self, address: int, data: bytes) -> int:
        error = self.check_write(address, data)
        if error:
            return error
        before = {n: self.get(n) for n in ("operating_mode", "torque_enable", "homing_offset")}
        self.mem[address:address + len(data)] = data
        if self.get("operating_mode") != before["operating_mode"]:
            for name in _GAINS:
                self.set(name, mx28.TABLE[name].default or 0)
            self.set("profile_velocity", 0)
            self.set("profile_acceleration", 0)
            self.set("goal_pwm", self.get("pwm_limit"))
        if self.get("homing_offset") != before["homing_offset"]:
            self.pos += self.get("homing_offset") - before["homing_offset"]
            self._publish(0.0)
        if self.torque and not before["torque_enable"]:
            self.set("goal_position", round(self.pos))  # hold where it stands
            self.vel = 0.0
        return 0

    def reg_write(self, address: int, data: bytes) -> int:
        error = self.check_write(address, data)
        if not error:
            self.registered = (address, bytes(data))
            self.set("registered_instruction", 1)
        return error

    def action(self) -> int:
        if self.registered is None:
            return ErrorCode.INSTRUCTION
        address, data = self.registered
        self.registered = None
        self.set("registered_instruction", 0)
        return self.write(address, data)

    def reboot(self) -> int:
        """Power cycle: RAM back to defaults (torque off, hardware error cleared); a
        multi-turn position folds back into one turn as after power-up."""
        self.pos = self.pos % mx28.TICKS_PER_REV
        self.vel = self.acc = 0.0
        self._ram_defaults()
        self._publish(0.0)
        return 0

    def factory_reset(self, mode: int) -> int:
        if self.torque:
            return ErrorCode.ACCESS
        if mode not in (0xFF, 0x01, 0x02):
            return ErrorCode.DATA_RANGE
        self._eeprom_defaults(keep_id=mode in (0x01, 0x02), keep_baud=mode == 0x02)
        return self.reboot()

    def clear(self, params: bytes) -> int:
        if params != CLEAR_MULTI_TURN:
            return ErrorCode.DATA_RANGE
        if self.get("moving"):
            return ErrorCode.RESULT_FAIL
        self.pos = self.pos % mx28.TICKS_PER_REV
        self._publish(0.0)
        return 0

    def inject_hardware_error(self, bits: int) -> None:
        """Fault injection: set Hardware Error Status; a shutdown bit clears Torque Enable."""
        self.set("hardware_error_status", self.get("hardware_error_status") | bits)
        if bits & self.get("shutdown"):
            self.set("torque_enable", 0)

    # motion -------------------------------------------------------------------------------
    def advance(self, dt: float, now: float) -> None:
        """Integrate `dt` seconds of motion and refresh the Present* items."""
        self.set("realtime_tick", int(now * 1000) % 32768)
        if dt <= 0.0:
            return
        if not self.torque:
            self.vel = self.acc = 0.0
            self._publish(0.0)
            return
        mode = self.get("operating_mode")
        if (mode in (POSITION, EXTENDED) and self.vel == 0.0
                and self.pos == float(self.get("goal_position"))):
            # At rest on its goal: every step would leave it there with no acceleration.
            self.acc = 0.0
            self._publish(0.0)
            return
        t_left = dt
        while t_left > 1e-12:
            h = min(STEP_S, t_left)
            t_left -= h
            if mode in (POSITION, EXTENDED):
                self._step_position(h)
            else:
                self._step_velocity(h, mode)
        self._publish(self.vel)

    def _limits(self) -> tuple[float, float]:
        """Profile (velocity ticks/s, acceleration ticks/s^2); 0 means use the limit item."""
        pv, pa = self.get("profile_velocity"), self.get("profile_acceleration")
        vmax = (pv or self.get("velocity_limit") or 1023) * VEL_UNIT
        amax = (pa or self.get("acceleration_limit") or 32767) * ACC_UNIT
        return vmax, amax

    def _step_position(self, h: float) -> None:
        vmax, amax = self._limits()
        goal = float(self.get("goal_position"))
        err = goal - self.pos
        if abs(err) < 1e-9 and abs(self.vel) <= amax * h:
            self.pos, self.acc, self.vel = goal, -self.vel / h, 0.0
            return
        # fastest velocity from which the goal can still be reached without overshoot
        v_des = math.copysign(min(vmax, math.sqrt(2.0 * amax * abs(err))), err)
        dv = max(-amax * h, min(amax * h, v_des - self.vel))
        v_new = self.vel + dv
        p_new = self.pos + 0.5 * (self.vel + v_new) * h
        if (goal - p_new) * err <= 0.0:
            p_new, v_new = goal, 0.0
        self.acc = (v_new - self.vel) / h
        self.pos, self.vel = p_new, v_new

    def _step_velocity(self, h: float, mode: int) -> None:
        vmax, amax = self._limits()
        if mode == VELOCITY:
            target = self.get("goal_velocity") * VEL_UNIT
        else:  # PWM: no-load speed scales with duty; 55 rpm at 12 V and full PWM
            target = self.get("goal_pwm") / 885.0 * 55.0 / 0.229 * VEL_UNIT
        target = max(-vmax, min(vmax, target))
        dv = max(-amax * h, min(amax * h, target - self.vel))
        v_new = self.vel + dv
        self.pos += 0.5 * (self.vel + v_new) * h
        self.acc = dv / h
        self.vel = v_new

    def _publish(self, vel: float) -> None:
        # Polled at rest, the Present* items come out the same every time: skip the writes when
        # neither the motion state, the items they read nor the items they write have changed.
        mem = self.mem
        key = (vel, self.acc, self.pos, bytes(mem[_PUB_READS_A]), bytes(mem[_PUB_READS_B]),
               bytes(mem[_PUB_READS_C]), bytes(mem[_PUB_WRITES]))
        if key == self._published:
            return
        self._write_present(vel)
        self._published = key[:-1] + (bytes(mem[_PUB_WRITES]),)

    def _write_present(self, vel: float) -> None:
        raw_vel = int(round(vel / VEL_UNIT))
        moving = abs(raw_vel) > self.get("moving_threshold")
        load = 0
        if self.torque:
            load = round(self.acc / ACC_UNIT * LOAD_PER_ACC)
            if moving:
                load += int(math.copysign(FRICTION_LOAD, vel))
            load = max(-1000, min(1000, load))
        self.set("present_position", round(self.pos))
        self.set("position_trajectory", round(self.pos))
        self.set("present_velocity", raw_vel)
        self.set("velocity_trajectory", raw_vel)
        self.set("present_load", load)
        self.set("present_pwm", max(-885, min(885, load)) if self.torque else 0)
        self.set("present_input_voltage", SUPPLY_V)
        self.set("present_temperature", TEMPERATURE_C)
        self.set("moving", int(moving))
        in_position = abs(self.get("goal_position") - self.pos) < 1.0
        profiling = self.torque and (abs(self.vel) > 0.0 or not in_position)
        self.set("moving_status", int(in_position) | (int(profiling) << 1))
