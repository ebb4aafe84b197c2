"""Server settings (environment, prefix ARMSERVER_) and arm profiles (TOML files).

An arm profile holds everything that differs between arms and between a simulated and a
real link: geometry, joint limits, encoder and transmission data, link address and rates.
Code never hard-codes these; the built-in profiles carry the design documents' values.
"""

from __future__ import annotations

import math
import tomllib
from importlib import resources
from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

BUILTIN_PROFILES = ("rbe3001", "angler")


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
    timeout_s: float = Field(0.05, gt=0.0, le=10.0, description="per-request reply timeout, s")
    poll_hz: float = Field(100.0, gt=0.0, le=2000.0)
    control_hz: float = Field(100.0, gt=0.0, le=1000.0)
    queue_size: int = Field(64, ge=1, le=10_000)
    faults: FaultConfig = Field(default_factory=FaultConfig)


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

    @model_validator(mode="after")
    def _check(self) -> JointConfig:
        if self.min >= self.max:
            raise ValueError(f"joint {self.name}: min must be below max")
        if self.kind == "prismatic" and self.lead_m is None:
            raise ValueError(f"joint {self.name}: a prismatic joint needs lead_m")
        return self


class GripperConfig(_Strict):
    kind: Literal["none", "claw", "magnet"] = "none"

    @property
    def actuated(self) -> bool:
        return self.kind == "claw"


class ForceConfig(_Strict):
    adc_scale: list[float]
    adc_offset: list[float]


class CartesianLimits(_Strict):
    """Tip limits for straight-line moves."""

    max_velocity: float = Field(0.1, gt=0.0, description="m/s")
    max_acceleration: float = Field(0.5, gt=0.0, description="m/s^2")
    max_jerk: float = Field(5.0, gt=0.0, description="m/s^3")
    line_tolerance: float = Field(0.005, gt=0.0, description="how far the measured tip may "
                                  "stray from a line move's segment, m (reported, tested)")


class Point3(_Strict):
    """A point in an arm's base frame, m (within 10 m of the base: no arm here reaches further)."""

    x: float = Field(ge=-10.0, le=10.0)
    y: float = Field(ge=-10.0, le=10.0)
    z: float = Field(ge=-10.0, le=10.0)


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
    model: Literal["rbe3001", "angler"]
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

    @field_validator("geometry")
    @classmethod
    def _finite(cls, v: dict[str, float]) -> dict[str, float]:
        for k, x in v.items():
            if not math.isfinite(x):
                raise ValueError(f"geometry {k} must be finite")
        return v

    @model_validator(mode="after")
    def _check(self) -> ArmProfile:
        need = {"rbe3001": ({"l1", "l2", "l3"}, 3), "angler": ({"r", "h"}, 4)}[self.model]
        missing = need[0] - set(self.geometry)
        if missing:
            raise ValueError(f"{self.model} geometry needs {sorted(missing)}")
        if len(self.joints) != need[1]:
            raise ValueError(f"{self.model} has {need[1]} joints, profile gives {len(self.joints)}")
        return self

    @property
    def joint_names(self) -> list[str]:
        return [j.name for j in self.joints]

    @property
    def lower(self) -> list[float]:
        return [j.min for j in self.joints]

    @property
    def upper(self) -> list[float]:
        return [j.max for j in self.joints]


def load_profile(source: str | Path) -> ArmProfile:
    """Load a profile by built-in name (`rbe3001`, `angler`) or from a TOML file path."""
    if isinstance(source, str) and source in BUILTIN_PROFILES:
        text = resources.files("app.profiles").joinpath(f"{source}.toml").read_text()
    else:
        text = Path(source).read_text()
    return ArmProfile.model_validate(tomllib.loads(text))


class ServerConfig(_Strict):
    """A server config file: which arms to host, each a built-in name or a profile path,
    with optional overrides of the profile's tables."""

    arms: list[dict[str, object]] = Field(default_factory=list)


def load_arms(config_file: str | Path | None) -> list[ArmProfile]:
    """The arms a server hosts. With no config file: the simulated rbe3001 and angler.

    A config file is TOML with `[[arms]]` tables, each either `profile = "rbe3001"` (or a
    path) plus overrides such as `name = "left"` and `[arms.link]`, or a whole profile.
    """
    if config_file is None:
        return [load_profile(n) for n in BUILTIN_PROFILES]
    path = Path(config_file)
    data = tomllib.loads(path.read_text())
    profiles: list[ArmProfile] = []
    for entry in data.get("arms", []):
        entry = dict(entry)
        base_name = entry.pop("profile", None)
        if base_name is not None:
            src = base_name if base_name in BUILTIN_PROFILES else path.parent / str(base_name)
            base = load_profile(src).model_dump()
            base = _merge(base, entry)
        else:
            base = entry
        profiles.append(ArmProfile.model_validate(base))
    names = [p.name for p in profiles]
    if len(set(names)) != len(names):
        raise ValueError(f"arm names must be unique, got {names}")
    if not profiles:
        raise ValueError(f"{path} names no [[arms]]")
    return profiles


def _merge(base: dict[str, object], over: dict[str, object]) -> dict[str, object]:
    out = dict(base)
    for k, v in over.items():
        if isinstance(v, dict) and isinstance(out.get(k), dict):
            out[k] = _merge(out[k], v)  # type: ignore[arg-type]
        else:
            out[k] = v
    return out


class Settings(BaseSettings):
    """Process settings from the environment (prefix ARMSERVER_) or CLI flags."""

    model_config = SettingsConfigDict(env_prefix="ARMSERVER_", extra="ignore")

    host: str = "127.0.0.1"
    port: int = 8000
    config: str | None = None
    operator_tokens: str = ""
    viewer_tokens: str = ""
    instructor_tokens: str = ""
    #: A TOML file of named tokens for a class (`[[tokens]] name, role, token`).
    tokens_file: str | None = None
    #: Classroom queue: how long an offered lease waits for its first renewal, s.
    claim_s: float = Field(30.0, gt=0.0, le=3600.0)
    #: Classroom queue: how long a slot lasts, renewed or not, s.
    slot_s: float = Field(300.0, gt=0.0, le=86400.0)
    #: Where the SQLite store keeps settings (safety envelopes) across restarts.
    data_dir: str = "./data"
    cors_origins: str = ""
    max_body_bytes: int = 64 * 1024
    max_ws_message_bytes: int = 4 * 1024
    lease_ttl_s: float = 5.0
    #: permessage-deflate on WebSockets: off by default, because compressing each telemetry
    #: message once per client was a fifth of the server's CPU at 100 clients (py-spy).
    ws_compression: bool = False
    log_level: str = "info"

    @staticmethod
    def _split(v: str) -> frozenset[str]:
        return frozenset(t.strip() for t in v.split(",") if t.strip())

    @property
    def operator_set(self) -> frozenset[str]:
        return self._split(self.operator_tokens)

    @property
    def viewer_set(self) -> frozenset[str]:
        return self._split(self.viewer_tokens)

    @property
    def instructor_set(self) -> frozenset[str]:
        return self._split(self.instructor_tokens)

    @property
    def auth_enabled(self) -> bool:
        return bool(self.operator_set or self.viewer_set or self.instructor_set
                    or self.tokens_file)
