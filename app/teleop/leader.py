"""What a teleoperation session needs of its leader: its name, profile, model, estop latch,
link, torque switch and a subscription to its samples. An arm of this server (`ArmService`) is
one; so is an arm on another worker of a lab, read over the network (app/teleop/remote.py)."""

from __future__ import annotations

from typing import Protocol

from app import schemas as s
from app.arms.model import KinematicsModel
from app.config import ArmProfile


class LeaderFeed(Protocol):
    """The leader's samples as a session reads them (`app.telemetry.hub.Subscription`)."""

    @property
    def initial(self) -> str | None:
        """The newest encoded sample when subscribing (None before the first)."""

    def take(self) -> tuple[list[str], list[str], int]:
        """Encoded samples and events since the last take, and how many were dropped."""

    def close(self) -> None: ...


class Leader(Protocol):
    @property
    def name(self) -> str: ...

    @property
    def profile(self) -> ArmProfile: ...

    @property
    def model(self) -> KinematicsModel: ...

    @property
    def estop(self) -> bool: ...

    def link_status(self) -> s.LinkStatus: ...

    async def set_torque(self, on: bool) -> None: ...

    def subscribe(self, backlog: int | None = None) -> LeaderFeed: ...
