"""The control thread: the link owners (drivers), their polls, the safety guard and the motion
executors run here, on their own asyncio loop, away from HTTP parsing and WebSocket fan-out.

Why a thread and not a process: the arms' state (latest sample, commanded setpoint, motion
records, estop latch) is read by every route; in one process those reads are plain attribute
reads, a process would need every one of them to become a message. What a thread must get right
is that nothing on the HTTP loop can hold the control loop up: the GIL is handed over every
`SWITCH_INTERVAL_S` (not CPython's 5 ms default), the control loop does no parsing and no
fan-out (samples go into the hub's locked shared log, events cross to the HTTP loop with
`call_soon_threadsafe`), and
everything the API asks of an arm crosses into the control loop (`on_home`). The figures
that back this choice are in the README ("Reliability").

Crossing rules:
- An object started on the control loop remembers it as its `home_loop`; each of its public
  async methods runs its private body there, explicitly: `return await on_home(self.home_loop,
  lambda: self._method(...))` (the caller awaits a wrapped concurrent future; cancelling the
  caller cancels the call). Everything the control thread owns (the estop latch, the guard,
  the executor, the driver queue, the envelope, the tare) changes only that way.
- Called from its own loop (tests that run a service in their loop, the executor itself), it
  is a plain await: no thread, no hop.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import logging
import os
import sys
import threading
from collections.abc import Callable, Coroutine
from typing import Any, TypeVar

from app.runtime.tasks import retrieve, running_loop

log = logging.getLogger(__name__)

#: GIL hand-over interval while the control thread runs, s (CPython's default is 5 ms: a
#: thread busy parsing a large header would hold the control loop for that long each turn).
#: A poll takes the GIL several times (timer, write, reply, publish), each wait up to this
#: long: at 0.5 ms the rbe3001's 500 Hz fell to 429 Hz under bench/hostile.py's 700 hostile
#: clients on one core; at 0.2 ms it kept 499.8 Hz (23 Nov). On 28 Nov the same bench's attack
#: took it to 446-480 Hz at 0.2 ms, at this commit's code and at the README table's (8f612a2)
#: alike (the host; its 500 stalled subscribers alone: 446 Hz); at 0.1 ms, 480-500 Hz
#: (docs/performance.md, "Session 25").
SWITCH_INTERVAL_S = 0.0001
#: Niceness the control thread asks for (Linux: per thread), where permitted (root or
#: CAP_SYS_NICE): on a busy machine the scheduler then runs the link owners and the executor
#: before the HTTP thread and other processes of its session. (Where the kernel shares the CPU
#: between sessions first, autogroup, not before another session's: docs/performance.md,
#: "Session 29".) Without the permission it runs at the default.
CONTROL_NICE = -10
#: How long starting the thread may take, s.
START_TIMEOUT_S = 10.0

T = TypeVar("T")


class ControlThread:
    """A thread running its own asyncio loop until `stop()`."""

    def __init__(self, name: str = "armserver-control") -> None:
        self.name = name
        self.loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._stopped: asyncio.Event | None = None
        self._old_switch: float | None = None
        #: The niceness the thread got (None: not changed, no permission).
        self.niceness: int | None = None

    def start(self) -> None:
        if self._thread is not None:
            return
        ready = threading.Event()

        def run() -> None:
            self.niceness = raise_priority()

            async def main() -> None:
                self.loop = asyncio.get_running_loop()
                self._stopped = asyncio.Event()
                ready.set()
                await self._stopped.wait()

            try:
                asyncio.run(main())
            finally:
                lower_priority()

        self._old_switch = sys.getswitchinterval()
        sys.setswitchinterval(min(self._old_switch, SWITCH_INTERVAL_S))
        self._thread = threading.Thread(target=run, name=self.name, daemon=True)
        self._thread.start()
        if not ready.wait(START_TIMEOUT_S):
            raise RuntimeError("the control thread did not start")

    def submit(self, coro: Coroutine[Any, Any, T]) -> concurrent.futures.Future[T]:
        """Schedule `coro` on the control loop (from any thread)."""
        if self.loop is None:
            coro.close()
            raise RuntimeError("the control thread is not running")
        return asyncio.run_coroutine_threadsafe(coro, self.loop)

    async def run(self, coro: Coroutine[Any, Any, T]) -> T:
        """Await `coro` run on the control loop, from another loop."""
        return await asyncio.wrap_future(self.submit(coro))

    def stop(self, timeout: float = 5.0) -> None:
        """End the loop (after its tasks were closed by their owners) and join the thread."""
        if self._thread is None or self.loop is None or self._stopped is None:
            return
        with contextlib.suppress(RuntimeError):  # loop already closed
            self.loop.call_soon_threadsafe(self._stopped.set)
        self._thread.join(timeout)
        if self._thread.is_alive():
            log.warning("control thread did not end within %.1f s", timeout)
        self._thread = None
        self.loop = None
        if self._old_switch is not None:
            sys.setswitchinterval(self._old_switch)
            self._old_switch = None


# A raised thread starves the kernel's own workers on a busy machine. Linux hands a terminal's
# received bytes (a USB serial adapter's, a pty's) to their reader in a work item run by an
# unbound kworker at niceness 0. Traced beside `stress-ng --cpu 4` with two servo set-ups at
# once (`make test-loaded`'s failure, docs/performance.md "Session 24"), that kworker waited
# 0.45-4.1 s runnable for a CPU while the control thread at -10 woke every 2 ms; with it at 0
# the longest wait was 0.11-0.51 s and no set-up failed. A thread waiting for a terminal's
# bytes above the worker that delivers them waits longer, not less. So while any terminal is
# in use in the process (`TerminalHold`: a serial arm's port, a servo set-up's), every raised
# thread runs at the default niceness; they get theirs back when the last is closed. Links
# over sockets and HID, which the kernel delivers without that worker, keep the raise.
# Brought down to 0, the control thread would share its priority with the HTTP side (parsing,
# fan-out: the process's main thread). Under bench/hostile.py's attack (`--serial-arm`) a server
# with a terminal open kept 311-342 device samples/s of 500 (its estop storm 350-367) with the
# main thread at 0 (and a serial link's own thread left at -10: app/links/threaded.py); with
# the main thread at +5 meanwhile and that thread held too, 380-406 (storm 438-497; +10 did no
# better), three runs each alternated (docs/performance.md, "Session 29"). So while the raised
# threads are held at 0, the main thread runs at HOLD_MAIN_NICE, below them and below the
# kworker, and gets its niceness back with theirs. A thread it starts meanwhile (an
# executor's, a camera's: the HTTP side's) inherits the +5 and gets its niceness back with it;
# raised threads set theirs themselves.
# Only where a thread was raised: the right to raise is the right to come back from +5.

#: Threads running above the default niceness: native id -> the niceness they asked for.
_raised: dict[int, int] = {}
#: Terminals in use (TerminalHold); while there is one, the raised threads run at 0.
_terminals = 0
#: The main thread's niceness before a hold lowered it to HOLD_MAIN_NICE; None: not lowered.
_main_before: int | None = None
_raised_lock = threading.Lock()
#: The main thread's niceness while the raised threads are held at 0 (see above).
HOLD_MAIN_NICE = 5


def _set_niceness(tid: int, niceness: int) -> None:
    with contextlib.suppress(OSError):
        os.setpriority(os.PRIO_PROCESS, tid, niceness)


def _settle_main() -> None:
    """The main thread at HOLD_MAIN_NICE while a terminal holds raised threads at 0, else at
    its own niceness again (under `_raised_lock`)."""
    global _main_before
    main = threading.main_thread().native_id
    if main is None:
        return
    lower = bool(_terminals) and bool(_raised) and main not in _raised
    if lower and _main_before is None:
        with contextlib.suppress(OSError):
            before = os.getpriority(os.PRIO_PROCESS, main)
            os.setpriority(os.PRIO_PROCESS, main, max(before, HOLD_MAIN_NICE))
            _main_before = before
    elif not lower and _main_before is not None:
        # the main thread and every thread it started meanwhile (they inherited its niceness)
        held = max(_main_before, HOLD_MAIN_NICE)
        for tid in thread_ids():
            if tid not in _raised and _niceness(tid) == held:
                _set_niceness(tid, _main_before)
        _main_before = None


def thread_ids() -> list[int]:
    """The native ids of this process's threads (app/arms/dynamixel/practice.py's too)."""
    try:
        return [int(t) for t in os.listdir("/proc/self/task")]
    except OSError:  # (no /proc: the main thread alone)
        main = threading.main_thread().native_id
        return [] if main is None else [main]


def _niceness(tid: int) -> int | None:
    try:
        return os.getpriority(os.PRIO_PROCESS, tid)
    except OSError:  # (it has ended)
        return None


def raise_priority(niceness: int = CONTROL_NICE) -> int | None:
    """Give the calling thread `niceness` if permitted (the control thread's, the link poll
    thread's, app/links/poller.py, and a serial link's own, app/links/threaded.py); the
    niceness it got, or None. While a terminal is in use it runs at the default meanwhile
    (above); `lower_priority` before the thread ends."""
    try:
        tid = threading.get_native_id()
        os.setpriority(os.PRIO_PROCESS, tid, niceness)
        got = os.getpriority(os.PRIO_PROCESS, tid)
    except (OSError, AttributeError):
        return None
    with _raised_lock:
        _raised[tid] = got
        if _terminals:
            _set_niceness(tid, 0)
        _settle_main()
    return got


def lower_priority() -> None:
    """The calling thread ends: forget it (a thread id the kernel gives again is another
    thread's, perhaps another process's)."""
    with _raised_lock:
        _raised.pop(threading.get_native_id(), None)
        _settle_main()


class TerminalHold:
    """A terminal in use by this process, from its open to `release` (idempotent): the raised
    threads run at the default niceness meanwhile, the main thread at HOLD_MAIN_NICE (see
    above)."""

    def __init__(self) -> None:
        global _terminals
        with _raised_lock:
            _terminals += 1
            if _terminals == 1:
                for tid in _raised:
                    _set_niceness(tid, 0)
            _settle_main()
        self._held = True

    def release(self) -> None:
        global _terminals
        with _raised_lock:
            if not self._held:
                return
            self._held = False
            _terminals -= 1
            if _terminals == 0:
                for tid, niceness in _raised.items():
                    _set_niceness(tid, niceness)
            _settle_main()


def terminal_hold(fd: int | None) -> TerminalHold | None:
    """A TerminalHold where `fd` is a terminal's, else None."""
    try:
        return TerminalHold() if fd is not None and os.isatty(fd) else None
    except OSError:
        return None


async def call_in(loop: asyncio.AbstractEventLoop | None,
                  fn: Callable[[], Coroutine[Any, Any, T]]) -> T:
    """`await fn()` on `loop`: directly if that is the running loop (or None), else by
    crossing into it and awaiting the result here."""
    if loop is None or loop is running_loop() or loop.is_closed():
        return await fn()
    return await asyncio.wrap_future(asyncio.run_coroutine_threadsafe(fn(), loop))


async def on_home(loop: asyncio.AbstractEventLoop | None,
                  fn: Callable[[], Coroutine[Any, Any, T]]) -> T:
    """`await fn()` on `loop`, the home loop of the object whose state `fn` changes: the one
    typed way for another thread to ask the control thread anything (an arm's public async
    methods are `return await on_home(self.home_loop, lambda: self._method(...))`). From the
    home loop itself (or before it is started) it is a plain await."""
    return await call_in(loop, fn)


def start_now(loop: asyncio.AbstractEventLoop | None, coro: Coroutine[Any, Any, Any]) -> None:
    """Start `coro` on `loop` from any thread, at once (a task of the running loop when `loop`
    is it or None). Its outcome is not awaited: an error is retrieved and logged at debug."""
    running = running_loop()
    if loop is None or loop is running or loop.is_closed():
        asyncio.ensure_future(coro).add_done_callback(retrieve)
    else:
        asyncio.run_coroutine_threadsafe(coro, loop).add_done_callback(retrieve)
