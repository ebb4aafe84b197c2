"""The RBE3001 arm type: a 3-DOF RRR arm on the WPI RBE3001 Nucleo firmware, 64-byte HID
packets (protocol/rbe3001.py). Package: the profile (rbe3001.toml), the kinematics model
(model.py, kinematics/rrr.py), the driver (driver.py), the pass-through routes (api.py); the
simulated firmware stays in app/arms/rbe3001/sim.py."""

from __future__ import annotations

from typing import TYPE_CHECKING

from app.arms.base import ArmType, UsbMatch
from app.arms.rbe3001.model import RrrModel

if TYPE_CHECKING:
    from app.config import ArmProfile
    from app.device.driver import Driver
    from app.links.base import Link
    from app.sim.base import SimDevice
    from app.telemetry.hub import TelemetryHub


def _driver(profile: ArmProfile, link: Link, hub: TelemetryHub) -> Driver:
    from app.arms.rbe3001.driver import Rbe3001Driver

    return Rbe3001Driver(profile, link, hub)


def _simulator(profile: ArmProfile) -> SimDevice:
    from app.arms.rbe3001.sim import Rbe3001Firmware

    return Rbe3001Firmware(profile)


ARM = ArmType(
    name="rbe3001",
    protocol="rbe3001",
    geometry_keys=frozenset({"l1", "l2", "l3"}),
    joints=3,
    model=RrrModel,
    driver=_driver,
    simulator=_simulator,
    routers=("app.arms.rbe3001.api",),
    # the RBE3001 Nucleo firmware's USBHID(64, 64)
    usb=(UsbMatch("hid", 0x3742, 0x0007, "rbe3001"),),
)
