"""Telemetry: samples, the WebSocket's telemetry and event messages."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from app.schemas.arms import Fault, Tip, Vec3
from app.schemas.common import Model

# ---------------------------------------------------------------- telemetry


class MotionBrief(Model):
    id: str
    status: Literal["queued", "running", "done", "stopped", "failed"]
    progress: float


class Sample(Model):
    """One device sample, as in `/state` and in every telemetry message."""

    seq: int
    time: float = Field(description="Unix time the device sample was taken, s")
    positions: list[float]
    velocities: list[float]
    torques: list[float] | None = None
    tip: Tip
    tip_velocity: Vec3
    tip_force: Vec3 | None = None
    gripper: float | None = None
    motion: MotionBrief | None = None
    estop: bool = False
    link: Literal["connecting", "up", "down"] = "up"
    stale: bool = False
    faults: list[Fault] = Field(default_factory=list)
    homed: list[bool] = Field(default_factory=list)
    calibrated: list[bool] = Field(default_factory=list)


class TelemetryMessage(Model):
    type: Literal["telemetry"] = "telemetry"
    arm: str
    samples: list[Sample]
    dropped: int = 0


class EventMessage(Model):
    type: Literal["event"] = "event"
    arm: str
    event: str = Field(description="motion_started, motion_ended, estop, estop_released, "
                       "link_lost, link_back, lease_expired, watchdog")
    time: float
    data: dict[str, object] = {}
