"""XM430-W350 (Protocol 2.0) control table as plain data, with the types of :mod:`protocol.mx28`.

Source: ROBOTIS e-manual, https://emanual.robotis.com/docs/en/dxl/x/xm430-w350/ (model number
1020): sections "Specifications" (stall torque, no-load speed), "Control Table of EEPROM Area",
"Control Table of RAM Area" and the item pages under "Control Table Description" (units and
ranges: Current Limit(38) and Goal Current(102) about 2.69 mA, 0 ~ 1193). The OpenManipulator-X
(RM-X52-TNM) is built from these servos.

The layout is the MX-28(2.0)'s with three differences that matter: Current Limit (38) in the
EEPROM, Goal Current (102) and Present Current (126, where the MX-28 has Present Load); the
Operating Mode also takes 0 (current) and 5 (current-based position). Defaults differ too
(Velocity Limit 200, i.e. 45.8 rpm, the 46 rpm no-load speed at 12 V, from firmware V42, 350
before it; Position P Gain 800). Sources, ROBOTIS-GIT/emanual docs/en/dxl/x/xm430-w350.md,
"Control Table of EEPROM Area": 200 at 08551725 (the current layout, with "Default Value"), 350
at 07fe860b (the older one); the item's page says the default "has been decreased since
Firmware V42". 265, which issue 24 quoted, is the XL430-W250's (docs/en/dxl/x/xl430-w250*.md),
not this servo's. As in
:mod:`protocol.mx28`, items whose range depends on another item carry the widest range and
the device (or simulator) enforces the dependent limit (Goal Current within Current Limit,
among the others); Indirect Address/Data are not listed.
"""

from __future__ import annotations

import math

from protocol.mx28 import (
    ACC_TICKS_PER_UNIT,
    FOLLOWING_ERROR,
    HARDWARE_ERRORS,
    IN_POSITION,
    PROFILE_ONGOING,
    SHUTDOWN_DEFAULT,
    TICKS_PER_REV,
    VEL_TICKS_PER_UNIT,
    ControlItem,
    hardware_error_bits,  # the X series has the MX-28 (2.0)'s Hardware Error Status bits
    hardware_error_names,
)

__all__ = [
    "ACC_TICKS_PER_UNIT", "BY_ADDRESS", "CURRENT_A_PER_UNIT", "E_MANUAL", "FOLLOWING_ERROR",
    "HARDWARE_ERRORS", "IN_POSITION", "MODEL_NUMBER", "NO_LOAD_RPM", "OPERATING_MODES",
    "PROFILE_ONGOING", "SHUTDOWN_DEFAULT", "STALL_TORQUE_NM", "TABLE", "TABLE_END",
    "TICKS_PER_REV", "VEL_TICKS_PER_UNIT", "ControlItem", "hardware_error_bits",
    "hardware_error_names", "item", "no_load_rpm", "rad_per_tick", "rad_s_per_unit",
    "to_unit",
]

MODEL_NUMBER = 1020
E_MANUAL = "https://emanual.robotis.com/docs/en/dxl/x/xm430-w350/"
#: Current Limit / Goal Current / Present Current unit: about 2.69 mA
CURRENT_A_PER_UNIT = 0.00269
#: Operating Mode (11) values: current, velocity, position, extended position,
#: current-based position, PWM
OPERATING_MODES = {0: "current", 1: "velocity", 3: "position", 4: "extended_position",
                   5: "current_based_position", 16: "pwm"}

_I32 = 2**31 - 1
# name, address, size, access, default, unit, scale, signed, min, max
_ROWS: tuple[tuple[str, int, int, str, int | None, str | None, float, bool, int, int], ...] = (
    ("model_number", 0, 2, "r", 1020, None, 1.0, False, 0, 0xFFFF),
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
    ("current_limit", 38, 2, "rw", 1193, "mA", 2.69, False, 0, 1193),
    ("acceleration_limit", 40, 4, "rw", 32767, "rev/min^2", 214.577, False, 0, 32767),
    ("velocity_limit", 44, 4, "rw", 200, "rpm", 0.229, False, 0, 1023),  # e-manual: 200 (V42+)
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
    ("position_p_gain", 84, 2, "rw", 800, None, 1.0, False, 0, 16383),
    ("feedforward_2nd_gain", 88, 2, "rw", 0, None, 1.0, False, 0, 16383),
    ("feedforward_1st_gain", 90, 2, "rw", 0, None, 1.0, False, 0, 16383),
    ("bus_watchdog", 98, 1, "rw", 0, "ms", 20.0, False, 0, 127),
    ("goal_pwm", 100, 2, "rw", None, "percent", 0.113, True, -885, 885),
    ("goal_current", 102, 2, "rw", None, "mA", 2.69, True, -1193, 1193),
    ("goal_velocity", 104, 4, "rw", None, "rpm", 0.229, True, -1023, 1023),
    ("profile_acceleration", 108, 4, "rw", 0, "rev/min^2", 214.577, False, 0, 32767),
    ("profile_velocity", 112, 4, "rw", 0, "rpm", 0.229, False, 0, 32767),
    ("goal_position", 116, 4, "rw", None, "deg", 0.088, True, -1_048_575, 1_048_575),
    ("realtime_tick", 120, 2, "r", None, "ms", 1.0, False, 0, 32767),
    ("moving", 122, 1, "r", 0, None, 1.0, False, 0, 1),
    ("moving_status", 123, 1, "r", 0, None, 1.0, False, 0, 0xFF),
    ("present_pwm", 124, 2, "r", None, "percent", 0.113, True, -885, 885),
    ("present_current", 126, 2, "r", None, "mA", 2.69, True, -1193, 1193),
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

#: No-load speed (rpm) and stall torque (N m) at supply voltage (V), "Specifications"
NO_LOAD_RPM: tuple[tuple[float, float], ...] = ((11.1, 43.0), (12.0, 46.0), (14.8, 57.0))
STALL_TORQUE_NM: tuple[tuple[float, float], ...] = ((11.1, 3.8), (12.0, 4.1), (14.8, 4.8))
#: stall current (A) at 12 V, "Specifications" (4.1 N m @ 12.0 V, 2.3 A)
STALL_CURRENT_A = 2.3


def item(name: str) -> ControlItem:
    """The item called `name` (snake_case); KeyError naming the close matches otherwise."""
    key = name.lower().replace(" ", "_")
    if key in TABLE:
        return TABLE[key]
    near = [n for n in TABLE if key in n or n in key]
    hint = f"; did you mean {', '.join(near)}?" if near else ""
    raise KeyError(f"no XM430-W350 control item {name!r}{hint} (see {E_MANUAL})")


def to_unit(it: ControlItem, raw: int) -> float | None:
    """Raw register value in the item's unit (ticks -> deg, 2.69 mA...), None if unitless."""
    return None if it.unit is None else raw * it.scale


def _interp(pts: tuple[tuple[float, float], ...], volts: float) -> float:
    k = 0 if volts <= pts[1][0] else 1
    (v0, r0), (v1, r1) = pts[k], pts[k + 1]
    return max(0.0, r0 + (r1 - r0) * (volts - v0) / (v1 - v0))


def no_load_rpm(volts: float) -> float:
    """The datasheet no-load speed at a supply voltage: linear between the e-manual's points
    (43 rpm at 11.1 V, 46 at 12 V, 57 at 14.8 V), extended along the end segments, >= 0."""
    return _interp(NO_LOAD_RPM, volts)


def rad_per_tick() -> float:
    """Goal/Present Position resolution in radians (2 pi / 4096, the 0.088 deg of the table)."""
    return 2.0 * math.pi / TICKS_PER_REV


def rad_s_per_unit() -> float:
    """Velocity items' unit (0.229 rpm) in rad/s."""
    return 0.229 * 2.0 * math.pi / 60.0
