"""Cameras: what a detection of a 640x480 frame costs, and how many frames per second 50 MJPEG
clients get from one camera while the arms keep their poll rate.

    python bench/cameras.py [--clients 50] [--seconds 10] [--detections 200]

1. Detection (app/cameras/detect.py, every default colour) on the simulated rbe3001's table
   with six objects, rendered by app/sim/camera.py at 640x480: median and p99, ms.
2. `armserver serve` in a subprocess (simulated arms, one simulated camera each, 10 fps);
   the rbe3001's samples per second (from GET /state's `seq` over a window) with no client,
   then while `--clients` clients read the rbe3001 camera's MJPEG stream: frames each client
   got per second, parts the server dropped for slow clients are not counted, and the
   samples per second meanwhile. Figures, not asserts: run it on a quiet machine.
"""

from __future__ import annotations

import argparse
import asyncio
import statistics
import sys
import time
from pathlib import Path

import httpx

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from app.arms.loading import load_profile  # noqa: E402
from app.cameras.config import DEFAULT_COLORS  # noqa: E402
from app.cameras.detect import detect  # noqa: E402
from app.sim.camera import SimView, render  # noqa: E402
from app.sim.world import World, random_objects  # noqa: E402
from bench._server import pct, server  # noqa: E402

ARM = "rbe3001"


def detection_figures(n: int) -> None:
    profile = load_profile(ARM)
    world = World(profile)
    world.set_scene(random_objects(world, seed=1), world.scene().bins)
    image = render(world, SimView.default_for(profile), 640, 480, noise=0.02, seed=1)
    colors = list(DEFAULT_COLORS)
    found = detect(image, DEFAULT_COLORS, colors, 50)
    times = []
    for _ in range(n):
        t0 = time.perf_counter()
        detect(image, DEFAULT_COLORS, colors, 50)
        times.append(time.perf_counter() - t0)
    print(f"detection 640x480, {len(colors)} colours, {len(found)} objects: "
          f"median {statistics.median(times) * 1e3:.2f} ms  p99 {pct(times, 99) * 1e3:.2f} ms")


async def samples_per_s(client: httpx.AsyncClient, seconds: float) -> float:
    s0 = (await client.get(f"/api/v1/arms/{ARM}/state")).json()["seq"]
    t0 = time.monotonic()
    await asyncio.sleep(seconds)  # the measurement window
    s1 = (await client.get(f"/api/v1/arms/{ARM}/state")).json()["seq"]
    return (s1 - s0) / (time.monotonic() - t0)


async def watch(url: str, seconds: float, counts: list[int], k: int) -> None:
    async with httpx.AsyncClient(timeout=httpx.Timeout(10.0, read=None)) as c:
        async with c.stream("GET", f"{url}/api/v1/cameras/{ARM}/stream") as resp:
            end = time.monotonic() + seconds
            async for chunk in resp.aiter_bytes():
                counts[k] += chunk.count(b"--frame\r\n")
                if time.monotonic() > end:
                    return


async def stream_figures(url: str, clients: int, seconds: float) -> None:
    async with httpx.AsyncClient(base_url=url, timeout=10.0) as c:
        idle = await samples_per_s(c, 3.0)
        counts = [0] * clients
        watchers = [asyncio.create_task(watch(url, seconds, counts, k)) for k in range(clients)]
        await asyncio.sleep(1.0)  # all connected
        loaded = await samples_per_s(c, seconds - 2.0)
        await asyncio.gather(*watchers)
        detail = (await c.get(f"/api/v1/cameras/{ARM}")).json()
    per = [n / seconds for n in counts]
    print(f"{ARM} samples/s: {idle:.1f} with no client, {loaded:.1f} with {clients} MJPEG "
          f"clients ({loaded / idle:.3f})")
    print(f"MJPEG frames/s per client: median {statistics.median(per):.1f}  min {min(per):.1f} "
          f"(camera at {detail['fps']:g} fps; {sum(counts)} parts in all)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--clients", type=int, default=50)
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--detections", type=int, default=200)
    args = ap.parse_args()
    detection_figures(args.detections)
    with server() as srv:
        asyncio.run(stream_figures(srv.url, args.clients, args.seconds))


if __name__ == "__main__":
    main()
