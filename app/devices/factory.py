"""Build an arm's link and driver from its profile. Hardware libraries load only here, on demand,
and only for the link kind the profile names (bleak's backend pattern)."""

from __future__ import annotations

from app.config import ArmProfile
from app.devices.base import Driver
from app.links.base import Link
from app.telemetry import TelemetryHub


def make_sim_device(profile: ArmProfile) -> object:
    """The simulated hardware for a profile: the rbe3001 firmware or an MX-28 bus."""
    if profile.model == "rbe3001":
        from app.sim.rbe3001_firmware import Rbe3001Firmware

        return Rbe3001Firmware(profile)
    from app.sim.dynamixel_bus import DynamixelBus

    modes = {int(j.motor_id): j.operating_mode for j in profile.joints  # type: ignore[arg-type]
             if j.operating_mode is not None}
    ids = tuple(int(j.motor_id) for j in profile.joints)  # type: ignore[arg-type]
    return DynamixelBus(ids=ids, baudrate=profile.link.baudrate, operating_modes=modes)


def make_link(profile: ArmProfile) -> Link:
    cfg = profile.link
    if cfg.kind == "sim":
        from app.links.sim import SimLink

        return SimLink(make_sim_device(profile), faults=cfg.faults,  # type: ignore[arg-type]
                       address=f"sim:{profile.model}")
    if cfg.kind == "hid":
        from app.links.hid import HidLink

        return HidLink(vid=cfg.vid, pid=cfg.pid, serial_number=cfg.serial_number,
                       address=cfg.address)
    from app.links.serial import SerialLink

    return SerialLink(cfg.address, baudrate=cfg.baudrate)


def make_driver(profile: ArmProfile, hub: TelemetryHub, link: Link | None = None) -> Driver:
    link = link if link is not None else make_link(profile)
    if profile.model == "rbe3001":
        from app.devices.rbe3001 import Rbe3001Driver

        return Rbe3001Driver(profile, link, hub)
    from app.devices.angler import AnglerDriver

    return AnglerDriver(profile, link, hub)
