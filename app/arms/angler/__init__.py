"""The angler arm type: a PPRP arm (x and y carriages, the t3 arm, the z carriage) of four
Dynamixel MX-28 (2.0) servos on Protocol 2.0 through a U2D2. Package: the profile
(angler.toml), the kinematics model and IK options (model.py, kinematics/pprp.py). Shared
with every Dynamixel arm (app/arms/dynamixel/): the driver, the simulated bus
(app/arms/dynamixel/sim_bus.py) and the pass-through router (app/arms/dynamixel/api.py)."""

from __future__ import annotations

from typing import TYPE_CHECKING

from app.arms import dynamixel
from app.arms.angler.model import AnglerIK, PprpModel
from app.arms.base import ArmType
from protocol import mx28

if TYPE_CHECKING:
    from app.config import ArmProfile
    from app.device.driver import Driver
    from app.links.base import Link
    from app.sim.base import SimDevice
    from app.telemetry.hub import TelemetryHub


def _driver(profile: ArmProfile, link: Link, hub: TelemetryHub) -> Driver:
    from app.arms.dynamixel.driver import DynamixelDriver

    return DynamixelDriver(profile, link, hub)


def _simulator(profile: ArmProfile) -> SimDevice:
    return dynamixel.simulated_bus(profile)


def _check(profile: ArmProfile) -> None:
    missing = [j.name for j in profile.joints if j.motor_id is None]
    if missing:
        raise ValueError(f"angler joints need a Dynamixel motor_id: {missing}")


ARM = ArmType(
    name="angler",
    protocol="dynamixel",
    geometry_keys=frozenset({"r", "h"}),
    joints=4,
    model=PprpModel,
    driver=_driver,
    simulator=_simulator,
    routers=(dynamixel.ROUTER,),
    pose_options=AnglerIK,
    control_table=mx28,
    usb=(dynamixel.U2D2,),
    check=_check,
)
