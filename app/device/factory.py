"""Build an arm's link and driver from its profile. Hardware libraries load only here, on demand,
and only for the link kind the profile names (bleak's backend pattern); the driver and the
simulated device come from the profile's arm type (app/arms)."""

from __future__ import annotations

from app.arms import arm_type
from app.config import ArmProfile
from app.device.driver import Driver
from app.links.base import Link
from app.sim.base import SimDevice
from app.telemetry.hub import TelemetryHub


def make_sim_device(profile: ArmProfile) -> SimDevice:
    """The simulated hardware for a profile (its arm type's simulator)."""
    return arm_type(profile.model).simulator(profile)


def make_link(profile: ArmProfile) -> Link:
    cfg = profile.link
    if cfg.kind == "sim":
        from app.links.sim import SimLink
        from app.sim.world_tap import with_world

        # the device watched by its simulated world (app/sim/world.py: objects, bins, grasp)
        return SimLink(with_world(profile, make_sim_device(profile)), faults=cfg.faults,
                       address=f"sim:{profile.model}", serial_number=cfg.serial_number)
    if cfg.kind == "hid":
        from app.links.hid import HidLink

        return HidLink(vid=cfg.vid, pid=cfg.pid, serial_number=cfg.serial_number,
                       address=cfg.address)
    if cfg.io == "thread":
        from app.links.threaded import ThreadLink

        return ThreadLink(cfg.address, baudrate=cfg.baudrate)
    from app.links.serial import SerialLink

    return SerialLink(cfg.address, baudrate=cfg.baudrate)


def make_driver(profile: ArmProfile, hub: TelemetryHub, link: Link | None = None) -> Driver:
    link = link if link is not None else make_link(profile)
    # an arm type's driver is a Driver (typed as the Actuator it is, so that app.arms does
    # not depend on the driver base for its types: tools/check_cycles.py --types)
    driver = arm_type(profile.model).driver(profile, link, hub)
    if not isinstance(driver, Driver):
        raise TypeError(f"the {profile.model} arm type's driver is not a Driver")
    return driver
