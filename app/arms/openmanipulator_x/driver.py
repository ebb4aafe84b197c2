"""The OpenManipulator-X driver: five XM430-W350-T servos on Protocol 2.0 through a U2D2, a
Dynamixel servo chain (app/arms/dynamixel/servos.py: polling, set-up, faults, reboot,
pass-through). Its own parts:

- Effort: the XM430's item 126 is Present Current (about 2.69 mA a unit, e-manual
  "Present Current(126)"), read as a share of the stall current (2.3 A at 12 V, 4.1 N m:
  "Specifications"), times the stall torque: a linear estimate of the joint torque.
- The gripper: its own servo (the profile's `[gripper] motor_id`, id 15) in current-based
  position mode (operating mode 5, as the e-manual's OpenManipulator-X set-up requires), so
  that the fingers stop on an object at the Goal Current instead of stalling against it.
  It is set up and polled with the joints; 0.0 open .. 1.0 closed maps linearly onto the
  finger travel `[gripper] max` .. `min` (m), and that onto the servo angle by
  `rad_per_m` (ROBOTIS's tool coefficient: -0.015 m a radian).
- Every joint has an absolute encoder within one turn: homed at start, no homing.
"""

from __future__ import annotations

import math
from typing import Any

from app.arms.dynamixel.driver import DynamixelDriver
from app.errors import NoGripper
from protocol import xm430


class OmxDriver(DynamixelDriver):
    effort_per_unit = xm430.CURRENT_A_PER_UNIT / xm430.STALL_CURRENT_A

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        g = self.profile.gripper
        self.gripper_id = g.motor_id if g.actuated else None
        if self.gripper_id is not None:
            self.aux_ids = (self.gripper_id,)
            if g.operating_mode is not None:
                self.aux_modes[self.gripper_id] = g.operating_mode
            self._ticks_per_rad = xm430.TICKS_PER_REV / (2.0 * math.pi)

    def gripper_ticks(self, value: float) -> int:
        """Goal Position (raw) of the gripper servo for 0.0 open .. 1.0 closed."""
        g = self.profile.gripper
        metres = g.max - value * (g.max - g.min)
        return round(g.offset_ticks + metres * g.rad_per_m * self._ticks_per_rad)

    def gripper_value(self, ticks: int) -> float:
        """0.0 open .. 1.0 closed from the gripper servo's Present Position (raw)."""
        g = self.profile.gripper
        metres = (ticks - g.offset_ticks) / self._ticks_per_rad / g.rad_per_m
        return (g.max - metres) / (g.max - g.min)

    async def set_gripper(self, value: float) -> None:
        if self.gripper_id is None:
            raise NoGripper(f"{self.name} has no gripper servo in its profile")
        await self.write_register(self.gripper_id, xm430.TABLE["goal_position"],
                                  self.gripper_ticks(value))

    def _on_aux_polled(self) -> None:
        if self.gripper_id is not None and self.gripper_id in self.aux_ticks:
            self.gripper = round(self.gripper_value(self.aux_ticks[self.gripper_id]), 4)
