"""A short faults soak (bench/soak.py): the server in process under injected link faults (5 %
of replies dropped, 2 % corrupted, 5 ms latency, the link cut every 6 s), with movers,
protocol clients and telemetry subscribers on both arms at once. Nothing may be lost or
answered wrongly, no motion reported done away from its target, and no telemetry gap left
unreported; afterwards both arms are healthy. `make soak` runs the long version."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "bench"))

import soak  # noqa: E402  (bench/soak.py)

from app.config import FaultConfig  # noqa: E402

pytestmark = pytest.mark.slow

#: The link is cut every 6 s: under these faults a move takes three to four times its planned
#: time (each dropped or corrupt reply holds the link for a timeout and a quiet period, and the
#: executor stretches the plan rather than jump), so a cut every 4 s left each window room for
#: one move at most and `done` hung on whether a move started early in its window.
SECONDS = 13.0
FAULTS = FaultConfig(drop=0.05, corrupt=0.02, latency_s=0.005, disconnect_after_s=6.0,
                     reconnect_after_s=0.5)


async def test_soak_under_faults() -> None:
    with soak.serve() as srv:
        # the clients run in this test's loop, the server in its own thread and loop
        res = await soak.soak(srv, SECONDS, FAULTS, seed=3, subscribers_per_arm=1)
    t = res["tally"]
    text = soak.report(res, FAULTS)
    print(text)
    assert t.lost == 0, text
    assert t.wrong == 0, text
    assert t.wrongly_done == 0, text
    assert t.seq_backwards == 0 and t.seq_gaps <= t.reported_dropped, text
    assert res["healthy"] and res["internal_errors"] == 0, text
    assert t.correct > 100 and t.motions["done"] >= 2, text
    assert t.samples > 100, text
    assert t.events["link_lost"] >= 2 and t.events["link_back"] >= 2, text  # faults were on
