"""What the telemetry log keeps of each sample read is the sample's JSON at its own size.

orjson 3.13 returns bytes that keep the buffer it wrote into (4 KiB for a sample of a few
hundred bytes); the hub kept those bytes for every sample a reader derived: 4 KiB a sample in
every arm's log, the soak's steady memory growth (docs/performance.md, session 13). Measured
with tracemalloc: the allocations the hub's own module makes while it derives and encodes
a log's samples, against the bytes of JSON they hold."""

from __future__ import annotations

import tracemalloc

import numpy as np

from app.telemetry import hub as hub_module
from tests.test_hub_subscribe import _hub

N = 1000  # (within the hub's default backlog: every sample stays in the log)


def test_a_read_sample_keeps_its_json_at_its_own_size() -> None:
    hub = _hub()
    sub = hub.subscribe()
    for seq in range(N):
        q = np.array([0.001 * seq, 0.6, 0.3])
        hub.publish({"seq": seq, "time": 1000.0 + seq, "positions": q.tolist(),
                     "velocities": [0.0, 0.0, 0.0], "motion": None, "estop": False},
                    (q, np.zeros(3), None))
    only_hub = [tracemalloc.Filter(True, hub_module.__file__)]
    tracemalloc.start()
    try:
        before = tracemalloc.take_snapshot().filter_traces(only_hub)
        samples, events, _dropped = sub.take()  # derives and encodes every unread sample
        after = tracemalloc.take_snapshot().filter_traces(only_hub)
    finally:
        tracemalloc.stop()
        sub.close()
    assert events == [] and len(samples) == N
    kept = sum(d.size_diff for d in after.compare_to(before, "filename"))
    payload = sum(len(s) for s in samples)  # the JSON text, as bytes and as str: twice this
    assert payload > 200 * N  # (a few hundred bytes a sample)
    # both forms at their own size, and what the log keeps beside them: 2.6 times the
    # payload; with orjson's 4 KiB buffers kept, 18 times
    print(f"kept {kept} bytes for {payload} of JSON: {kept / payload:.2f}x")
    assert kept < 3 * payload, (kept, payload, kept / payload)
    latest = hub.latest_bytes
    assert latest is not None and latest == samples[-1].encode()
