"""Thread or process for the control loop (app/runtime/control_thread.py)? What one crossing costs.

    python bench/crossing.py [--n 5000]

A route that asks an arm something crosses from the HTTP loop into the control loop and back.
Measured here for the two choices: a coroutine run on the control thread's loop
(`ControlThread.run`, what the server does) and the same small request sent to a control
process over a pipe and answered (the cheapest process boundary: no serialisation beyond a
small pickle). Also what a sample costs to hand over: `call_soon_threadsafe` (thread) against a
pickled sample through a pipe (process). Median and 99th percentile, microseconds.
"""

from __future__ import annotations

import argparse
import asyncio
import multiprocessing as mp
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from app.runtime.control_thread import ControlThread  # noqa: E402

SAMPLE = {"seq": 1, "time": 0.0, "positions": [0.1, 0.2, 0.3], "velocities": [0.0, 0.0, 0.0],
          "torques": None, "tip": {"x": 0.1, "y": 0.2, "z": 0.3},
          "tip_velocity": {"x": 0.0, "y": 0.0, "z": 0.0}, "tip_force": None, "gripper": None,
          "motion": None, "estop": False, "link": "up", "stale": False}


def _child(conn: mp.connection.Connection) -> None:
    while True:
        msg = conn.recv()
        if msg is None:
            return
        conn.send(msg)


def _figures(xs: list[float]) -> str:
    xs = sorted(xs)
    return (f"median {statistics.median(xs) * 1e6:7.1f} us  "
            f"p99 {xs[int(len(xs) * 0.99)] * 1e6:7.1f} us")


async def thread_round_trips(n: int) -> list[float]:
    control = ControlThread()
    control.start()

    async def ask() -> dict[str, object]:
        return SAMPLE

    out = []
    try:
        for _ in range(n):
            t0 = time.perf_counter()
            await control.run(ask())
            out.append(time.perf_counter() - t0)
    finally:
        control.stop()
    return out


def process_round_trips(n: int) -> list[float]:
    parent, child = mp.Pipe()
    proc = mp.Process(target=_child, args=(child,), daemon=True)
    proc.start()
    out = []
    for _ in range(n):
        t0 = time.perf_counter()
        parent.send(("status", "rbe3001"))
        parent.recv()
        out.append(time.perf_counter() - t0)
    for _ in range(n):  # a sample back, as the process would stream them
        t0 = time.perf_counter()
        parent.send(SAMPLE)
        parent.recv()
        out.append(time.perf_counter() - t0)
    parent.send(None)
    proc.join(5)
    return out


async def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--n", type=int, default=5000)
    n = ap.parse_args().n
    thread = await thread_round_trips(n)
    process = process_round_trips(n)
    print(f"thread  (run_coroutine_threadsafe, there and back): {_figures(thread)}")
    print(f"process (pipe, request and reply):                  {_figures(process[:n])}")
    print(f"process (pipe, one sample there and back):          {_figures(process[n:])}")


if __name__ == "__main__":
    asyncio.run(main())
