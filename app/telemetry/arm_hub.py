"""An arm's telemetry hub: the place its samples are published, where each sample gets the
arm's own state (the estop latch and the motion in progress) that the device does not know.

The driver publishes the device's reading (positions, velocities, torques, tip, link, stale,
faults, homed); the service that owns the arm builds this hub with the step that stamps the
rest, so the driver needs no callback from the service and the wire sample is one dict.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from app.telemetry.hub import DEFAULT_BACKLOG, TelemetryHub

Stamp = Callable[[dict[str, Any]], None]


class ArmHub(TelemetryHub):
    """A `TelemetryHub` that stamps each sample with `stamp(sample)` before it is encoded."""

    def __init__(self, arm: str, stamp: Stamp, backlog: int = DEFAULT_BACKLOG) -> None:
        super().__init__(arm, backlog)
        self._stamp = stamp

    def publish(self, sample: dict[str, Any], inputs: Any = None) -> None:
        self._stamp(sample)
        super().publish(sample, inputs)

    def publish_run(self, sample: dict[str, Any], stamps: list[tuple[int, float]],
                    inputs: Any = None) -> None:
        """`TelemetryHub.publish_run`, the arm's fields stamped once for the whole run: its
        samples are published at once, in one call on the control loop, where the estop latch
        and the motion change, so each would be stamped with the same."""
        sample = dict(sample)
        self._stamp(sample)
        super().publish_run(sample, stamps, inputs)
