"""MX-28 (Protocol 2.0 firmware) control table as plain data: name -> address, size, access,
default, unit and valid write range.

Source: ROBOTIS e-manual, https://emanual.robotis.com/docs/en/dxl/mx/mx-28-2/ (model number 30).
EEPROM items (address < 64) are writable only while Torque Enable is 0. `min_raw`/`max_raw`
are the widest valid write range; items whose range depends on another item (Goal Position
within the position limits in position mode, Goal Velocity within Velocity Limit, Goal PWM
within PWM Limit, Profile Acceleration within Acceleration Limit) carry the widest range here
and the device (or simulator) enforces the dependent limit. The Indirect Address/Data items
(168-251, 578-661) are not listed.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

MODEL_NUMBER = 30
E_MANUAL = "https://emanual.robotis.com/docs/en/dxl/mx/mx-28-2/"
#: Present/Goal Position resolution: 4096 ticks per revolution, 0.088 deg per tick
TICKS_PER_REV = 4096
#: Velocity Limit (44) as shipped: 230 (0.229 rpm units, 52.7 rpm, just under the 55 rpm no-load
#: speed at 12 V) from firmware V42; 380 (87 rpm) before it. Sources, ROBOTIS-GIT/emanual:
#: docs/en/dxl/mx/mx-28-2.md, "Control Table of EEPROM Area", Velocity Limit initial value 230
#: at 203f49b5 (the current page's layout) and 380 at 07fe860b (the older layout, before the
#: change); _includes/en/dxl/control_table_vellimit.md (321fd0e5), the item's page: "NOTE: The
#: default value of Velocity Limit has been decreased since Firmware V42." A servo on older
#: firmware keeps 380: the driver reads the item, it never assumes this.
VELOCITY_LIMIT_DEFAULT = 230


@dataclass(frozen=True)
class ControlItem:
    """One control-table item. `scale` is unit per raw count (e.g. 0.088 deg per tick);
    `to_unit` gives raw * scale. `default` is None where the e-manual gives none ('-')."""

    name: str
    address: int
    size: int
    area: Literal["eeprom", "ram"]
    access: Literal["r", "rw"]
    default: int | None
    unit: str | None
    scale: float
    signed: bool
    min_raw: int
    max_raw: int

    @property
    def writable(self) -> bool:
        return self.access == "rw"


_I32 = 2**31 - 1
# name, address, size, access, default, unit, scale, signed, min, max
_ROWS: tuple[tuple[str, int, int, str, int | None, str | None, float, bool, int, int], ...] = (
    ("model_number", 0, 2, "r", 30, None, 1.0, False, 0, 0xFFFF),
    ("model_information", 2, 4, "r", None, None, 1.0, False, 0, 0xFFFFFFFF),
    ("firmware_version", 6, 1, "r", None, None, 1.0, False, 0, 0xFF),
    ("id", 7, 1, "rw", 1, None, 1.0, False, 0, 252),
    ("baud_rate", 8, 1, "rw", 1, None, 1.0, False, 0, 7),
    ("return_delay_time", 9, 1, "rw", 250, "us", 2.0, False, 0, 254),
    ("drive_mode", 10, 1, "rw", 0, None, 1.0, False, 0, 5),
    ("operating_mode", 11, 1, "rw", 3, None, 1.0, False, 0, 16),
    ("secondary_id", 12, 1, "rw", 255, None, 1.0, False, 0, 255),
    ("protocol_version", 13, 1, "rw", 2, None, 1.0, False, 1, 2),
    ("homing_offset", 20, 4, "rw", 0, "deg", 0.088, True, -1_044_479, 1_044_479),
    ("moving_threshold", 24, 4, "rw", 10, "rpm", 0.229, False, 0, 1023),
    ("temperature_limit", 31, 1, "rw", 80, "C", 1.0, False, 0, 100),
    ("max_voltage_limit", 32, 2, "rw", 160, "V", 0.1, False, 95, 160),
    ("min_voltage_limit", 34, 2, "rw", 95, "V", 0.1, False, 95, 160),
    ("pwm_limit", 36, 2, "rw", 885, "percent", 0.113, False, 0, 885),
    ("acceleration_limit", 40, 4, "rw", 32767, "rev/min^2", 214.577, False, 0, 32767),
    # Velocity Limit: 230 (52.7 rpm) from firmware V42, 380 before it (the e-manual's
    # MX-28(2.0) page, "Control Table of EEPROM Area"; VELOCITY_LIMIT_DEFAULT below)
    ("velocity_limit", 44, 4, "rw", 230, "rpm", 0.229, False, 0, 1023),
    ("max_position_limit", 48, 4, "rw", 4095, "deg", 0.088, False, 0, 4095),
    ("min_position_limit", 52, 4, "rw", 0, "deg", 0.088, False, 0, 4095),
    ("shutdown", 63, 1, "rw", 52, None, 1.0, False, 0, 0xFF),
    ("torque_enable", 64, 1, "rw", 0, None, 1.0, False, 0, 1),
    ("led", 65, 1, "rw", 0, None, 1.0, False, 0, 1),
    ("status_return_level", 68, 1, "rw", 2, None, 1.0, False, 0, 2),
    ("registered_instruction", 69, 1, "r", 0, None, 1.0, False, 0, 1),
    ("hardware_error_status", 70, 1, "r", 0, None, 1.0, False, 0, 0xFF),
    ("velocity_i_gain", 76, 2, "rw", 1920, None, 1.0, False, 0, 16383),
    ("velocity_p_gain", 78, 2, "rw", 100, None, 1.0, False, 0, 16383),
    ("position_d_gain", 80, 2, "rw", 0, None, 1.0, False, 0, 16383),
    ("position_i_gain", 82, 2, "rw", 0, None, 1.0, False, 0, 16383),
    ("position_p_gain", 84, 2, "rw", 850, None, 1.0, False, 0, 16383),
    ("feedforward_2nd_gain", 88, 2, "rw", 0, None, 1.0, False, 0, 16383),
    ("feedforward_1st_gain", 90, 2, "rw", 0, None, 1.0, False, 0, 16383),
    ("bus_watchdog", 98, 1, "rw", 0, "ms", 20.0, False, 0, 127),
    ("goal_pwm", 100, 2, "rw", None, "percent", 0.113, True, -885, 885),
    ("goal_velocity", 104, 4, "rw", None, "rpm", 0.229, True, -1023, 1023),
    ("profile_acceleration", 108, 4, "rw", 0, "rev/min^2", 214.577, False, 0, 32767),
    ("profile_velocity", 112, 4, "rw", 0, "rpm", 0.229, False, 0, 32767),
    ("goal_position", 116, 4, "rw", None, "deg", 0.088, True, -1_048_575, 1_048_575),
    ("realtime_tick", 120, 2, "r", None, "ms", 1.0, False, 0, 32767),
    ("moving", 122, 1, "r", 0, None, 1.0, False, 0, 1),
    ("moving_status", 123, 1, "r", 0, None, 1.0, False, 0, 0xFF),
    ("present_pwm", 124, 2, "r", None, "percent", 0.113, True, -885, 885),
    ("present_load", 126, 2, "r", None, "percent", 0.1, True, -1000, 1000),
    ("present_velocity", 128, 4, "r", None, "rpm", 0.229, True, -_I32 - 1, _I32),
    ("present_position", 132, 4, "r", None, "deg", 0.088, True, -_I32 - 1, _I32),
    ("velocity_trajectory", 136, 4, "r", None, "rpm", 0.229, True, -_I32 - 1, _I32),
    ("position_trajectory", 140, 4, "r", None, "deg", 0.088, True, -_I32 - 1, _I32),
    ("present_input_voltage", 144, 2, "r", None, "V", 0.1, False, 0, 0xFFFF),
    ("present_temperature", 146, 1, "r", None, "C", 1.0, False, 0, 0xFF),
)

TABLE: dict[str, ControlItem] = {
    r[0]: ControlItem(r[0], r[1], r[2], "eeprom" if r[1] < 64 else "ram",
                      "rw" if r[3] == "rw" else "r", r[4], r[5], r[6], r[7], r[8], r[9])
    for r in _ROWS
}
BY_ADDRESS: dict[int, ControlItem] = {it.address: it for it in TABLE.values()}
#: one past the last address of the table (the simulator's control-table size)
TABLE_END = max(it.address + it.size for it in TABLE.values())


def item(name: str) -> ControlItem:
    """The item called `name` (snake_case); KeyError naming the close matches otherwise."""
    try:
        return TABLE[name]
    except KeyError:
        key = name.lower().replace(" ", "_")
        if key in TABLE:
            return TABLE[key]
        near = [n for n in TABLE if key in n or n in key]
        hint = f"; did you mean {', '.join(near)}?" if near else ""
        raise KeyError(f"no MX-28 control item {name!r}{hint} (see {E_MANUAL})") from None


def to_unit(it: ControlItem, raw: int) -> float | None:
    """Raw register value in the item's unit (e.g. ticks -> deg), None for unitless items."""
    if it.unit is None:
        return None
    return raw * it.scale


#: Hardware Error Status (70) and Shutdown (63) bits, by name (e-manual, "Shutdown(63)").
#: Bits 1, 6 and 7 are unused (always 0).
HARDWARE_ERRORS: dict[str, int] = {
    "input_voltage": 0x01,
    "overheating": 0x04,
    "motor_encoder": 0x08,
    "electrical_shock": 0x10,
    "overload": 0x20,
}
#: Shutdown (63) default: overheating | electrical shock | overload
SHUTDOWN_DEFAULT = 0x34
#: Moving Status (123) bits (e-manual, "Moving Status(123)")
IN_POSITION = 0x01
PROFILE_ONGOING = 0x02
FOLLOWING_ERROR = 0x08
PROFILE_TYPE_MASK = 0x30
PROFILE_TRAPEZOIDAL, PROFILE_TRIANGULAR, PROFILE_RECTANGULAR, PROFILE_STEP = 0x30, 0x20, 0x10, 0x00
#: No-load speed (rpm) at supply voltage (V), from the e-manual's specifications table
NO_LOAD_RPM: tuple[tuple[float, float], ...] = ((11.1, 50.0), (12.0, 55.0), (14.8, 67.0))


def hardware_error_names(bits: int) -> list[str]:
    """The names of the Hardware Error Status bits set in `bits`, in bit order."""
    return [name for name, bit in sorted(HARDWARE_ERRORS.items(), key=lambda kv: kv[1])
            if bits & bit]


def hardware_error_bits(names: str | list[str] | tuple[str, ...]) -> int:
    """The Hardware Error Status bits of one name or several; ValueError naming the valid
    ones for an unknown name."""
    bits = 0
    for name in [names] if isinstance(names, str) else names:
        key = name.strip().lower().replace(" ", "_").replace("-", "_")
        if key not in HARDWARE_ERRORS:
            raise ValueError(f"no Dynamixel hardware error {name!r}; one of "
                             f"{', '.join(HARDWARE_ERRORS)}")
        bits |= HARDWARE_ERRORS[key]
    return bits


def no_load_rpm(volts: float) -> float:
    """The datasheet no-load speed at a supply voltage: linear between the e-manual's points
    (50 rpm at 11.1 V, 55 at 12 V, 67 at 14.8 V), extended along the end segments, never
    below 0."""
    pts = NO_LOAD_RPM
    k = 0 if volts <= pts[1][0] else 1
    (v0, r0), (v1, r1) = pts[k], pts[k + 1]
    return max(0.0, r0 + (r1 - r0) * (volts - v0) / (v1 - v0))


#: ticks/s per raw velocity unit (0.229 rpm) and ticks/s^2 per raw acceleration unit
#: (214.577 rev/min^2)
VEL_TICKS_PER_UNIT = 0.229 * TICKS_PER_REV / 60.0
ACC_TICKS_PER_UNIT = 214.577 * TICKS_PER_REV / 3600.0
