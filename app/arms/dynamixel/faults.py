"""Dynamixel hardware faults as the driver reports them: the Hardware Error Status bits (the
MX-28 (2.0) and X series share them, e-manual address 70) with what a lab should do.

A status whose error byte has only the Alert bit (0x80) set is a valid reply; the Alert bit
says "read Hardware Error Status (70)". Only REBOOT clears a hardware error.
"""

from __future__ import annotations

from protocol import mx28

#: Hardware Error Status bits (e-manual MX-28 (2.0) / XM430-W350, address 70) and advice.
FAULT_BITS: dict[int, tuple[str, str]] = {
    0: ("input_voltage", "check the supply: the input voltage left the servo's limits"),
    2: ("overheating", "let the servo cool down and reduce its load"),
    3: ("motor_encoder", "the servo's encoder failed: check the servo, it may need replacing"),
    4: ("electrical_shock", "check the wiring and the supply for shorts"),
    5: ("overload", "remove the load or obstruction (a jammed screw, an end stop)"),
}


def decode_faults(raw: int) -> list[str]:
    """Names of the Hardware Error Status bits set in `raw` (unknown bits as `bitN`)."""
    known = mx28.hardware_error_names(raw)
    return known + [f"bit{b}" for b in range(8) if raw >> b & 1 and b not in FAULT_BITS]


def fault_advice(dxl_id: int, raw: int, arm: str, falls: str | None = None) -> str:
    """What to do about servo `dxl_id`'s Hardware Error Status `raw`; `falls`: the name of its
    joint where gravity moves it without torque (the profile's `falls_without_torque`: the
    reboot asks whether its load is supported while the servo still holds torque)."""
    hints = [FAULT_BITS[b][1] for b in FAULT_BITS if raw >> b & 1]
    load = ("" if falls is None else f"; {falls} falls without torque: rest or hold its load, "
            'and say so with {"load_supported": true} if the servo still holds torque')
    return ("; ".join(hints) + "; " if hints else "") + (
        f"then clear it with POST /api/v1/arms/{arm}/dynamixel/{dxl_id}/reboot (only a reboot "
        f"clears a hardware error; multi-turn joints then need homing again{load})")
