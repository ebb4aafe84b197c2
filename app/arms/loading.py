"""Loading arm profiles (built-in names or TOML files) and server config files (`[[arms]]`
entries with overrides and copies), each profile checked against its arm type
(`check_profile`), with a `ConfigError` that says what and where.

This is the registry's side of the profiles: app/config holds the plain models and imports no
arm type, so the arm types may name ArmProfile in their types without an import cycle."""

from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Any

from pydantic import Field, ValidationError

from app.arms import arm_type, builtin_profiles
from app.config.profiles import (
    ArmProfile,
    ConfigError,
    _Strict,
    homed_at_start,
    invalid_config,
)

__all__ = ["MAX_COPIES", "TOP_LEVEL_KEYS", "ServerConfig", "check_profile", "load_arms",
           "load_profile"]

#: The top-level tables and keys a server config file may have; anything else is refused at
#: start with its name. `cameras` is read by app/cameras/config.py (`load_cameras`), `teleop`
#: by app/teleop/config.py (`load_teleop`).
TOP_LEVEL_KEYS = frozenset({"arms", "cameras", "teleop"})

#: Most copies one `[[arms]]` entry may ask for (`count`).
MAX_COPIES = 256
#: Most worker processes one server may run (`worker` in an `[[arms]]` entry, app/lab).
MAX_WORKERS = 64


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


def check_profile(data: object, where: str = "profile") -> ArmProfile:
    """`data` (a mapping, as read from TOML) as a profile that its arm type accepts: the
    models' own checks, then the type named by `model` (known, its geometry keys, its joint
    count, its own check). Raises :class:`ConfigError` saying where and what."""
    try:
        profile = ArmProfile.model_validate(data)
    except ValidationError as exc:
        raise invalid_config(exc, where) from None
    try:
        kind = arm_type(profile.model)
    except ValueError as exc:  # names the known arm types
        raise ConfigError(f"{where}: model: {exc}") from None
    try:
        kind.validate(profile)
        profile.check_calibration_poses()
    except ValueError as exc:
        raise ConfigError(f"{where}: {exc}") from None
    return profile


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
    return check_profile(data, where)


class ServerConfig(_Strict):
    """A server config file: which arms to host, each a built-in name or a profile path,
    with optional overrides of the profile's tables."""

    arms: list[dict[str, object]] = Field(default_factory=list)


def load_arms(config_file: str | Path | None,
              placed: dict[str, int] | None = None) -> list[ArmProfile]:
    """The arms a server hosts. With no config file: every built-in profile, simulated.

    A config file is TOML with `[[arms]]` tables, each either `profile = "rbe3001"` (or a
    path) plus overrides such as `name = "left"` and `[arms.link]`, or a whole profile.
    `count = N` (1..256) in an entry hosts N copies named `{name}-1` .. `{name}-N` (a lab of
    simulated arms from one entry; a copy's link address, if any, is shared, so use it with
    `kind = "sim"`).
    `worker = K` (0..MAX_WORKERS-1) names the worker process that hosts the entry's arms under
    `armserver serve --workers N` (app/lab); it is written into `placed` (arm name -> K), if
    given, and otherwise only checked.
    """
    if config_file is None:  # the built-in simulators start at a known pose: homed
        builtin = [load_profile(n) for n in builtin_profiles()]
        return [homed_at_start(p) for p in builtin if arm_type(p.model).default_server]
    path = Path(config_file)
    data = _read_toml(path, "config file")
    unknown = sorted(set(data) - TOP_LEVEL_KEYS)
    if unknown:  # a misspelt table would otherwise be silently ignored
        raise ConfigError(f"config file {path}: unknown table or key {', '.join(unknown)} "
                          f"(known: {', '.join(sorted(TOP_LEVEL_KEYS))})")
    arms = data.get("arms", [])
    if not isinstance(arms, list) or not all(isinstance(a, dict) for a in arms):
        raise ConfigError(f"config file {path}: `arms` must be [[arms]] tables")
    profiles: list[ArmProfile] = []
    for k, entry in enumerate(arms):
        entry = dict(entry)
        where = f"config file {path}, [[arms]] #{k + 1}"
        count = entry.pop("count", 1)
        worker = entry.pop("worker", None)
        if worker is not None and (isinstance(worker, bool) or not isinstance(worker, int)
                                   or not 0 <= worker < MAX_WORKERS):
            raise ConfigError(f"{where}: worker must be an integer 0..{MAX_WORKERS - 1}, "
                              f"got {worker!r}")
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
            profiles.append(check_profile(copy, where))
            if worker is not None and placed is not None:
                placed[profiles[-1].name] = worker
    names = [p.name for p in profiles]
    if len(set(names)) != len(names):
        raise ConfigError(f"config file {path}: arm names must be unique, got {names} (give "
                          "each a `name`)")
    if not profiles:
        raise ConfigError(f"config file {path} names no [[arms]]")
    return profiles


def _merge(base: dict[str, object], over: dict[str, object]) -> dict[str, object]:
    out = dict(base)
    for k, v in over.items():
        if isinstance(v, dict) and isinstance(out.get(k), dict):
            out[k] = _merge(out[k], v)  # type: ignore[arg-type]  # both dicts: checked above
        else:
            out[k] = v
    return out
