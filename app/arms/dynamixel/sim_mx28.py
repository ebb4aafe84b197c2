"""One simulated MX-28 (Protocol 2.0 firmware): its control table, its faults and its motion.

Sources: the MX-28(2.0) e-manual (https://emanual.robotis.com/docs/en/dxl/mx/mx-28-2/) and the
Protocol 2.0 page (https://emanual.robotis.com/docs/en/dxl/protocol2/); docs/hardware.md
("Dynamixel MX-28") cites the section of each behaviour below.

The control table is a bytearray laid out as the e-manual's, initialised to its defaults.
Writes are checked as the firmware does: read-only items and EEPROM items with torque on give
the access error, values outside an item's range the data range error, values beyond a limit
item (position limits in position mode, Velocity Limit for Profile Velocity and Goal Velocity,
PWM/Acceleration Limit) the data limit error, and partial writes of an item the data length
error. A refused write changes nothing.

Faults: Hardware Error Status (70) bits stay set until a REBOOT (or a power cycle); while any
is set every status packet carries the Alert bit (the bus adds it). A bit that is also set in
Shutdown (63) clears Torque Enable, and Torque Enable cannot be set again until a REBOOT: the
e-manual does not say what the servo answers to such a write; this one ignores it (nothing
changes) and answers with no error number, so the host sees only the Alert bit
(`TORQUE_REFUSAL`; a bus may choose the result-fail error instead). The input voltage and
overheating bits are also raised by the conditions themselves (supply outside the voltage
limits, temperature above the limit).

Motion: in the position modes a profile generator (Profile Velocity/Acceleration: step,
rectangular, triangular or trapezoidal, as the e-manual's Profile Velocity section) drives
Position/Velocity Trajectory (140/136); the motor follows the trajectory exactly where it
can, but never faster than its no-load speed at the present supply voltage (55 rpm at 12 V,
scaled by the PWM limit in force): a trajectory it cannot follow leaves it behind, with the
Following Error bit of Moving Status set. Present PWM is the duty that speed needs, so the
PWM model and the motion agree. Present Load (0.1 %) is proportional to acceleration plus
Coulomb friction. Drive Mode (reverse, time-based profile) is not modelled. Deterministic.
"""

from __future__ import annotations

import functools
import math
from types import ModuleType

from app.arms.dynamixel.sim_motion import Motion
from protocol import mx28
from protocol.dynamixel import CLEAR_MULTI_TURN, ErrorCode, from_bytes, to_bytes

#: Present Input Voltage (V) and Present Temperature (C) of a healthy servo on a 12 V supply
SUPPLY_V = 12.0
TEMPERATURE_C = 35
FIRMWARE_VERSION = 45
#: the status error number answered to Torque Enable = 1 after a shutdown (0: none, the
#: write is ignored and only the Alert bit shows); the e-manual is silent, see the docstring
TORQUE_REFUSAL = 0
#: Present Load model, 0.1 % units: per raw acceleration unit, and Coulomb friction while moving
LOAD_PER_ACC = 0.05
FRICTION_LOAD = 40
#: ticks/s per raw velocity unit and ticks/s^2 per raw acceleration unit (old names, kept)
VEL_UNIT = mx28.VEL_TICKS_PER_UNIT
ACC_UNIT = mx28.ACC_TICKS_PER_UNIT
BAUD_CODES = {0: 9600, 1: 57_600, 2: 115_200, 3: 1_000_000, 4: 2_000_000, 5: 3_000_000,
              6: 4_000_000, 7: 4_500_000}
POSITION, EXTENDED, VELOCITY, PWM = 3, 4, 1, 16
_MODES = (VELOCITY, POSITION, EXTENDED, PWM)
_GAINS = ("velocity_i_gain", "velocity_p_gain", "position_d_gain", "position_i_gain",
          "position_p_gain", "feedforward_2nd_gain", "feedforward_1st_gain")
_LIMITS = {"goal_velocity": "velocity_limit", "profile_velocity": "velocity_limit",
           "goal_pwm": "pwm_limit", "profile_acceleration": "acceleration_limit"}


#: What a servo's step reads (see `Mx28Servo._rest_key`).
_RestKey = tuple[bytearray, bytearray, float, float, float, float, int]


@functools.cache
def _layout(spec: ModuleType) -> dict[str, tuple[int, int, int, bool]]:
    """(start, end, size, signed) of each control-table item of `spec`, by name: `get` and
    `set` run a few dozen times per servo per poll."""
    return {name: (it.address, it.address + it.size, it.size, it.signed)
            for name, it in spec.TABLE.items()}


class Mx28Servo:
    """A servo on the bus. `read`/`write` return ErrorCode values (0: success).

    The model is data: `spec` is the control-table module (protocol/mx28.py here), `modes`
    the Operating Mode values it accepts, `position_modes` those run by the profile
    generator, `limits` the items bounded by another item. A subclass for another
    Protocol 2.0 model of the same family changes these (app/arms/dynamixel/sim_xm430.py)."""

    spec: ModuleType = mx28
    modes: tuple[int, ...] = _MODES
    position_modes: tuple[int, ...] = (POSITION, EXTENDED)
    limits: dict[str, str] = _LIMITS
    firmware_version = FIRMWARE_VERSION

    def __init__(self, id: int, operating_mode: int = POSITION, baud_code: int = 1) -> None:
        self.mem = bytearray(self.spec.TABLE_END)
        self.motion = Motion()
        self.registered: tuple[int, bytes] | None = None
        self.supply_v = SUPPLY_V  # volts at the servo's power input
        self.temperature_c = float(TEMPERATURE_C)
        self.shut_down = False  # a shutdown happened: torque stays off until REBOOT
        #: `_rest_key()` after a step that left the motor at rest (None: moving, or not yet).
        self._rest: _RestKey | None = None
        self.torque_refusal = TORQUE_REFUSAL
        self._eeprom_defaults(keep_id=False, keep_baud=False)
        self.set("id", id)
        self.set("baud_rate", baud_code)
        self.set("operating_mode", operating_mode)
        self.motion.reset(2048.0)
        self._ram_defaults()
        self._publish()

    # raw access ---------------------------------------------------------------------------
    def get(self, name: str) -> int:
        start, end, _, signed = _layout(self.spec)[name]
        return int.from_bytes(self.mem[start:end], "little", signed=signed)

    def set(self, name: str, value: int) -> None:
        start, end, size, _ = _layout(self.spec)[name]
        self.mem[start:end] = to_bytes(value, size)

    @property
    def id(self) -> int:
        return self.mem[mx28.TABLE["id"].address]  # the same address on every model

    @property
    def torque(self) -> bool:
        return bool(self.get("torque_enable"))

    @property
    def alert(self) -> bool:
        return self.get("hardware_error_status") != 0

    @property
    def pos(self) -> float:
        """Present position, ticks, in the reported frame (homing offset included)."""
        return self.motion.pos

    @pos.setter
    def pos(self, value: float) -> None:
        """Put the motor at `value` ticks, at rest (a test's way to wind a carriage out)."""
        self.motion.reset(float(value))
        self._publish()

    def carry(self, ticks: float, ticks_per_s: float, now: float) -> None:
        """An outside force turns the horn (torque off: a hand, gravity): the motor at `ticks`,
        turning at `ticks_per_s`, its Present Position and Velocity published at `now` with
        no time passed (app/sim/hand.py, app/arms/dynamixel/sim_gravity.py)."""
        self.motion.reset(float(ticks))
        self.motion.vel = float(ticks_per_s)
        self.advance(0.0, now)

    @property
    def vel(self) -> float:
        """Present velocity, ticks/s."""
        return self.motion.vel

    @property
    def acc(self) -> float:
        """Acceleration during the last integration step, ticks/s^2."""
        return self.motion.acc

    def _eeprom_defaults(self, keep_id: bool, keep_baud: bool) -> None:
        keep = {"id": self.mem[7], "baud_rate": self.mem[8]}
        for it in self.spec.TABLE.values():
            if it.area == "eeprom":
                self.set(it.name, it.default if it.default is not None else 0)
        self.set("firmware_version", self.firmware_version)
        if keep_id:
            self.set("id", keep["id"])
        if keep_baud:
            self.set("baud_rate", keep["baud_rate"])

    def _ram_defaults(self) -> None:
        for it in self.spec.TABLE.values():
            if it.area == "ram":
                self.set(it.name, it.default if it.default is not None else 0)
        self.set("goal_pwm", self.get("pwm_limit"))
        self.set("goal_position", round(self.pos))
        self.registered = None
        self.shut_down = False
        self.motion.stop()

    def _fold(self) -> None:
        """Present Position re-initialised within one turn (0..4095, then the homing offset
        added), as at power-up, on entering position mode and on torque-on in it."""
        offset = self.get("homing_offset")
        self.motion.reset((self.pos - offset) % mx28.TICKS_PER_REV + offset)

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
        touched = [it for it in self.spec.TABLE.values()
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
                    it.name == "operating_mode" and value not in self.modes):
                return ErrorCode.DATA_RANGE
            if self._beyond_limit(it.name, value):
                return ErrorCode.DATA_LIMIT
        return 0

    def _beyond_limit(self, name: str, value: int) -> bool:
        if name == "goal_position" and self.get("operating_mode") == POSITION:
            return not self.get("min_position_limit") <= value <= self.get("max_position_limit")
        limit = self.limits.get(name)
        return limit is not None and abs(value) > self.get(limit)

    def _torque_refused(self, address: int, data: bytes) -> bool:
        """A write that would turn torque on after a shutdown (refused until REBOOT)."""
        at = self.spec.TABLE["torque_enable"].address
        return self.shut_down and address <= at < address + len(data) and data[at - address] != 0

    def write(self, address: int, data: bytes) -> int:
        error = self.check_write(address, data)
        if error:
            return error
        if self._torque_refused(address, data):
            return self.torque_refusal
        names = ("operating_mode", "torque_enable", "homing_offset", "goal_position")
        before = {n: self.get(n) for n in names}
        self.mem[address:address + len(data)] = data
        goal_written = address <= self.spec.TABLE["goal_position"].address < address + len(data)
        mode = self.get("operating_mode")
        if mode != before["operating_mode"]:
            for name in _GAINS:
                self.set(name, self.spec.TABLE[name].default or 0)
            self.set("profile_velocity", 0)
            self.set("profile_acceleration", 0)
            self.set("goal_pwm", self.get("pwm_limit"))
            if mode == POSITION:
                self._fold()
        if self.get("homing_offset") != before["homing_offset"]:
            self.motion.reset(self.pos + self.get("homing_offset") - before["homing_offset"])
        if self.torque and not before["torque_enable"]:
            if mode == POSITION:
                self._fold()
            self.set("goal_position", round(self.pos))  # hold where it stands
            self.motion.stop()
            goal_written = True
        if goal_written and mode in self.position_modes:
            self.motion.new_goal(self.get("goal_position"), *self._profile())
        self._publish()
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
        """REBOOT (or a power cycle): RAM back to defaults (torque off, Profile Velocity 0,
        hardware error and shutdown cleared); Present Position re-initialised within one turn,
        so an extended-position count is lost."""
        self._fold()
        self._ram_defaults()
        self._publish()
        return 0

    power_cycle = reboot

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
        self._fold()
        self.set("goal_position", round(self.pos))
        self._publish()
        return 0

    # faults -------------------------------------------------------------------------------
    def inject_hardware_error(self, bits: int | str | list[str] | tuple[str, ...]) -> None:
        """Raise Hardware Error Status bits (a mask, a name such as "overload", or names);
        a bit also set in Shutdown turns torque off until REBOOT."""
        mask = bits if isinstance(bits, int) else self.spec.hardware_error_bits(bits)
        self.set("hardware_error_status", self.get("hardware_error_status") | mask)
        if mask & self.get("shutdown"):
            self.set("torque_enable", 0)
            self.shut_down = True
            self.motion.stop()
        self._publish()

    def _check_conditions(self) -> None:
        volts = round(self.supply_v * 10)
        bits = 0
        if not self.get("min_voltage_limit") <= volts <= self.get("max_voltage_limit"):
            bits |= mx28.HARDWARE_ERRORS["input_voltage"]
        if self.temperature_c > self.get("temperature_limit"):
            bits |= mx28.HARDWARE_ERRORS["overheating"]
        if bits & ~self.get("hardware_error_status"):
            self.inject_hardware_error(bits)

    # motion -------------------------------------------------------------------------------
    def _profile(self) -> tuple[float, float]:
        """(Profile Velocity, Profile Acceleration) in raw units, Profile Velocity never above
        Velocity Limit; 0 keeps its meaning (step / rectangular profile)."""
        pv = min(self.get("profile_velocity"), self.get("velocity_limit"))
        return float(pv), float(self.get("profile_acceleration"))

    def speed_cap(self) -> float:
        """The fastest the motor turns now, ticks/s: the no-load speed at the supply voltage,
        scaled by the PWM limit in force (Goal PWM limits PWM in every mode but PWM mode)."""
        duty = min(abs(self.get("goal_pwm")), self.get("pwm_limit")) / 885.0
        rpm: float = self.spec.no_load_rpm(self.supply_v)
        return rpm / 60.0 * mx28.TICKS_PER_REV * duty

    def advance(self, dt: float, now: float) -> None:
        """Integrate `dt` seconds of motion and refresh the Present* items."""
        self.set("realtime_tick", int(now * 1000) % 32768)
        if (dt > 0.0 and self._rest is not None and self.motion.at_rest
                and self._rest == self._rest_key()):
            return  # at rest, and nothing the model reads has changed: the same items again
        self._check_conditions()
        if dt <= 0.0:
            self._publish()
            return
        if not self.torque:
            self.motion.stop()
        else:
            mode = self.get("operating_mode")
            pv, pa = self._profile()
            if mode in self.position_modes:
                self.motion.step_position(dt, self.speed_cap(), pv, pa)
            elif mode == VELOCITY:
                self.motion.step_velocity(dt, self.get("goal_velocity"), pa, self.speed_cap())
            else:  # PWM: duty sets the no-load speed; the Acceleration Limit as the ramp
                full = self.spec.no_load_rpm(self.supply_v) / 60.0 * mx28.TICKS_PER_REV
                target = self._drive() * full / mx28.VEL_TICKS_PER_UNIT
                self.motion.step_velocity(dt, target, self.get("acceleration_limit"), full)
        self._publish()
        self._rest = self._rest_key() if self.motion.at_rest else None

    def _rest_key(self) -> _RestKey:
        """Everything `advance` reads, but the time: the control table (without the
        Realtime Tick it has just written), the supply, the temperature and the motion's
        position, goal and profile. Equal at two steps of a servo at rest, `advance` would
        write the same values."""
        mem, (start, end, _, _) = self.mem, _layout(self.spec)["realtime_tick"]
        m = self.motion
        return (mem[:start], mem[end:], self.supply_v, self.temperature_c, m.pos, m.goal,
                m.profile_bits)

    def _drive(self) -> float:
        """The duty (-1..1) the motor runs at in the modes without a goal position or
        velocity: Goal PWM over its full scale (PWM mode)."""
        return self.get("goal_pwm") / 885.0

    def _publish_load(self, load: int) -> None:
        """Publish the load model (0.1 % of the stall torque): Present Load on the MX-28."""
        self.set("present_load", load)

    def _publish(self) -> None:
        m = self.motion
        raw_vel = int(round(m.vel / mx28.VEL_TICKS_PER_UNIT))
        moving = abs(raw_vel) > self.get("moving_threshold")
        mode = self.get("operating_mode")
        load = pwm = 0
        if self.torque:
            load = round(m.acc / mx28.ACC_TICKS_PER_UNIT * LOAD_PER_ACC)
            if moving:
                load += int(math.copysign(FRICTION_LOAD, m.vel))
            load = max(-1000, min(1000, load))
            if mode not in self.position_modes and mode != VELOCITY:
                pwm = round(self._drive() * 885.0)
            else:
                limit = min(abs(self.get("goal_pwm")), self.get("pwm_limit"))
                full = self.spec.no_load_rpm(self.supply_v) / 60.0 * mx28.TICKS_PER_REV
                need = 885.0 * m.vel / full if full > 0 else 0.0
                pwm = max(-limit, min(limit, round(need + 0.885 * load)))
        self.set("present_position", round(m.pos))
        self.set("present_velocity", raw_vel)
        self._publish_load(load)
        self.set("present_pwm", pwm)
        self.set("present_input_voltage", round(self.supply_v * 10))
        self.set("present_temperature", round(self.temperature_c))
        self.set("moving", int(moving))
        if mode in self.position_modes and self.torque:
            self.set("position_trajectory", round(m.traj_pos))
            self.set("velocity_trajectory", round(m.traj_vel / mx28.VEL_TICKS_PER_UNIT))
            self.set("moving_status", m.moving_status(self.get("goal_position")))
        else:
            self.set("position_trajectory", round(m.pos))
            self.set("velocity_trajectory", raw_vel)
            self.set("moving_status", 0)
