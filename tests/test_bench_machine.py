"""What the benches read from /proc (bench/_machine.py): a process's CPU time in the kernel's
ticks, its ended threads' included, and its threads by niceness. Every bench's CPU figure (the
server's, the simulators', the front's) and bench/hostile.py's niceness line come from these,
so they are checked against a real child process whose CPU and niceness are known."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "bench"))

import _machine  # noqa: E402  (bench/_machine.py)
from _wait import wait_until  # noqa: E402

#: The child's work: a thread that spins for SPIN_S of CPU (nearly all of it user time) and
#: ends, then the main thread says so and waits for its stdin to close.
CHILD = textwrap.dedent("""
    import os, sys, threading, time
    os.setpriority(os.PRIO_PROCESS, 0, 5)  # (the main thread; the spinner inherits it)
    def spin():  # (user time: the clock, a system call, read once in 100,000 steps)
        t, n = time.thread_time(), 0
        while time.thread_time() - t < {spin}:
            for _ in range(100_000):
                n += 1
    worker = threading.Thread(target=spin)
    worker.start()
    worker.join()
    print("spun", flush=True)
    sys.stdin.read()
""")
SPIN_S = 0.3


def test_a_process_cpu_counts_its_ended_threads_and_its_niceness_is_read() -> None:
    child = subprocess.Popen([sys.executable, "-c", CHILD.format(spin=SPIN_S)],
                             stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert child.stdout is not None and child.stdout.readline() == "spun\n"
        # (a joined thread's task is gone from /proc a moment after `join` returns)
        wait_until(lambda: len(os.listdir(f"/proc/{child.pid}/task")) == 1,
                   what="the spinning thread's task gone")
        fields = _machine.proc_stat(child.pid)
        assert fields[0] in "RSD"  # proc(5)'s field 3, the state, first
        assert int(fields[1]) == os.getpid()  # field 4, the parent
        # the spinning thread has ended: the living threads' count misses it, the ticks do not
        assert _machine.ticks_cpu_s(child.pid) >= SPIN_S - 0.05
        assert _machine.process_cpu_s(child.pid) < SPIN_S / 2
        assert _machine.ticks_cpu_s(child.pid, part=slice(0, 1)) >= SPIN_S - 0.1  # user time
        assert _machine.ticks_cpu_s(child.pid, os.getpid()) > _machine.ticks_cpu_s(child.pid)
        assert _machine.threads_by_niceness(child.pid) == {5: 1}
    finally:
        child.communicate("")
    # a process that is gone: nothing, and no CPU
    wait_until(lambda: not Path(f"/proc/{child.pid}").exists(), what="the child reaped")
    assert _machine.proc_stat(child.pid) == []
    assert _machine.ticks_cpu_s(child.pid) == 0.0
    assert _machine.threads_by_niceness(child.pid) == {}
