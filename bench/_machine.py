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
from pathlib import Path


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


def proc_stat(pid: int | str = "self", tid: int | None = None) -> list[str]:
    """The fields of /proc/PID/stat (of thread `tid`'s: /proc/PID/task/TID/stat) after the
    command's name, which may hold spaces and parentheses: [0] is proc(5)'s field 3 (`state`),
    field N is [N - 3]. [] for a process or thread that is gone."""
    path = f"/proc/{pid}/stat" if tid is None else f"/proc/{pid}/task/{tid}/stat"
    try:
        return Path(path).read_text().rsplit(")", 1)[1].split()
    except OSError:
        return []


def ticks_cpu_s(*pids: int | str, part: slice = slice(0, 2)) -> float:
    """User and system CPU time of processes `pids` together, s, their ended threads' included
    (proc(5)'s `utime` and `stime`, in the kernel's clock ticks: what a process cost over a
    window; `threads_cpu_s` is finer but knows only the living threads). `part`: slice(0, 1)
    user time alone, slice(1, 2) system time alone. A process that is gone counts 0."""
    ticks = sum(int(x) for pid in pids for x in proc_stat(pid)[11:13][part])
    return ticks / os.sysconf("SC_CLK_TCK")


def threads_by_niceness(pid: int | str) -> dict[int, int]:
    """How many of process `pid`'s threads run at each niceness (proc(5)'s field 19)."""
    out: dict[int, int] = {}
    for task in Path(f"/proc/{pid}/task").glob("*"):
        f = proc_stat(pid, int(task.name))
        if f:
            out[int(f[16])] = out.get(int(f[16]), 0) + 1
    return dict(sorted(out.items()))


def describe() -> str:
    """One line: the load average, the cores, and `wake_us` now."""
    return (f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores; a wake-up and "
            f"a little Python cost a thread {wake_us():.0f} µs now (bench/_machine.py)")
