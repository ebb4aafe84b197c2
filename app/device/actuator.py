"""What motion and the safety guard need from an arm's device (the `Actuator`), apart from the
link machinery of app/device/driver.py: every `Driver` is one.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from app.errors import ArmError
from app.links.base import Link


@dataclass(frozen=True)
class SettleState:
    """What the actuators say about arriving (joint indices): joints whose actuator holds no
    torque (such a joint can never be done) and joints whose actuator says it is still on
    its way. A device that tells neither leaves both empty."""

    torque_off: tuple[int, ...] = ()
    moving: tuple[int, ...] = ()


class Actuator(Protocol):
    """What the motion executor and the safety guard need from an arm's device: the last
    reading and its health, and the commands that move it. Every `Driver` is one; a test or a
    new device type may provide it without the link machinery."""

    link: Link
    positions: np.ndarray | None
    velocities: np.ndarray | None
    stale: bool
    stale_error: ArmError | None
    faults: list[dict[str, Any]]
    homed: list[bool]
    calibrated: list[bool]
    #: The joints whose actuator this server switched off (the torque route, a teleoperation
    #: leader, a pass-through Torque Enable 0) and not on again since: no command can move
    #: them (the safety guard's `require_torque`). A device without a torque switch: ().
    torque_off: tuple[int, ...]
    #: Counts the commands noted as sent (any source): the executor's own last setpoint is
    #: still the arm's commanded state while this has not moved on.
    command_seq: int
    commanded_at: float

    @property
    def commanded(self) -> np.ndarray | None: ...

    def told(self) -> np.ndarray | None: ...

    def pace(self) -> np.ndarray | None: ...

    async def command_joints(self, q: np.ndarray, *, hold: bool = False) -> None: ...

    async def set_gripper(self, value: float) -> None: ...

    async def settle_state(self) -> SettleState: ...
