"""TelemetryHub.subscribe while the control thread publishes: a subscription begins with the
latest sample (a WebSocket client's first message, "the latest sample at once"), even when a
sample is published between the hub deriving the latest and taking its lock. On a loaded
machine that happened: the subscription began with no initial sample, and the client's first
message was the first batch, 23 samples (tests/test_ws_telemetry.py)."""

from __future__ import annotations

import json
from typing import Any

import numpy as np
import pytest

from app.arms import model_for
from app.arms.loading import load_profile
from app.telemetry.hub import SUBSCRIBE_TRIES, TelemetryHub


def _hub() -> TelemetryHub:
    hub = TelemetryHub("rbe3001")
    model = model_for(load_profile("rbe3001"))
    hub.derive_with(lambda: model)
    return hub


def _publish(hub: TelemetryHub, seq: int) -> None:
    q = np.array([0.001 * seq, 0.6, 0.3])
    hub.publish({"seq": seq, "time": 1000.0 + seq, "positions": q.tolist(),
                 "velocities": [0.0, 0.0, 0.0]}, (q, np.zeros(3), None))


def _publishing_after_each_derivation(hub: TelemetryHub, times: int) -> list[int]:
    """Each of the hub's next `times` derivations of its latest sample is followed at once by
    the publication of a new sample: the control thread taking the GIL at that moment. Returns
    the seqs published so (the real `_snapshot` runs every time)."""
    real = hub._snapshot
    published: list[int] = []

    def snapshot() -> Any:
        out = real()
        if len(published) < times:
            seq = 100 + len(published)
            _publish(hub, seq)
            published.append(seq)
        return out

    hub._snapshot = snapshot  # type: ignore[method-assign]
    return published


@pytest.mark.parametrize("between", [1, SUBSCRIBE_TRIES - 1, SUBSCRIBE_TRIES, 10])
def test_a_subscription_begins_with_the_latest_sample_published_while_it_was_made(
        between: int) -> None:
    hub = _hub()
    for seq in range(1, 4):
        _publish(hub, seq)
    published = _publishing_after_each_derivation(hub, between)
    sub = hub.subscribe()
    try:
        assert sub.initial is not None, "the subscription began with no sample"
        initial = json.loads(sub.initial)
        # the latest as of the subscription: the last sample published before it was made
        last = published[min(between, SUBSCRIBE_TRIES) - 1]
        assert initial["seq"] == last
        assert "tip" in initial  # derived, as every sample a client reads
        # and the samples after it follow on from it, none lost, none twice
        for seq in range(200, 203):
            _publish(hub, seq)
        samples, _, dropped = sub.take()
        seqs = [json.loads(t)["seq"] for t in samples]
        assert dropped == 0
        assert [s for s in seqs if s < 200] == published[min(between, SUBSCRIBE_TRIES):]
        assert seqs[-3:] == [200, 201, 202]
    finally:
        sub.close()
