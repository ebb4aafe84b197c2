"""Angler driver: four Dynamixel MX-28 servos on Protocol 2.0, a Dynamixel servo chain
(app/devices/dynamixel_chain.py: polling, set-up, faults, reboot, pass-through).

What is the angler's own: Present Load (MX-28 (2.0), address 126) is 0.1 % of the stall
torque (the chain's default effort unit), and its end effector is a passive magnet.
"""

from __future__ import annotations

from app.devices.dynamixel_chain import BOOT_WAIT_S, FAULT_REFRESH_S, POWER_CHECK_S
from app.devices.dynamixel_chain import DynamixelChainDriver as _Chain
from app.devices.dynamixel_exchange import DxlRequest
from app.devices.dynamixel_faults import FAULT_BITS, decode_faults, fault_advice
from app.errors import NoGripper

__all__ = ["BOOT_WAIT_S", "FAULT_BITS", "FAULT_REFRESH_S", "POWER_CHECK_S", "AnglerDriver",
           "DxlRequest", "decode_faults", "fault_advice"]


class AnglerDriver(_Chain):
    async def set_gripper(self, value: float) -> None:
        raise NoGripper(f"{self.name} has a passive magnet, not an actuated gripper")
