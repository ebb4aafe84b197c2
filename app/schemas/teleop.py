"""Teleoperation (API.md "Teleoperation (v1.2)") and replay (API.md "Recordings (v1.2)",
`POST /arms/{arm}/replay`)."""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import Field

from app.schemas.common import Bool, Finite, Int, Model

ArmRef = Annotated[str, Field(min_length=1, max_length=64)]


class TeleopStart(Model):
    """Start a session: `leader` drives `follower` at `rate_hz`. The mapping's parameters
    (`scale`, `offset`, `tip_scale`, `tip_offset`, `clamp_margin`), `deadman_s` and
    `free_leader` and `load_supported` are additions to API.md's body, all optional."""

    leader: ArmRef
    follower: ArmRef
    rate_hz: Annotated[float, Field(ge=30.0, le=100.0, allow_inf_nan=False, strict=True)] = 50.0
    mapping: Literal["joints", "tip"] = Field(
        "joints", description="`joints`: one to one, for like arms (scaled, offset, clamped); "
        "`tip`: the leader's tip (forward kinematics), the follower's IK solution nearest "
        "where it is")
    deadman_s: Annotated[float, Field(ge=0.02, le=2.0, allow_inf_nan=False, strict=True)] = Field(
        0.2, description="a leader sample older than this (s) holds the follower")
    scale: list[Finite] | None = Field(None, min_length=1, max_length=16,
                                       description="joints: per follower joint, default 1")
    offset: list[Finite] | None = Field(None, min_length=1, max_length=16,
                                        description="joints: per follower joint (rad or m), "
                                        "default 0")
    tip_scale: Annotated[float, Field(gt=0.0, le=10.0, allow_inf_nan=False, strict=True)] = Field(
        1.0, description="tip: the leader's tip position times this, about its base origin")
    tip_offset: list[Finite] | None = Field(None, min_length=3, max_length=3,
                                            description="tip: x, y, z m added after scaling")
    clamp_margin: Annotated[float, Field(ge=0.0, le=1.0, allow_inf_nan=False, strict=True)] = Field(
        0.0, description="the follower's targets are clamped this far (rad or m) inside its "
        "joint limits")
    free_leader: Bool | None = Field(
        None, description="the leader's torque off for the session, to be moved by hand (on "
        "again, holding, when it ends): default true for a real leader, false for a simulated "
        "one (moved by its own commands); true for a simulated leader moved through its world "
        "(PUT /api/v1/arms/{leader}/world/hand)")
    load_supported: Bool = Field(
        False, description="the leader's joints that fall without torque (its profile's "
        "`falls_without_torque`: the angler's z winch, an OpenManipulator-X's shoulder, elbow "
        "and wrist) are held by hand or rest: without it a session that frees such a leader "
        "is 409 `in_use` (gravity would move it where no planned move may go), as a reboot's")


class TeleopLatency(Model):
    p50: float
    p99: float


class TeleopSession(Model):
    id: str
    leader: str
    follower: str
    rate_hz: float = Field(description="as asked")
    mapping: Literal["joints", "tip"]
    deadman_s: float
    free_leader: bool = Field(False, description="the leader's torque is off for the session "
                              "(moved by hand)")
    achieved_hz: float = Field(description="ticks per second over the last 2 s (0 once ended)")
    latency_ms: TeleopLatency | None = Field(
        description="leader sample to follower command, over the last 3000 commands; null "
        "before the first")
    commands: int = Field(description="setpoints sent to the follower")
    holds: int = Field(description="ticks that sent nothing (stale or late leader sample, a "
                       "setpoint the follower refused): the follower held its last command")
    status: Literal["running", "ended"]
    reason: str | None = Field(None, description="why it ended")
    last_refusal: str | None = Field(None, description="the error code of the follower's "
                                     "last refused setpoint")
    held: str | None = Field(None, description="why the last tick held the follower: "
                             "`deadman` (the leader's newest sample stale or older than "
                             "deadman_s), `no_target` (its pose maps to no follower target), "
                             "`refused:<code>` (the follower refused the setpoint); null while "
                             "the follower follows, and once ended")
    started: float
    ended: float | None = None


class ReplayRequest(Model):
    recording: Annotated[str, Field(min_length=1, max_length=128,
                                    description="the recording's id (its name)")]
    episode: Annotated[Int, Field(ge=0, description="the episode's index")]
    wait: Bool = Field(False, description="answer 200 when the replay ends (an addition to "
                       "API.md's body, as the move routes have it)")
