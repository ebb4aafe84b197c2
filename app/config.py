"""Server settings (environment, prefix ARMSERVER_) and arm profiles (TOML files).

An arm profile holds everything that differs between arms and between a simulated and a
real link: geometry, joint limits, encoder and transmission data, link address and rates.
Code never hard-codes these; the built-in profiles carry the design documents' values.
"""

from __future__ import annotations

import math
import tomllib
from pathlib import Path
from typing import Any, Literal

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    ValidationError,
    field_validator,
    model_validator,
)
from pydantic_settings import BaseSettings, SettingsConfigDict

from app.arms import arm_type, builtin_profiles

#: Most copies one `[[arms]]` entry may ask for (`count`).
MAX_COPIES = 256


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
    homed_at_start: bool = Field(
        False, description="the joints that need homing start homed: true only for a device "
        "that starts at a known pose (the built-in simulated config); a real multi-turn joint "
        "does not know where it is after a power cycle")
    sim_echo: bool = Field(False, description="rbe3001 simulator only: reply as firmware builds "
                           "that echo the request's unwritten floats, instead of zeroing them as "
                           "PidServer.cpp does (the default)")


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
    settle_tolerance: float | None = Field(
        None, gt=0.0, description="rad or m: a motion is done when the joint is this close to "
        "where it was sent (default: 8 encoder ticks)")

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

    @field_validator("model")
    @classmethod
    def _known_type(cls, v: str) -> str:
        arm_type(v)  # ValueError naming the known arm types
        return v

    @model_validator(mode="after")
    def _check(self) -> ArmProfile:
        arm_type(self.model).validate(self)  # geometry keys, joint count, the type's own
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


class ConfigError(ValueError):
    """A config file or profile that cannot be used; the message says what is wrong, where,
    and (for an unknown profile) which profiles are built in. `armserver serve` prints it and
    exits 2, no traceback."""


def _builtins() -> str:
    return ", ".join(f'"{n}"' for n in builtin_profiles())


def _read_toml(path: Path, what: str) -> dict[str, Any]:
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError(f"{what} {path}: no such file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{what} {path}: cannot be read: {exc}") from None
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{what} {path}: malformed TOML: {exc}") from None


def _invalid(exc: ValidationError, where: str) -> ConfigError:
    lines = [f"{where}: {exc.error_count()} invalid value(s):"]
    for e in exc.errors():
        loc = ".".join(str(p) for p in e["loc"]) or "(top level)"
        lines.append(f"  {loc}: {e['msg']}")
    return ConfigError("\n".join(lines))


def load_profile(source: str | Path) -> ArmProfile:
    """Load a profile by built-in name (a `*.toml` shipped in an arm type's package, e.g.
    `rbe3001`, `angler`) or from a TOML file path.
    Raises :class:`ConfigError` naming the file and what is wrong with it."""
    builtins = builtin_profiles()
    if isinstance(source, str) and source in builtins:
        text = builtins[source].read_text(encoding="utf-8")
        data, where = tomllib.loads(text), f"built-in profile {source!r}"
    else:
        path = Path(source)
        if not path.is_file():
            raise ConfigError(f"profile {str(source)!r}: not a built-in profile (those are "
                              f"{_builtins()}) and no profile file {path}")
        data, where = _read_toml(path, "profile file"), f"profile file {path}"
    try:
        return ArmProfile.model_validate(data)
    except ValidationError as exc:
        raise _invalid(exc, where) from None


class ServerConfig(_Strict):
    """A server config file: which arms to host, each a built-in name or a profile path,
    with optional overrides of the profile's tables."""

    arms: list[dict[str, object]] = Field(default_factory=list)


def load_arms(config_file: str | Path | None) -> list[ArmProfile]:
    """The arms a server hosts. With no config file: every built-in profile, simulated.

    A config file is TOML with `[[arms]]` tables, each either `profile = "rbe3001"` (or a
    path) plus overrides such as `name = "left"` and `[arms.link]`, or a whole profile.
    `count = N` (1..256) in an entry hosts N copies named `{name}-1` .. `{name}-N` (a lab of
    simulated arms from one entry; a copy's link address, if any, is shared, so use it with
    `kind = "sim"`).
    """
    if config_file is None:  # the built-in simulators start at a known pose: homed
        builtin = [load_profile(n) for n in builtin_profiles()]
        return [homed_at_start(p) for p in builtin if arm_type(p.model).default_server]
    path = Path(config_file)
    data = _read_toml(path, "config file")
    arms = data.get("arms", [])
    if not isinstance(arms, list) or not all(isinstance(a, dict) for a in arms):
        raise ConfigError(f"config file {path}: `arms` must be [[arms]] tables")
    profiles: list[ArmProfile] = []
    for k, entry in enumerate(arms):
        entry = dict(entry)
        where = f"config file {path}, [[arms]] #{k + 1}"
        count = entry.pop("count", 1)
        if isinstance(count, bool) or not isinstance(count, int) or not 1 <= count <= MAX_COPIES:
            raise ConfigError(f"{where}: count must be an integer 1..{MAX_COPIES}, got {count!r}")
        base_name = entry.pop("profile", None)
        if base_name is not None:
            if not isinstance(base_name, str) or not base_name:
                raise ConfigError(f"{where}: `profile` must be a built-in profile name "
                                  f"({_builtins()}) or a path to a profile file")
            src = base_name if base_name in builtin_profiles() else path.parent / base_name
            if isinstance(src, Path) and not src.is_file():
                raise ConfigError(f"{where}: profile = {base_name!r} is neither a built-in "
                                  f"profile ({_builtins()}) nor a profile file ({src})")
            try:
                base = load_profile(src).model_dump()
            except ConfigError as exc:
                raise ConfigError(f"{where}: {exc}") from None
            base = _merge(base, entry)
        else:
            base = entry
        copies = [base] if count == 1 else [
            {**base, "name": f"{base.get('name')}-{n}"} for n in range(1, count + 1)]
        for copy in copies:
            try:
                profiles.append(ArmProfile.model_validate(copy))
            except ValidationError as exc:
                raise _invalid(exc, where) from None
    names = [p.name for p in profiles]
    if len(set(names)) != len(names):
        raise ConfigError(f"config file {path}: arm names must be unique, got {names} (give "
                          "each a `name`)")
    if not profiles:
        raise ConfigError(f"config file {path} names no [[arms]]")
    return profiles


def homed_at_start(p: ArmProfile) -> ArmProfile:
    return p.model_copy(update={"link": p.link.model_copy(update={"homed_at_start": True})})


def _merge(base: dict[str, object], over: dict[str, object]) -> dict[str, object]:
    out = dict(base)
    for k, v in over.items():
        if isinstance(v, dict) and isinstance(out.get(k), dict):
            out[k] = _merge(out[k], v)  # type: ignore[arg-type]  # both dicts: checked above
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
    #: Lab-wide telemetry (API.md "Lab-wide telemetry over MQTT"): the broker,
    #: `mqtt://[user[:password]@]host[:port]`; unset: no bridge.
    mqtt_url: str | None = None
    mqtt_prefix: str = Field("armserver", pattern=r"^[A-Za-z0-9_-]+(/[A-Za-z0-9_-]+)*$")
    mqtt_rate: float = Field(10.0, gt=0.0, le=100.0, description="state/telemetry messages per s")

    @field_validator("mqtt_url")
    @classmethod
    def _mqtt_url(cls, v: str | None) -> str | None:
        if v is None or not v.strip():
            return None
        from app.mqtt import parse_broker_url

        parse_broker_url(v)
        return v.strip()
    #: Run the arms (links, polls, motion) on their own thread and loop (app.control).
    control_thread: bool = True
    #: Largest request head (request line and headers), bytes: more is refused with 400 after
    #: that many bytes, before any parsing of the rest (uvicorn's h11 parser).
    max_header_bytes: int = 32 * 1024
    #: Open connections (HTTP keep-alive and WebSocket) before new requests get 503: room
    #: for `max_subscribers` dashboards and the REST clients beside them.
    max_connections: int = 4096
    #: Telemetry WebSocket subscribers per arm and in all; more are closed with 1013 `busy`.
    #: A lab's 1,000 dashboards on one arm fit (issue 12: 1,000 clients at 30 msg/s).
    max_subscribers_per_arm: int = 1000
    max_subscribers: int = 2000
    #: After SIGTERM has stopped the arms: how long open requests may take to finish, s.
    shutdown_timeout_s: float = 5.0

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

    #: Host names an open server answers to besides its loopback names and bound host
    #: (comma separated; `*`: any). See app/hostguard.py and README "Access and safety".
    allowed_hosts: str = ""

    # ------------------------------------------------ validation (issue 11.5)

    @field_validator("log_level")
    @classmethod
    def _lower_level(cls, v: str) -> str:
        return v.strip().lower()

    @model_validator(mode="after")
    def _validate_every_setting(self) -> Settings:
        """Every setting, checked at start-up (a NaN lease TTL locked an arm until restart):
        explicit ranges where known, and for every other number (settings other modules add
        included) finite, and not negative where the name says duration, rate or size."""
        problems: list[str] = []
        for name, value in self:
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                continue
            shown = f"{env_name(name)}={value!r}"
            if not math.isfinite(value):
                problems.append(f"{shown}: must be a finite number")
            elif name in SETTING_RANGES:
                lo, hi, what = SETTING_RANGES[name]
                if not (lo < value <= hi if what.startswith(">") else lo <= value <= hi):
                    problems.append(f"{shown}: must be {what}")
            elif name.endswith(_QUANTITY_SUFFIXES) or name.startswith("max_"):
                if value < 0:
                    problems.append(f"{shown}: must not be negative")
        if self.log_level.lower() not in LOG_LEVELS:
            problems.append(f"{env_name('log_level')}={self.log_level!r}: must be one of "
                            f"{', '.join(LOG_LEVELS)}")
        if not self.host.strip():
            problems.append(f"{env_name('host')}: must not be empty")
        if problems:
            raise ValueError("; ".join(problems))
        return self


#: name -> (low, high, "what it must be"); a leading ">" means the low end is excluded.
SETTING_RANGES: dict[str, tuple[float, float, str]] = {
    "port": (0, 65535, "a TCP port, 0..65535"),
    "max_body_bytes": (1, 1 << 30, "1..1073741824 bytes"),
    "max_ws_message_bytes": (1, 1 << 26, "1..67108864 bytes"),
    "lease_ttl_s": (0.0, 86400.0, "> 0 and at most 86400 s (a day)"),
}
_QUANTITY_SUFFIXES = ("_s", "_hz", "_bytes", "_rate", "_size", "_count", "_limit")
LOG_LEVELS = ("critical", "error", "warning", "info", "debug", "trace")


def env_name(field: str) -> str:
    return f"ARMSERVER_{field.upper()}"


def settings_error(exc: ValidationError) -> str:
    """A start-up message for invalid settings: which variable, what value, what it must be."""
    lines = ["invalid settings (environment ARMSERVER_* or command-line flags):"]
    for e in exc.errors():
        loc = ".".join(str(p) for p in e["loc"])
        msg = str(e["msg"]).removeprefix("Value error, ")
        if loc:
            lines.append(f"  {env_name(loc)}={e.get('input')!r}: {msg}")
        else:
            lines.extend(f"  {m}" for m in msg.split("; "))
    return "\n".join(lines)
