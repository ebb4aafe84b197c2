"""TelemetryHub.subscribe while the control thread publishes: a subscription begins with the
latest sample (a WebSocket client's first message, "the latest sample at once"), even when a
sample is published while it is being made. On a loaded machine that happened between the
hub deriving the latest and taking its lock: the subscription began with no initial sample,
and the client's first message was the first batch, 23 samples (tests/test_ws_telemetry.py)."""

from __future__ import annotations

import json
from typing import Any

import numpy as np
import pytest

from app.arms import model_for
from app.arms.loading import load_profile
from app.telemetry.hub import TelemetryHub


def _hub() -> TelemetryHub:
    hub = TelemetryHub("rbe3001")
    model = model_for(load_profile("rbe3001"))
    hub.derive_with(lambda: model)
    return hub


def _publish(hub: TelemetryHub, seq: int) -> None:
    q = np.array([0.001 * seq, 0.6, 0.3])
    hub.publish({"seq": seq, "time": 1000.0 + seq, "positions": q.tolist(),
                 "velocities": [0.0, 0.0, 0.0]}, (q, np.zeros(3), None))


def _publishing_at_the_first_derivation(hub: TelemetryHub, seqs: list[int]) -> None:
    """When the hub next derives samples, `seqs` are published first: the control thread
    taking the GIL at that moment (the real derivation runs, every time)."""
    real = hub._ready
    todo = list(seqs)

    def ready(entries: Any) -> None:
        while todo:
            _publish(hub, todo.pop(0))
        real(entries)

    hub._ready = ready  # type: ignore[method-assign]


@pytest.mark.parametrize("between", [1, 3])
def test_a_subscription_begins_with_the_latest_sample_published_while_it_was_made(
        between: int) -> None:
    hub = _hub()
    for seq in range(1, 4):
        _publish(hub, seq)
    meanwhile = list(range(100, 100 + between))
    _publishing_at_the_first_derivation(hub, meanwhile)
    sub = hub.subscribe()
    try:
        assert sub.initial is not None, "the subscription began with no sample"
        initial = json.loads(sub.initial)
        assert initial["seq"] == 3  # the latest when it was made
        assert "tip" in initial  # derived, as every sample a client reads
        # those published meanwhile, then the later ones, follow on from it: none lost or twice
        for seq in range(200, 203):
            _publish(hub, seq)
        samples, _, dropped = sub.take()
        assert dropped == 0
        assert [json.loads(t)["seq"] for t in samples] == [*meanwhile, 200, 201, 202]
    finally:
        sub.close()
