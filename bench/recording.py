"""Recording's cost: what an episode takes on the HTTP loop per frame, whether the arms keep
their sample rate while it records, and how long writing an episode takes.

    python bench/recording.py [--seconds 5] [--episodes 3] [--fps 30] [--no-cameras]

The server in process (the default simulated arms and their simulated cameras, a fresh data
folder); a dataset of every arm (and the first camera), `--episodes` episodes of `--seconds`.
Prints per episode: frames (and the grid's count, seconds x fps), the recorder's work per frame
on the HTTP loop (p50, p99, max, ms: `EpisodeRecorder._tick` timed from outside), each arm's
samples per second while it recorded against before, and the stop's latency (the episode
written: parquet, the video joined, the metadata). Figures depend on the machine and what else
runs on it: quote them from a quiet one.
"""

from __future__ import annotations

import argparse
import asyncio
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import httpx
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from app.config import Settings  # noqa: E402
from app.recording import session  # noqa: E402
from app.web.factory import create_app  # noqa: E402

API = "/api/v1"
TICKS: list[float] = []


def _timed_tick() -> None:
    original = session.EpisodeRecorder._tick

    def tick(self: session.EpisodeRecorder) -> None:
        t = time.perf_counter()
        try:
            original(self)
        finally:
            TICKS.append(time.perf_counter() - t)
    session.EpisodeRecorder._tick = tick  # type: ignore[method-assign]


def _rates(services: dict[str, Any]) -> dict[str, int]:
    return {n: s.hub.published for n, s in services.items()}


async def main(a: argparse.Namespace) -> None:
    _timed_tick()
    settings = Settings(data_dir=tempfile.mkdtemp(prefix="armserver-bench-rec-"), config=None,
                        operator_tokens="", viewer_tokens="", instructor_tokens="",
                        allowed_hosts="armserver.test")
    app = create_app(settings)
    async with app.router.lifespan_context(app):
        transport = httpx.ASGITransport(app=app)
        async with httpx.AsyncClient(transport=transport, base_url="http://armserver.test",
                                     timeout=120) as c:
            await asyncio.sleep(2.0)
            services = app.state.services
            arms = list(services)
            cams = [] if a.no_cameras else [x["name"] for x in
                                            (await c.get(f"{API}/cameras")).json()][:1]
            r = await c.post(f"{API}/recordings", json={"name": "bench", "arms": arms,
                                                         "cameras": cams, "fps": a.fps})
            r.raise_for_status()
            t0, before = time.monotonic(), _rates(services)
            await asyncio.sleep(a.seconds)
            idle = {n: (v - before[n]) / (time.monotonic() - t0)
                    for n, v in _rates(services).items()}
            print(f"arms {arms}, cameras {cams}, {a.fps} fps; samples/s before recording: "
                  + ", ".join(f"{n} {v:.0f}" for n, v in idle.items()))
            for k in range(a.episodes):
                TICKS.clear()
                (await c.post(f"{API}/recordings/bench/episodes")).raise_for_status()
                t0, before = time.monotonic(), _rates(services)
                await asyncio.sleep(a.seconds)
                dt = time.monotonic() - t0
                rec = {n: (v - before[n]) / dt for n, v in _rates(services).items()}
                s0 = time.perf_counter()
                r = await c.post(f"{API}/recordings/bench/episodes/stop")
                r.raise_for_status()
                stop_ms = (time.perf_counter() - s0) * 1e3
                d = r.json()
                frames = d["episode_list"][-1]["length"]
                ticks = np.array(TICKS) * 1e3
                print(f"episode {k}: {frames} frames (grid {a.seconds * a.fps:.0f}); per frame "
                      f"p50 {np.percentile(ticks, 50):.2f} ms, p99 {np.percentile(ticks, 99):.2f}"
                      f" ms, max {ticks.max():.2f} ms; samples/s "
                      + ", ".join(f"{n} {v:.0f}" for n, v in rec.items())
                      + f"; stop (written) {stop_ms:.0f} ms")
            print(f"dataset: {d['episodes']} episodes, {d['frames']} frames in {d['path']}")


if __name__ == "__main__":
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--seconds", type=float, default=5.0)
    p.add_argument("--episodes", type=int, default=3)
    p.add_argument("--fps", type=int, default=30)
    p.add_argument("--no-cameras", action="store_true")
    asyncio.run(main(p.parse_args()))
