"""The coupling of a simulated device to its world: a SimDevice that passes every byte to the
device it wraps and, at most every `TAP_PERIOD_S` of simulated time, hands the world what the
simulated hardware holds (joint positions in device ticks, the claw's opening).

What it reads is each simulator's own state, the same numbers the device would report:

- the RBE3001 firmware (app/arms/rbe3001/sim.py): ``position_ticks`` (what GetPIDPosition
  returns) and ``claw`` (0..1);
- a Dynamixel bus (app/arms/dynamixel/sim_bus.py): each joint servo's Present Position (132),
  by the profile's ``motor_id``; an OpenManipulator-X's gripper servo's Present Position turned
  into 0..1 as its driver does (finger travel from ``[gripper]``, e-manual: 4096 ticks a turn).

It runs where the device runs (the control thread, inside the link's write and read): one
reading per period, and a deque append when it differs from the last (an arm at rest adds
nothing), nothing else.

The tap also carries the world's hand (app/sim/hand.py) where the device has servos: while it
moves, the device is run up to the link's time and the hand sets its free joints before the
device answers, so a reply carries where the hand has the arm.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from app.config import ArmProfile
from app.sim.base import SimDevice
from app.sim.hand import Hand
from app.sim.world import TAP_PERIOD_S, World

Reading = tuple[tuple[float, ...], float | None]
_XM430_TICKS_PER_RAD = 4096 / (2 * 3.141592653589793)


def reader_for(profile: ArmProfile, device: Any) -> Callable[[], Reading | None]:
    """A function reading `device`'s joint ticks and claw opening (None: nothing to read now,
    e.g. a servo that does not answer on the bus)."""
    if hasattr(device, "position_ticks") and hasattr(device, "claw"):
        def rbe3001() -> Reading:
            return tuple(device.position_ticks), float(device.claw)
        return rbe3001
    if hasattr(device, "servo"):
        ids = [int(j.motor_id or 0) for j in profile.joints]
        g = profile.gripper
        grip_id = g.motor_id if g.actuated else None

        def bus() -> Reading | None:
            ticks = []
            for i in ids:
                s = device.servo(i)
                if s is None:
                    return None
                ticks.append(float(s.get("present_position")))
            value = None
            if grip_id is not None:
                s = device.servo(grip_id)
                if s is not None:
                    metres = ((s.get("present_position") - g.offset_ticks)
                              / _XM430_TICKS_PER_RAD / g.rad_per_m)
                    value = (g.max - metres) / (g.max - g.min) if g.max != g.min else None
            return tuple(ticks), value
        return bus
    raise TypeError(f"no world reader for a {type(device).__name__}")


class WorldTap:
    """A SimDevice: `device` with its `world` watching. Bytes and timing are the device's.

    Transparent to whoever reaches the device through the link (tests inject faults into the
    simulated firmware or bus as `link.device.<attribute>`): an attribute the tap does not have
    is the device's, read and written. The tap's own `receive` and `advance` stay the tap's
    when replaced (a test that wraps `link.device.receive` wraps the tap's, which calls the
    device's: writing the wrapper into the device would make it call itself)."""

    _OWN = frozenset({"device", "world", "hand", "packetized", "_read", "_next", "_last",
                      "receive", "advance"})
    device: SimDevice

    def __init__(self, device: SimDevice, world: World,
                 read: Callable[[], Reading | None]) -> None:
        object.__setattr__(self, "device", device)
        self.world = world
        #: The hand in the world (None: the device has no servos a hand could move).
        self.hand: Hand | None = Hand(world, device) if hasattr(device, "servo") else None
        self.packetized = device.packetized
        self._read = read
        self._next = float("-inf")
        self._last: Reading | None = None

    def __getattr__(self, name: str) -> Any:
        return getattr(object.__getattribute__(self, "device"), name)

    def __setattr__(self, name: str, value: Any) -> None:
        if name in self._OWN:
            object.__setattr__(self, name, value)
        else:
            setattr(self.device, name, value)

    def receive(self, data: bytes, now: float) -> list[tuple[float, bytes]]:
        self._hand(now)
        out = self.device.receive(data, now)
        self._tap(now)
        return out

    def advance(self, now: float) -> None:
        self.device.advance(now)
        self._hand(now)
        self._tap(now)

    def _hand(self, now: float) -> None:
        hand = self.hand
        if hand is not None and hand.active:
            self.device.advance(now)  # the servos up to now first (torque off: at rest) ...
            hand.apply(now)  # ... then where the hand has them

    def _tap(self, now: float) -> None:
        if now < self._next:
            return
        self._next = now + TAP_PERIOD_S
        reading = self._read()
        if reading is not None and reading != self._last:  # at rest: nothing to replay
            self._last = reading
            self.world.observe(*reading)


def with_world(profile: ArmProfile, device: SimDevice) -> SimDevice:
    """`device` watched by a new World of `profile`'s arm (the device itself where no world
    reader fits it)."""
    try:
        read = reader_for(profile, device)
    except TypeError:
        return device
    return WorldTap(device, World(profile), read)


def world_of(device: object) -> World | None:
    """The world watching a link's simulated device, or None (a real link, or no world)."""
    return device.world if isinstance(device, WorldTap) else None


def hand_of(device: object) -> Hand | None:
    """The hand in the world of a link's simulated device, or None (a real link, no world, or
    a device without servos)."""
    return device.hand if isinstance(device, WorldTap) else None
