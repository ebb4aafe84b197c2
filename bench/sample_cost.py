"""What one arm's sample costs the server (issue 27): CPU per sample and per arm at its poll rate.

    python bench/sample_cost.py [--model rbe3001] [--seconds 10] [--profile 25]

Serves the arm type's simulated hardware with `armserver sim MODEL --listen tcp://...` in
another process, and in this one runs the arm as the server does (`ArmService` over a
`socket://` serial link, on a plain asyncio loop like the control thread's), with nobody
subscribed. Prints the samples it published, this process's CPU time per sample (µs) and per
arm at the poll rate (% of a core; the issue's goal: 3 %, 60 µs a sample at 500 Hz).
`--profile N` runs the window under cProfile and prints the N costliest functions (cProfile
slows what it measures: read its shares, not its times).

The machine's other load shows in the figures: on a shared machine compare runs made back to
back (ratios), not figures from different days.
"""

from __future__ import annotations

import argparse
import asyncio
import cProfile
import os
import pstats
import socket
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from app.arms.loading import load_profile  # noqa: E402
from app.config import homed_at_start  # noqa: E402
from app.service import ArmService  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent


def _port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


async def run(model: str, port: int, seconds: float, prof: cProfile.Profile | None) -> None:
    base = load_profile(model).model_dump()
    base["link"].update(kind="serial", address=f"socket://127.0.0.1:{port}")
    from app.arms.loading import check_profile

    profile = homed_at_start(check_profile(base))
    svc = ArmService(profile)
    await svc.start()
    try:
        deadline = time.monotonic() + 30
        while svc.hub.published < 100:  # noqa: ASYNC110 - a bench, polling its own arm
            if time.monotonic() > deadline:
                raise RuntimeError("the arm did not come up")
            await asyncio.sleep(0.05)
        await asyncio.sleep(1.0)  # past the set-up
        n0, c0, t0 = svc.hub.published, os.times(), time.monotonic()
        if prof is not None:
            prof.enable()
        await asyncio.sleep(seconds)
        if prof is not None:
            prof.disable()
        c1 = os.times()
        n, wall = svc.hub.published - n0, time.monotonic() - t0
        user, system = c1.user - c0.user, c1.system - c0.system
        cpu = user + system
    finally:
        await svc.close()
    rate = n / wall
    per = cpu / n
    print(f"{model}: {n} samples in {wall:.1f} s ({rate:.0f}/s, poll_hz "
          f"{profile.link.poll_hz:.0f}); CPU {1e6 * per:.0f} µs a sample, "
          f"({1e6 * user / n:.0f} user, {1e6 * system / n:.0f} system), "
          f"{100 * cpu / wall:.1f} % of a core for this arm")


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--model", default="rbe3001")
    p.add_argument("--seconds", type=float, default=10.0)
    p.add_argument("--profile", type=int, default=0, metavar="N")
    args = p.parse_args()
    port = _port()
    env = {k: v for k, v in os.environ.items() if not k.startswith("ARMSERVER_")}
    sim = subprocess.Popen([sys.executable, "-m", "app.cli", "sim", args.model, "--listen",
                            f"tcp://127.0.0.1:{port}"], cwd=ROOT, env=env,
                           stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        time.sleep(1.0)  # the simulator listens (the link retries with backoff if not yet)
        prof = cProfile.Profile() if args.profile else None
        asyncio.run(run(args.model, port, args.seconds, prof))
        if prof is not None:
            pstats.Stats(prof).sort_stats("tottime").print_stats(args.profile)
    finally:
        sim.terminate()
        sim.wait(10)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
