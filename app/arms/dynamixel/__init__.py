"""What every arm of Dynamixel Protocol 2.0 servos shares, for its package to use: the driver
(driver.py, `DynamixelDriver`: one servo per joint), the simulated bus, the U2D2 adapter's
USB ids and the pass-through router's module. Not an arm type itself (not in ARM_TYPES);
nothing here names one."""

from __future__ import annotations

from typing import TYPE_CHECKING

from app.arms.base import UsbMatch

if TYPE_CHECKING:
    from app.arms.dynamixel.sim_bus import DynamixelBus
    from app.arms.dynamixel.sim_mx28 import Mx28Servo
    from app.config import ArmProfile
    from app.sim.base import SimDevice

#: The Dynamixel pass-through routes (generic, parameterised by the arm's control table).
ROUTER = "app.arms.dynamixel.api"
#: The ROBOTIS U2D2 (FTDI FT232H); its latency timer defaults to 16 ms, ROBOTIS says 1 ms.
U2D2 = UsbMatch("serial", 0x0403, 0x6014, "dynamixel-u2d2", ftdi_latency=True)


def simulated_bus(profile: ArmProfile, servo: type[Mx28Servo] | None = None) -> SimDevice:
    """A simulated bus holding the profile's servos (its joints' `motor_id`s, then an actuated
    gripper's) at the link's baud rate, in their operating modes; `servo` is the servo class
    of them all (default MX-28, e.g. an XM430 class). The joints that fall without torque
    fall on it too (app/arms/dynamixel/sim_gravity.py)."""
    from app.arms.dynamixel.sim_bus import DynamixelBus

    modes = {int(j.motor_id): j.operating_mode for j in profile.joints
             if j.motor_id is not None and j.operating_mode is not None}
    ids = tuple(int(j.motor_id) for j in profile.joints if j.motor_id is not None)
    g = profile.gripper
    if g.actuated and g.motor_id is not None and int(g.motor_id) not in ids:
        ids += (int(g.motor_id),)
        if g.operating_mode is not None:
            modes[int(g.motor_id)] = g.operating_mode
    models = None if servo is None else dict.fromkeys(ids, servo)
    bus = DynamixelBus(ids=ids, baudrate=profile.link.baudrate, operating_modes=modes,
                       models=models)
    _start_within_limits(profile, bus)
    if any(j.falls_without_torque for j in profile.joints):
        from app.arms.dynamixel.sim_gravity import Gravity

        bus.gravity = Gravity(profile, bus)
    return bus


def _start_within_limits(profile: ArmProfile, bus: DynamixelBus) -> None:
    """A simulated servo starts mid-turn (tick 2048); a joint whose limits exclude that (the
    angler's theta3, 0 at tick 0 as the design's MATLAB has it) starts at its home pose."""
    from app.arms import model_for

    if profile.home is None:
        return
    tr = model_for(profile).transmission
    mid = tr.from_ticks([2048.0] * len(profile.joints))
    home = tr.to_ticks(list(profile.home))
    for k, j in enumerate(profile.joints):
        s = bus.servo(int(j.motor_id)) if j.motor_id is not None else None
        if s is not None and not j.min <= float(mid[k]) <= j.max:
            s.pos = float(home[k])
