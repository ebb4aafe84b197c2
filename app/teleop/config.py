"""The `[[teleop]]` tables of a server config file: per leader/follower pair, the mapping's
defaults (scale, offset, clamp margin, tip scale and offset, rate, deadman time), which a
`POST /api/v1/teleop` for that pair starts from; a field the request gives wins.

    [[teleop]]
    leader = "leader"
    follower = "follower"
    scale = [1.0, 1.0, 1.0, 1.0]
    clamp_margin = 0.05
"""

from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from app import schemas as s
from app.config.profiles import ArmProfile, ConfigError, invalid_config

__all__ = ["TeleopPair", "load_teleop", "parse_teleop", "with_pair"]

Finite = Annotated[float, Field(allow_inf_nan=False)]


class TeleopPair(BaseModel):
    """One `[[teleop]]` table. Unknown keys are refused by name; bounds as the request's."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    leader: Annotated[str, Field(min_length=1, max_length=64)]
    follower: Annotated[str, Field(min_length=1, max_length=64)]
    mapping: Literal["joints", "tip"] | None = None
    rate_hz: Annotated[float, Field(ge=30.0, le=100.0, allow_inf_nan=False)] | None = None
    deadman_s: Annotated[float, Field(ge=0.02, le=2.0, allow_inf_nan=False)] | None = None
    scale: Annotated[list[Finite], Field(min_length=1, max_length=16)] | None = None
    offset: Annotated[list[Finite], Field(min_length=1, max_length=16)] | None = None
    tip_scale: Annotated[float, Field(gt=0.0, le=10.0, allow_inf_nan=False)] | None = None
    tip_offset: Annotated[list[Finite], Field(min_length=3, max_length=3)] | None = None
    clamp_margin: Annotated[float, Field(ge=0.0, le=1.0, allow_inf_nan=False)] | None = None


#: The request fields a pair's table may set.
_DEFAULTS = ("mapping", "rate_hz", "deadman_s", "scale", "offset", "tip_scale", "tip_offset",
             "clamp_margin")


def with_pair(req: s.TeleopStart, pairs: list[TeleopPair]) -> s.TeleopStart:
    """`req` with its pair's configured values where the request gave none."""
    pair = next((p for p in pairs if (p.leader, p.follower) == (req.leader, req.follower)),
                None)
    if pair is None:
        return req
    given = req.model_fields_set
    update = {k: getattr(pair, k) for k in _DEFAULTS
              if k not in given and getattr(pair, k) is not None}
    return req.model_copy(update=update) if update else req


def parse_teleop(tables: object, arms: list[str], where: str) -> list[TeleopPair]:
    """`[[teleop]]` tables as read from TOML, checked: known keys and bounds, hosted arms, a
    leader that is not its follower, one table per pair. `ConfigError` says which and what."""
    if not isinstance(tables, list) or not all(isinstance(t, dict) for t in tables):
        raise ConfigError(f"{where}: `teleop` must be [[teleop]] tables")
    out: list[TeleopPair] = []
    for k, table in enumerate(tables):
        at = f"{where}, [[teleop]] #{k + 1}"
        try:
            pair = TeleopPair.model_validate(table)
        except ValidationError as exc:
            raise invalid_config(exc, at, "not a teleoperation setting") from None
        for role, name in (("leader", pair.leader), ("follower", pair.follower)):
            if name not in arms:
                raise ConfigError(f"{at}: {role} = {name!r} is not a hosted arm "
                                  f"({', '.join(arms)})")
        if pair.leader == pair.follower:
            raise ConfigError(f"{at}: the leader and the follower are both {pair.leader!r}")
        out.append(pair)
    keys = [(p.leader, p.follower) for p in out]
    if len(set(keys)) != len(keys):
        raise ConfigError(f"{where}: one [[teleop]] table per leader and follower, got {keys}")
    return out


def load_teleop(config_file: str | Path | None, profiles: list[ArmProfile]) -> list[TeleopPair]:
    """The config file's `[[teleop]]` tables (none without a file or a table). The file was
    read and its top-level tables checked by `app.arms.loading.load_arms` already."""
    if config_file is None:
        return []
    path = Path(config_file)
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        raise ConfigError(f"config file {path}: {exc}") from None
    if "teleop" not in data:
        return []
    return parse_teleop(data["teleop"], [p.name for p in profiles], f"config file {path}")
