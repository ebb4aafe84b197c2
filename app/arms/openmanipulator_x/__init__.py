"""The OpenManipulator-X arm type (ROBOTIS RM-X52-TNM): four revolute joints and a gripper
on five Dynamixel XM430-W350-T servos, Protocol 2.0 through a U2D2. Package: the profile
(openmanipulator_x.toml, citing the ROBOTIS e-manual), the kinematics model (model.py,
kinematics/omx.py, with the wrist's pitch), the driver (driver.py, a Dynamixel servo chain
with the gripper servo) and the simulated bus of XM430s (protocol/xm430.py's control table,
app/arms/dynamixel/sim_xm430.py). Shared with every Dynamixel arm (app/arms/dynamixel.py): the
pass-through router (app/arms/dynamixel/api.py, here on the XM430 table) and the U2D2's USB ids.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from app.arms import dynamixel
from app.arms.base import ArmType
from app.arms.openmanipulator_x.model import GEOMETRY_KEYS, OmxModel
from protocol import xm430

if TYPE_CHECKING:
    from app.config import ArmProfile
    from app.device.driver import Driver
    from app.links.base import Link
    from app.sim.base import SimDevice
    from app.telemetry.hub import TelemetryHub


def _driver(profile: ArmProfile, link: Link, hub: TelemetryHub) -> Driver:
    from app.arms.openmanipulator_x.driver import OmxDriver

    return OmxDriver(profile, link, hub)


def _simulator(profile: ArmProfile) -> SimDevice:
    """The joints' and the gripper's servos, every one an XM430-W350, in their modes."""
    from app.arms.dynamixel.sim_xm430 import Xm430Servo

    return dynamixel.simulated_bus(profile, Xm430Servo)


def _check(profile: ArmProfile) -> None:
    missing = [j.name for j in profile.joints if j.motor_id is None]
    if missing:
        raise ValueError(f"openmanipulator_x joints need a Dynamixel motor_id: {missing}")
    if any(j.kind != "revolute" for j in profile.joints):
        raise ValueError("openmanipulator_x joints are all revolute")
    g = profile.gripper
    if g.actuated and g.motor_id is None:
        raise ValueError("openmanipulator_x: an actuated gripper needs its motor_id")


ARM = ArmType(
    name="openmanipulator_x",
    protocol="dynamixel",
    geometry_keys=GEOMETRY_KEYS,
    joints=4,
    model=OmxModel,
    driver=_driver,
    simulator=_simulator,
    routers=(dynamixel.ROUTER,),
    has_pitch=True,
    control_table=xm430,
    usb=(dynamixel.U2D2,),
    check=_check,
    default_server=False,  # API.md: the default server hosts the rbe3001 and the angler
)
