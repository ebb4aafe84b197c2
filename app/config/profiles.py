"""Arm profiles: the pydantic models of a profile (link, joints, gripper, force, limits,
safety envelope) and their own checks. Plain data: what the arm type named by `model` asks of
a profile (geometry keys, joint count) is checked where profiles are read
(app/arms/loading.py `check_profile`), so this module imports no arm type."""

from __future__ import annotations

import math
from typing import Literal

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    ValidationError,
    field_validator,
    model_validator,
)


class ConfigError(ValueError):
    """A config file or profile that cannot be used; the message says what is wrong, where,
    and (for an unknown profile) which profiles are built in. `armserver serve` prints it and
    exits 2, no traceback."""


def invalid_config(exc: ValidationError, where: str, unknown: str | None = None) -> ConfigError:
    """A `ConfigError` listing each invalid value of `exc` by its place, under `where` (the
    file and table). `unknown`, where given, says what an unknown key is not (e.g. "not a
    camera setting") instead of pydantic's "Extra inputs are not permitted"."""
    lines = [f"{where}: {exc.error_count()} invalid value(s):"]
    for e in exc.errors():
        loc = ".".join(str(p) for p in e["loc"]) or "(top level)"
        what = (f"unknown key ({unknown})" if unknown is not None
                and e["type"] == "extra_forbidden" else e["msg"])
        lines.append(f"  {loc}: {what}")
    return ConfigError("\n".join(lines))


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


class FaultConfig(_Strict):
    """Fault injection on a simulated link (fractions are probabilities per reply)."""

    drop: float = Field(0.0, ge=0.0, le=1.0, description="fraction of replies dropped")
    corrupt: float = Field(0.0, ge=0.0, le=1.0,
                           description="fraction of replies with a byte flipped")
    latency_s: float = Field(0.0, ge=0.0, le=5.0, description="extra delay before each reply, s")
    disconnect_after_s: float | None = Field(
        None, ge=0.0, description="drop the link this long after it opens (None: never)"
    )
    reconnect_after_s: float = Field(0.5, ge=0.0, description="how long a disconnect lasts, s")


class LinkConfig(_Strict):
    kind: Literal["sim", "hid", "serial"] = "sim"
    address: str = Field(
        "", description="serial URL (/dev/ttyUSB0, socket://host:port) or hidraw path")
    vid: int | None = None
    pid: int | None = None
    serial_number: str | None = None
    baudrate: int = 1_000_000
    io: Literal["thread", "asyncio"] = Field(
        "thread", description="serial only: `thread` polls on the schedule on the link's own "
        "thread while the arm's loop waits, a poll's request and reply in one blocking call, "
        "replies handed over in batches (app/links/threaded.py, issue 27: less CPU a sample "
        "at rest); `asyncio` polls on the control loop (pyserial-asyncio)")
    timeout_s: float = Field(0.05, gt=0.0, le=10.0, description="per-request reply timeout, s")
    poll_hz: float = Field(100.0, gt=0.0, le=2000.0)
    control_hz: float = Field(100.0, gt=0.0, le=1000.0)
    queue_size: int = Field(64, ge=1, le=10_000)
    faults: FaultConfig = Field(default_factory=FaultConfig)
    homed_at_start: bool = Field(
        False, description="the joints that need homing start homed: true only for a device "
        "that starts at a known pose (the built-in simulated config); a real multi-turn joint "
        "does not know where it is after a power cycle")
    return_delay_us: float | None = Field(
        None, ge=0.0, le=508.0, description="Dynamixel only: the servos' Return Delay Time (9), "
        "us (e-manual: units of 2 us, default 250 = 500 us), written at set-up where it differs "
        "and the servo's torque is off (after power-on; an EEPROM write needs torque off, and "
        "the driver never switches it off just for this); None leaves the servos' own value")
    sim_echo: bool = Field(False, description="rbe3001 simulator only: reply as firmware builds "
                           "that echo the request's unwritten floats, instead of zeroing them as "
                           "PidServer.cpp does (the default)")
    calibrated_at_start: bool | None = Field(
        None, description="the joints the profile marks `zero_known = false` start calibrated: "
        "None (the default) for a simulated link (`kind = \"sim\"`: its zero is the "
        "simulator's) and not for a real one; false makes a simulator start like hardware")
    sim_firmware: Literal["status", "stock_99", "stock_silent"] = Field(
        "status", description="rbe3001 simulator only: the firmware build: `status` has the "
        "STATUS server (38); `stock_99` answers STATUS with error 99 and `stock_silent` not at "
        "all, as builds without it (RBE3001_nucleo_firmware: no server registered for the id)")
    sim_power_on_pose: str | None = Field(
        None, description="rbe3001 simulator only: the arm is powered on in this calibration "
        "pose (a name in the profile's `calibration_poses`) and the firmware zeroes its "
        "encoders there, as RBE3001_nucleo_firmware's src/main.cpp does (`ZeroPID()` at "
        "start-up); None: the encoders read the profile's offsets (a calibrated arm)")
    sim_gain_claw_reply: Literal["zeros", "echo", "silent", "other"] = Field(
        "zeros", description="rbe3001 simulator only: what SET_GAIN (39) and SET_CLAW (40) "
        "answer: zeros (PidServer's reply buffer), the echo, nothing (the design document: "
        "they \"do not provide any return values\"), or other bytes")


class JointConfig(_Strict):
    name: str
    kind: Literal["revolute", "prismatic"]
    min: float
    max: float
    max_velocity: float = Field(gt=0.0, description="rad/s or m/s")
    max_acceleration: float = Field(gt=0.0, description="rad/s^2 or m/s^2")
    max_jerk: float = Field(gt=0.0, description="rad/s^3 or m/s^3")
    motor_id: int | None = Field(None, ge=0, le=252,
                                 description="Dynamixel id, where the arm has one")
    ticks_per_rev: int = 4096
    offset_ticks: float = 0.0
    sign: Literal[1, -1] = 1
    lead_m: float | None = Field(None, gt=0.0,
                                 description="metres per motor revolution (prismatic)")
    operating_mode: int | None = None
    stall_torque_nm: float | None = Field(
        None, gt=0.0, description="motor stall torque, N m (Dynamixel Present Load is 0.1 % of it)"
    )
    needs_homing: bool = Field(False, description="the joint's zero is lost at power-up (a "
                               "multi-turn screw or winch): moves wait for POST /home")
    min_kp: float | None = Field(
        None, ge=0.0, description="rbe3001 SET_GAIN: the least kp (firmware units) accepted for "
        "this joint through pass-through unless the profile allows raw access: with no "
        "proportional gain the joint holds nothing (422 `out_of_range` below it)")
    max_kp_ki: float | None = Field(
        None, gt=0.0, description="rbe3001 SET_GAIN: the largest kp + ki (firmware units) "
        "accepted for this joint through pass-through unless the profile allows raw access: "
        "the firmware's integral is the error's running mean, so at rest ki adds to kp, and "
        "a stiffer loop chatters (422 `out_of_range` above it)")
    falls_without_torque: bool = Field(
        False, description="gravity moves the joint once its servo's torque is off (the "
        "angler's z winch, an OpenManipulator-X's shoulder, elbow and wrist): pass-through "
        "torque off, and a reboot while its servo holds torque, are 409 `in_use` unless the "
        "profile allows raw access (a reboot also with `load_supported`)")
    settle_tolerance: float | None = Field(
        None, gt=0.0, description="rad or m: a motion is done when the joint is this close to "
        "where it was sent (default: 8 encoder ticks)")
    zero_known: bool = Field(
        True, description="the hardware knows this joint's zero (an absolute encoder read "
        "against a fixed mark, a servo set up to the profile); false where the zero is wherever "
        "the board was powered on or the horn was fitted (the rbe3001's three; the angler's "
        "theta3): on a real link the joint starts not calibrated and a move waits for "
        "POST /calibration (the offset found is stored under the hardware's identity)")

    @model_validator(mode="after")
    def _check(self) -> JointConfig:
        if self.min >= self.max:
            raise ValueError(f"joint {self.name}: min must be below max")
        if self.kind == "prismatic" and self.lead_m is None:
            raise ValueError(f"joint {self.name}: a prismatic joint needs lead_m")
        return self


class GripperConfig(_Strict):
    kind: Literal["none", "claw", "magnet"] = "none"
    # A claw on its own servo (a Dynamixel on the arm's bus); unset for one the arm's
    # controller drives (the rbe3001's claw).
    motor_id: int | None = Field(None, ge=0, le=252, description="the gripper's servo id")
    operating_mode: int | None = Field(None, description="the gripper servo's operating mode")
    min: float = Field(0.0, description="finger travel when closed (1.0), m")
    max: float = Field(0.0, description="finger travel when open (0.0), m")
    rad_per_m: float = Field(1.0, description="servo angle per metre of finger travel")
    offset_ticks: float = Field(2048.0, description="servo ticks at zero travel")

    @property
    def actuated(self) -> bool:
        return self.kind == "claw"


class ForceConfig(_Strict):
    """Strain gauge calibration, per joint: torque = k * adc + y (the published student form;
    its units are not stated, the server reads the result as N m). Either `k` and `y`, or the
    equivalent `adc_scale` (= k) and `adc_offset` (= -y / k): tau = scale * (adc - offset).
    `calibrated` false marks placeholder constants: the arm detail then says the torques and
    tip force are not a measurement."""

    k: list[float] | None = None
    y: list[float] | None = None
    adc_scale: list[float] | None = None
    adc_offset: list[float] | None = None
    calibrated: bool = False
    note: str = ""

    @model_validator(mode="after")
    def _forms(self) -> ForceConfig:
        if self.k is not None and self.y is not None:  # k and y win where both forms are given
            if len(self.k) != len(self.y) or any(v == 0.0 for v in self.k):
                raise ValueError("force: k and y need one entry per joint, k nonzero")
            self.adc_scale = list(self.k)
            self.adc_offset = [-b / a for a, b in zip(self.k, self.y, strict=True)]
        elif self.adc_scale is not None and self.adc_offset is not None:
            if len(self.adc_scale) != len(self.adc_offset):
                raise ValueError("force: adc_scale and adc_offset need one entry per joint")
            self.k = list(self.adc_scale)
            self.y = [-a * o for a, o in zip(self.adc_scale, self.adc_offset, strict=True)]
        else:
            raise ValueError("force: give k and y (torque = k * adc + y) per joint")
        for v in (*self.k, *self.y):
            if not math.isfinite(v):
                raise ValueError("force: calibration constants must be finite")
        return self

    @property
    def scale(self) -> list[float]:
        return list(self.adc_scale or ())

    @property
    def offset(self) -> list[float]:
        return list(self.adc_offset or ())


class CartesianLimits(_Strict):
    """Tip limits for straight-line moves."""

    max_velocity: float = Field(0.1, gt=0.0, description="m/s")
    max_acceleration: float = Field(0.5, gt=0.0, description="m/s^2")
    max_jerk: float = Field(5.0, gt=0.0, description="m/s^3")
    line_tolerance: float = Field(0.005, gt=0.0, description="how far the measured tip may "
                                  "stray from a line move's segment, m (reported, tested)")


class Point3(_Strict):
    """A point in an arm's base frame, m (within 10 m of the base: no arm here reaches further)."""

    x: float = Field(ge=-10.0, le=10.0, strict=True)
    y: float = Field(ge=-10.0, le=10.0, strict=True)
    z: float = Field(ge=-10.0, le=10.0, strict=True)


class KeepOutBox(_Strict):
    """An axis-aligned box no body point of the arm may enter, in the arm's base frame."""

    name: str = Field(pattern=r"^[A-Za-z0-9][A-Za-z0-9 _.-]{0,63}$")
    min: Point3
    max: Point3

    @model_validator(mode="after")
    def _check(self) -> KeepOutBox:
        for axis in "xyz":
            if getattr(self.min, axis) >= getattr(self.max, axis):
                raise ValueError(f"zone {self.name}: min.{axis} must be below max.{axis}")
        return self


class SafetySettings(_Strict):
    """What an instructor may change (PUT /arms/{arm}/safety); the profile sets the start."""

    zones: list[KeepOutBox] = Field(default_factory=list, max_length=32)
    floor_z: float | None = Field(None, ge=-10.0, le=10.0,
                                  description="no body point below this height, m (None: none)")
    speed_override: float = Field(1.0, ge=0.05, le=1.0, description="scales every planned "
                                  "velocity, acceleration and jerk limit")

    @field_validator("zones")
    @classmethod
    def _unique(cls, v: list[KeepOutBox]) -> list[KeepOutBox]:
        names = [z.name for z in v]
        if len(set(names)) != len(names):
            raise ValueError(f"zone names must be unique, got {names}")
        return v


class SafetyConfig(SafetySettings):
    """A profile's `[safety]`: the settings plus the margins, which only the profile sets."""

    tool_margin: float = Field(0.0, ge=0.0, le=0.5, description="the tool's size around the "
                               "tip: zones and the floor are grown by it for the tip, m")
    body_margin: float = Field(0.0, ge=0.0, le=0.5, description="the same for every other "
                               "joint origin, m")


class ArmProfile(_Strict):
    name: str = Field(pattern=r"^[a-z0-9][a-z0-9_-]{0,31}$")
    model: str = Field(description="the arm type (a name in app/arms ARM_TYPES)")
    description: str = ""
    link: LinkConfig = Field(default_factory=LinkConfig)
    geometry: dict[str, float]
    joints: list[JointConfig]
    gripper: GripperConfig = Field(default_factory=GripperConfig)
    force: ForceConfig | None = None
    cartesian: CartesianLimits = Field(default_factory=CartesianLimits)
    home: list[float] | None = Field(None, description="joint positions of the home pose")
    raw_access: bool = Field(False, description="allow pass-through commands outside the limits")
    safety: SafetyConfig = Field(default_factory=SafetyConfig)
    calibration_poses: dict[str, list[float]] = Field(
        default_factory=dict, description="named calibration poses, joint values per joint "
        "(rad or m): POST /calibration {\"pose\": NAME} declares the arm is at one (e.g. "
        "`jig`: the arm held in its jig)")
    power_on_pose: str | None = Field(
        None, description="where the firmware zeroes its encoders at power-on, the name of "
        "one of `calibration_poses`: the joints then start calibrated (source `profile`) on "
        "the assumption the board was powered on in that pose")
    geometry_sets: dict[str, dict[str, float]] = Field(
        default_factory=dict, description="named sets of link lengths (m) an arm of this type "
        "may have; `geometry_set` picks one, its values replace those in `geometry`")
    geometry_set: str | None = Field(None, description="the name in `geometry_sets` this arm "
                                     "has (None: `geometry` as written)")
    tracking_margin: float = Field(
        0.9, gt=0.0, le=1.0, description="moves are planned with the joints' velocity and "
        "acceleration limits times this (a line: its joint velocity bound; the Cartesian "
        "limits are the tip's own), so that the device's own tracking "
        "(a PID catching up on a plan at the limit) stays within the limits the guard "
        "enforces, which stay the joints' own")

    @field_validator("geometry")
    @classmethod
    def _finite(cls, v: dict[str, float]) -> dict[str, float]:
        for k, x in v.items():
            if not math.isfinite(x):
                raise ValueError(f"geometry {k} must be finite")
        return v

    @model_validator(mode="after")
    def _calibration_and_geometry(self) -> ArmProfile:
        for name, pose in self.calibration_poses.items():
            if not all(math.isfinite(v) for v in pose):
                raise ValueError(f"calibration pose {name}: joint values must be finite")
        sim_pose = self.link.sim_power_on_pose
        if sim_pose is not None and sim_pose not in self.calibration_poses:
            raise ValueError(f"link.sim_power_on_pose {sim_pose!r} is not one of "
                             f"calibration_poses {sorted(self.calibration_poses)}")
        if self.power_on_pose is not None and self.power_on_pose not in self.calibration_poses:
            raise ValueError(f"power_on_pose {self.power_on_pose!r} is not one of "
                             f"calibration_poses {sorted(self.calibration_poses)}")
        for name, values in self.geometry_sets.items():
            if not all(math.isfinite(v) and v > 0.0 for v in values.values()):
                raise ValueError(f"geometry set {name}: lengths must be finite and positive")
        if self.geometry_set is not None:
            chosen = self.geometry_sets.get(self.geometry_set)
            if chosen is None:
                raise ValueError(f"geometry_set {self.geometry_set!r} is not one of "
                                 f"geometry_sets {sorted(self.geometry_sets)}")
            self.geometry = {**self.geometry, **chosen}
        return self

    def check_calibration_poses(self) -> None:
        """ValueError unless every calibration pose has a value per joint (checked where
        profiles are read, after the arm type's joint count)."""
        n = len(self.joints)
        for name, pose in self.calibration_poses.items():
            if len(pose) != n:
                raise ValueError(f"calibration pose {name}: give {n} joint values, not "
                                 f"{len(pose)}")

    @property
    def calibration_joints(self) -> list[int]:
        """The indexes of the joints whose zero the hardware does not know."""
        return [i for i, j in enumerate(self.joints) if not j.zero_known]

    @property
    def joint_names(self) -> list[str]:
        return [j.name for j in self.joints]

    @property
    def falling_joints(self) -> list[str]:
        """The joints gravity moves once their servos' torque is off (`falls_without_torque`),
        unless the profile allows raw access (which lifts every such refusal): what a
        teleoperation session that frees the arm as its leader asks to be held."""
        return [] if self.raw_access else [j.name for j in self.joints
                                           if j.falls_without_torque]

    def falls_on(self, motor_id: int) -> str | None:
        """The name of the joint servo `motor_id` drives if gravity moves it once the servo's
        torque is off (`falls_without_torque`), else None."""
        return next((j.name for j in self.joints
                     if j.motor_id == motor_id and j.falls_without_torque), None)

    @property
    def lower(self) -> list[float]:
        return [j.min for j in self.joints]

    @property
    def upper(self) -> list[float]:
        return [j.max for j in self.joints]


def homed_at_start(p: ArmProfile) -> ArmProfile:
    """`p` with its link marked homed at start (the built-in simulators start at a known
    pose)."""
    return p.model_copy(update={"link": p.link.model_copy(update={"homed_at_start": True})})
