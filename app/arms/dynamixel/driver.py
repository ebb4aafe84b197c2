"""Dynamixel driver: a chain of Dynamixel servos on Protocol 2.0 (protocol/dynamixel.py), one
per joint (the profile's `motor_id`s): the angler's as it is, and the base for any other arm
of Dynamixel servos (the OpenManipulator-X's adds its gripper servo and its effort unit).

The work is in chain.py (set-up, poll, faults, power check, reboot), exchange.py (the bus
exchange and the pass-through) and faults.py (Hardware Error Status bits and advice); this
class adds the end effector of an arm with no actuated gripper. Present Load (MX-28 (2.0),
address 126) is read as 0.1 % of the stall torque (the chain's default effort unit).
"""

from __future__ import annotations

from app.arms.dynamixel.exchange import DxlRequest
from app.arms.dynamixel.faults import FAULT_BITS, decode_faults, fault_advice
from app.arms.dynamixel.servos import (
    BOOT_WAIT_S,
    FAULT_REFRESH_S,
    POWER_CHECK_S,
    DynamixelChainDriver,
)
from app.errors import NoGripper

__all__ = ["BOOT_WAIT_S", "FAULT_BITS", "FAULT_REFRESH_S", "POWER_CHECK_S", "DxlRequest",
           "DynamixelChainDriver", "DynamixelDriver", "decode_faults", "fault_advice"]


class DynamixelDriver(DynamixelChainDriver):
    async def set_gripper(self, value: float) -> None:
        raise NoGripper(f"{self.name} has a {self.profile.gripper.kind} end effector, not an "
                        "actuated gripper")
