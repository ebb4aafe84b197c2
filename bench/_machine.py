"""How fast this machine is right now, printed beside a bench's figures.

The development machine is a 2-core virtual machine whose host is shared. On 26 Nov 2026 the
same code measured one rbe3001's sample at 80 µs at 21:24 and at 120-160 µs at 22:12-22:20
(`bench/sample_cost.py`), the machine idle both times, and `make bench-peers` moved with it
(pypot's own figures too). The load average does not show that: the host's other tenants are
not in it. What does, in part, is what a thread pays to wake from a short sleep and run a
little Python cold, which is what an arm's poll does 500 times a second: `wake_us`. Figures
from runs whose yardsticks differ are not comparable; ratios from one run are
(docs/performance.md).
"""

from __future__ import annotations

import os
import select
import statistics
import time


def wake_us(groups: int = 5, n: int = 100) -> float:
    """CPU of this thread, µs, for one wake-up from a 1 ms sleep followed by a sample's worth
    of Python (a dict of a few fields, a little arithmetic): the median over `groups` of the
    mean of `n` (about 0.6 s)."""
    p = select.poll()
    acc = 0.0
    means = []
    for _ in range(groups):
        c0 = time.thread_time()
        for k in range(n):
            p.poll(1)
            d = {"seq": k, "time": k * 0.002, "positions": [k * 0.1, k * 0.2, k * 0.3]}
            acc += d["positions"][1] + d["time"]
        means.append((time.thread_time() - c0) / n * 1e6)
    return statistics.median(means)


def threads_cpu_s(pid: int | str = "self") -> dict[int, float]:
    """CPU time (s) of each thread of process `pid`, by thread id: the scheduler's own count
    in ns (app/lab/supervisor.py `thread_activity`, which the lab's hang rule reads), not the
    10 ms ticks of /stat. A thread that ended meanwhile is left out; a process that is gone
    gives {}."""
    from app.lab.supervisor import thread_activity

    return {tid: ran / 1e9 for tid, (ran, _) in (thread_activity(pid) or {}).items()}


def process_cpu_s(pid: int | str = "self") -> float:
    """CPU time (s) of every thread of process `pid` together (`threads_cpu_s`)."""
    return sum(threads_cpu_s(pid).values())


def describe() -> str:
    """One line: the load average, the cores, and `wake_us` now."""
    return (f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores; a wake-up and "
            f"a little Python cost a thread {wake_us():.0f} µs now (bench/_machine.py)")
