"""Server settings: the environment (prefix ARMSERVER_) or CLI flags, each checked at
start-up, and the start-up message for invalid ones.

Secrets never show in a message that prints a setting: a setting whose name says token, secret
or password is `***` (a `*_file` setting is a path, shown), and a URL's password is `***`
(`mqtt://user:***@broker`), in the start-up error, in a validator's message, and in the
settings' repr; pydantic's own error text carries no input at all.
"""

from __future__ import annotations

import math
import re
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any
from urllib.parse import unquote, urlsplit

from pydantic import Field, ValidationError, field_validator, model_validator
from pydantic_settings import BaseSettings, SettingsConfigDict


class Settings(BaseSettings):
    """Process settings from the environment (prefix ARMSERVER_) or CLI flags."""

    model_config = SettingsConfigDict(env_prefix="ARMSERVER_", extra="ignore",
                                      hide_input_in_errors=True)

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
    #: Where the SQLite store keeps settings (safety envelopes), queues and the audit log.
    data_dir: str = "./data"
    #: Audit log retention: rows kept at most, the oldest deleted beyond (100,000 rows: 18 MB
    #: of typical records, 105 MB of the longest).
    audit_max_rows: int = 100_000
    #: Refused requests are counted in one audit record per address and reason per this, s.
    audit_refusal_interval_s: float = 60.0
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
        try:
            parse_broker_url(v)
        except ValueError as exc:  # its message quotes the URL: password included
            raise ValueError(mask_url(str(exc))) from None
        return v.strip()
    #: Run the arms (links, polls, motion) on their own thread and loop
    #: (app.runtime.control_thread).
    control_thread: bool = True
    #: At start-up, build every route (app/web/warm.py: the first request, an estop press, does
    #: no framework work) and collect garbage before the start-up objects are frozen
    #: (app/runtime/gc_policy.py): some 0.15-0.3 s of CPU. Off, for a process that starts many
    #: short-lived servers (the test suite starts one per test): each router is built by its
    #: first request and start-up's garbage stays frozen until the server stops.
    warm_start: bool = True
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
    #: (comma separated; `*`: any). See app/web/hostguard.py and README "Access and safety".
    allowed_hosts: str = ""

    # ------------------------------------------------ validation (issue 11.5)

    def __repr_args__(self) -> Iterator[tuple[str | None, Any]]:
        for name, value in super().__repr_args__():
            yield name, shown(name or "", value)

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
    "audit_max_rows": (100, 1_000_000_000, "100..1000000000 rows"),
    "audit_refusal_interval_s": (0.0, 86400.0, "> 0 and at most 86400 s (a day)"),
}
_QUANTITY_SUFFIXES = ("_s", "_hz", "_bytes", "_rate", "_size", "_count", "_limit")
LOG_LEVELS = ("critical", "error", "warning", "info", "debug", "trace")


_SECRET_NAME = re.compile(r"(?i)token|secret|password")
#: `scheme://user:password@`: the password part (to the last `@` before the host: a password
#: may hold an `@`).
_URL_PASSWORD = re.compile(r"(?i)([a-z][a-z0-9+.-]*://[^/@:\s'\"]*):[^/\s'\"]*@")
MASK = "***"


def env_name(field: str) -> str:
    return f"ARMSERVER_{field.upper()}"


def is_secret(name: str) -> bool:
    """Whether a setting's value is a secret (its name says token, secret or password; a
    `*_file` setting is the path of one, not one)."""
    return bool(_SECRET_NAME.search(name)) and not name.lower().endswith("_file")


@dataclass(frozen=True)
class BrokerUrl:
    """An MQTT broker address, parsed from ARMSERVER_MQTT_URL."""


    host: str
    port: int
    username: str | None
    password: str | None
    tls: bool

    @property
    def public(self) -> str:
        """The URL without credentials (health, logs)."""
        scheme = "mqtts" if self.tls else "mqtt"
        user = f"{self.username}@" if self.username else ""
        return f"{scheme}://{user}{self.host}:{self.port}"


def parse_broker_url(url: str) -> BrokerUrl:
    """`mqtt://[user[:password]@]host[:port]` (mqtts:// for TLS; default ports 1883 / 8883)."""
    parts = urlsplit(url.strip())
    if parts.scheme not in ("mqtt", "mqtts", "tcp"):
        raise ValueError(f"MQTT URL must start with mqtt:// or mqtts://, got {url!r}")
    if not parts.hostname:
        raise ValueError(f"MQTT URL names no host: {url!r}")
    tls = parts.scheme == "mqtts"
    try:
        port = parts.port or (8883 if tls else 1883)
    except ValueError as exc:
        raise ValueError(f"MQTT URL has a bad port: {exc}") from None
    user = unquote(parts.username) if parts.username else None
    password = unquote(parts.password) if parts.password is not None else None
    return BrokerUrl(parts.hostname, port, user, password, tls)


def mask_url(text: str) -> str:
    """`text` with the password of every `scheme://user:password@` in it as `***`."""
    return _URL_PASSWORD.sub(rf"\1:{MASK}@", text)


def shown(name: str, value: Any) -> Any:
    """A setting's value as a message may show it: a secret's as `***`, URLs' passwords
    masked."""
    if is_secret(name) and value not in (None, ""):
        return MASK
    return mask_url(value) if isinstance(value, str) else value


def settings_error(exc: ValidationError) -> str:
    """A start-up message for invalid settings: which variable, what value, what it must be;
    no secret (see `shown`)."""
    lines = ["invalid settings (environment ARMSERVER_* or command-line flags):"]
    for e in exc.errors():
        loc = ".".join(str(p) for p in e["loc"])
        msg = mask_url(str(e["msg"]).removeprefix("Value error, "))
        value = e.get("input")
        if loc and is_secret(loc) and isinstance(value, str) and value:
            msg = msg.replace(value, MASK)
        if loc:
            lines.append(f"  {env_name(loc)}={shown(loc, value)!r}: {msg}")
        else:
            lines.extend(f"  {m}" for m in msg.split("; "))
    return "\n".join(lines)
