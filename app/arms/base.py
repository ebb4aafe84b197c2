"""The arm-type contract: what one package under app/arms/<name>/ gives the core.

An arm type is a frozen :class:`ArmType` that the package's ``__init__.py`` names ``ARM``;
the registry (app/arms/__init__.py) imports the package the first time the type is asked for.
The core (service, motion, api, envelope, telemetry, dashboard, config, discovery) reaches an
arm type only through this object and the :class:`KinematicsModel` it builds; it never names
one.

Keep a package's ``__init__.py`` light: it builds ``ARM`` and imports its driver, simulator
and routers inside the factory functions (bleak's backend pattern), so that loading a profile
or the registry does not load serial, HID or FastAPI code it does not need, and so that no
import cycle runs through app/arms (``make lint`` checks).

How to add an arm type (docs/architecture.md says it at length):

1. ``app/arms/<name>/__init__.py`` with ``ARM = ArmType(...)``; its profile(s) as
   ``app/arms/<name>/*.toml`` (``model = "<name>"``); ``model.py`` with a
   :class:`KinematicsModel` subclass binding the pure maths in ``kinematics/``;
   the driver (a ``app.device.driver.Driver``) and the simulator (a device behind SimLink,
   the same bytes as the hardware) where the package or app/sim/ keeps them.
2. One line in ``ARM_TYPES`` (app/arms/__init__.py).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Literal

from pydantic import BaseModel

from app.arms.model import Chain, ChainStep, KinematicsModel, Solution, chain_points

if TYPE_CHECKING:
    from app.config import ArmProfile
    from app.device.actuator import Actuator
    from app.links.base import Link
    from app.sim.base import SimDevice
    from app.telemetry.hub import TelemetryHub

__all__ = ["ArmType", "Chain", "ChainStep", "KinematicsModel", "Solution", "UsbMatch",
           "chain_points"]


@dataclass(frozen=True)
class UsbMatch:
    """A USB id pair that `armserver devices` reports as this arm type's hardware: ``label``
    is what the listing shows (e.g. "rbe3001", "dynamixel-u2d2"); ``ftdi_latency``: an FTDI
    serial adapter whose latency timer should be 1 ms (the listing warns where it is not)."""

    kind: Literal["hid", "serial"]
    vid: int
    pid: int
    label: str
    ftdi_latency: bool = False


@dataclass(frozen=True)
class ArmType:
    """One arm type. Every callable is called with a validated profile of this type."""

    #: The registry key and every profile's ``model`` (e.g. "rbe3001").
    name: str
    #: What the arm speaks, ``Capabilities.protocol`` ("rbe3001", "dynamixel"); the
    #: pass-through routers check it with ``ArmService.require_protocol``.
    protocol: str
    #: The geometry keys (metres) the model reads from ``[geometry]``.
    geometry_keys: frozenset[str]
    #: How many joints a profile of this type has (the gripper is not a joint).
    joints: int
    #: ``model(profile)``: the kinematics model (see app/arms/model.py).
    model: Callable[[ArmProfile], KinematicsModel]
    #: ``driver(profile, link, hub)``: the owner task of the arm's link (app/device/driver.py).
    driver: Callable[[ArmProfile, Link, TelemetryHub], Actuator]
    #: ``simulator(profile)``: the simulated hardware a ``kind = "sim"`` link talks to (a
    #: SimDevice answering the same bytes as the real device).
    simulator: Callable[[ArmProfile], SimDevice]
    #: Modules whose ``router`` (a FastAPI APIRouter under /arms/{arm}/...) the app mounts for
    #: this type: its pass-through routes. Shared between types of one protocol (the
    #: Dynamixel router serves every Dynamixel arm); each mounted once however many types
    #: name it. Module paths, imported when the app is built.
    routers: tuple[str, ...] = ()
    #: Arm-specific IK options read from move/pose and inverse requests (fields of the same
    #: names there), or None: the model gets an instance, or None when none is given.
    pose_options: type[BaseModel] | None = None
    #: The arm has a wrist: poses carry `pitch` (API.md "Wrist pitch"); equal to its model's
    #: ``has_pitch`` (a test holds them equal).
    has_pitch: bool = False
    #: The servos' control table, for the Dynamixel pass-through router: a module shaped as
    #: protocol/mx28.py (``item(name)``, ``to_unit(item, raw)``, ``TABLE``); None elsewhere.
    control_table: Any = None
    #: USB ids `armserver devices` recognises as this type's hardware.
    usb: tuple[UsbMatch, ...] = ()
    #: Extra profile checks beyond geometry keys and joint count: raise ValueError.
    check: Callable[[ArmProfile], None] | None = field(default=None, repr=False)
    #: The default server (no config file) hosts this type's built-in profiles (API.md: the
    #: rbe3001 and the angler); False: only a config naming them does.
    default_server: bool = True

    def validate(self, profile: ArmProfile) -> None:
        """Raise ValueError where a profile does not fit this type (called by
        app/arms/loading.py check_profile)."""
        missing = self.geometry_keys - set(profile.geometry)
        if missing:
            raise ValueError(f"{self.name} geometry needs {sorted(missing)}")
        if len(profile.joints) != self.joints:
            raise ValueError(f"{self.name} has {self.joints} joints, profile gives "
                             f"{len(profile.joints)}")
        if self.check is not None:
            self.check(profile)

    def options(self, request: BaseModel) -> BaseModel | None:
        """The arm's IK options taken from a request's fields of the same names (None where
        the type has none or the request gives none of them)."""
        if self.pose_options is None:
            return None
        given: dict[str, Any] = {
            k: getattr(request, k) for k in self.pose_options.model_fields
            if getattr(request, k, None) is not None}
        return self.pose_options.model_validate(given) if given else None
