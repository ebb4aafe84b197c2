"""The HTTP thread's CPU for a Dynamixel goal `PUT` (issue 23), and where it goes.

    python bench/goal_http.py [--n 1000] [--profile 40] [--root DIR]

The app of `create_app` (no cameras) runs its lifespan in this process, the arms on the
control thread as `armserver serve` runs them; each goal is one call of the ASGI app with the
scope, headers and body the harness's client sends (../shared/peers/rtt_armserver.py: `PUT
.../angler/dynamixel/3/registers/goal_position`, `{"raw": ...}`), 35 ms apart (the step rule
paces pass-through goals: app/safety/guard.py `PASSTHROUGH_STEP_S`). Around each call it
reads the calling thread's CPU time (`time.thread_time`): the middleware, the route, the
crossing's HTTP half and the answer, not the control thread's part. It prints p50, p90 and
p99 of that, and with `--profile N` the N largest entries of a cProfile (timed by thread CPU,
so a wait for the control thread or a GIL hand-over costs nothing) by cumulative and by own
time. `--root DIR` imports the app from another checkout (an export of an older commit:
`git archive <commit> | tar -x -C DIR`), for before and after. No HTTP parsing or socket:
`bench/goal_trace.py` has those hops.
"""

from __future__ import annotations

import argparse
import asyncio
import cProfile
import json
import os
import pstats
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
_root = sys.argv[sys.argv.index("--root") + 1] if "--root" in sys.argv else str(ROOT)
sys.path.insert(0, _root)

GOAL = "/api/v1/arms/angler/dynamixel/3/registers/goal_position"
#: The harness's client's request head (httpx), but for the body's length.
HEADERS = [(b"host", b"127.0.0.1:8000"), (b"accept", b"*/*"),
           (b"accept-encoding", b"gzip, deflate"), (b"connection", b"keep-alive"),
           (b"user-agent", b"python-httpx/0.28.1"), (b"content-type", b"application/json")]


async def call(app: Any, method: str, path: str, body: bytes = b"") -> tuple[int, bytes]:
    scope = {"type": "http", "asgi": {"version": "3.0", "spec_version": "2.3"},
             "http_version": "1.1", "server": ("127.0.0.1", 8000), "client": ("127.0.0.1", 5),
             "scheme": "http", "method": method, "root_path": "", "path": path,
             "raw_path": path.encode(), "query_string": b"", "state": {},
             "headers": HEADERS + [(b"content-length", str(len(body)).encode())]}
    sent = False
    out: list[Any] = []

    async def receive() -> Any:
        nonlocal sent
        if not sent:
            sent = True
            return {"type": "http.request", "body": body, "more_body": False}
        await asyncio.Event().wait()  # the client stays connected

    async def send(message: Any) -> None:
        out.append(message)
    await app(scope, receive, send)
    return int(out[0]["status"]), b"".join(m.get("body", b"") for m in out[1:])


async def run(n: int, top: int) -> None:
    from app.config import Settings
    from app.web.factory import create_app

    app = create_app(Settings(config=None), camera_configs=[])
    async with app.router.lifespan_context(app):
        deadline = time.monotonic() + 30
        while True:  # the angler's first sample
            status, _ = await call(app, "GET", "/api/v1/arms/angler/state")
            if status == 200 or time.monotonic() > deadline:
                break
            await asyncio.sleep(0.05)
        _, body = await call(app, "GET", GOAL.replace("goal_position", "present_position"))
        start = int(json.loads(body)["raw"])
        prof = cProfile.Profile(time.thread_time) if top else None
        cpu: list[float] = []
        statuses: dict[int, int] = {}
        warm = min(50, n // 10)
        for i in range(n):
            goal = start + (30 if i % 2 else -30)
            payload = json.dumps({"raw": goal}).encode()
            t0 = time.thread_time()
            if prof is not None and i >= warm:
                prof.enable()
            status, _ = await call(app, "PUT", GOAL, payload)
            if prof is not None and i >= warm:
                prof.disable()
            if i >= warm:
                cpu.append(time.thread_time() - t0)
            statuses[status] = statuses.get(status, 0) + 1
            await asyncio.sleep(0.035)
        cpu.sort()
        print(f"{len(cpu)} goals (after {warm} not counted), answers {statuses}, load average "
              f"{os.getloadavg()[0]:.2f}" + (" (profiled: slower)" if prof else ""))
        print("HTTP thread CPU a goal PUT, us: p50 {:.0f}  p90 {:.0f}  p99 {:.0f}".format(
            *(cpu[min(len(cpu) - 1, int(q * len(cpu)))] * 1e6 for q in (.5, .9, .99))))
        if prof is not None:
            stats = pstats.Stats(prof)
            stats.sort_stats("cumulative").print_stats(top)
            stats.sort_stats("tottime").print_stats(top)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--n", type=int, default=1000, help="goals (default 1000)")
    ap.add_argument("--profile", type=int, default=0, metavar="N",
                    help="print the N largest entries of a cProfile by thread CPU")
    ap.add_argument("--root", help="import the app from this checkout")
    args = ap.parse_args()
    os.environ.setdefault("ARMSERVER_DATA_DIR", tempfile.mkdtemp(prefix="goal-http-"))
    asyncio.run(run(args.n, args.profile))


if __name__ == "__main__":
    main()
