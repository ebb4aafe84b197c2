"""Garbage collection that cannot stall control for long (issues 11 and 23).

CPython's cyclic collector stops every thread while it runs, the control thread too (it holds
the GIL). A full (generation 2) collection walks every tracked object of the process: with
500 stalled telemetry subscribers and 200 slowloris sockets connected (bench/hostile.py) that
was about 200,000 objects and 140-180 ms, once every 0.8 s, which is what held the control
loop up (sample rate -25 %, worst gap 150-180 ms; measured with a `gc.callbacks` timer).
Collections of the young generations took 5-9 ms.

So, while a server runs:
- the objects that exist once the arms are up (modules, classes, the app) are frozen
  (`gc.freeze()`): no collection walks them again;
- automatic full collections are `GEN2_THRESHOLD` times rarer (CPython runs one after
  `threshold2` collections of generation 1; default 10);
- a full collection is run here every `FULL_EVERY_S`, at a moment when no arm is executing a
  motion, or after `FULL_DEFER_MAX_S` of waiting for one, so cyclic garbage is still freed.
The young generations (issue 23). A young collection stops every thread as a full one does,
and CPython starts one at the allocation that crosses generation 0's threshold: a command's
own path (HTTP parsing, validation, the check, the write) allocates, so that is where they
fell. In a traced run of 1,000 Dynamixel goals (bench/goal_trace.py) 184 goals met one (a
goal is some 7 ms in 80), and a generation-1 or a full one was in 15 of the slowest 20, which
set the goal's p99 (a generation-1 collection walks the young generations' thousands of live
samples: 2-4 ms of CPU, more with the trace's own records). So:
- the policy collects the young generations itself, every `YOUNG_EVERY_S`, generation 1 at
  every third (`YOUNG_GEN1_AFTER`): at a wake-up the control loop makes anyway once one is
  due (`young_if_due`: an arm's hand-over of replies, a poll's sample), else at its own
  timer's (`YOUNG_TIMER_S` after the last; session 41: an idle loop was woken 20 times a
  second for them). The collections then come at moments of the loop, not of a command,
  and a command's allocations seldom reach the threshold (which stays, for bursts the policy
  does not keep up with). At every `YOUNG_EVERY_S`, not
  once CPython's count says one is due (issue 27): that count is the allocations less the
  deallocations of tracked objects of any generation, so a process that frees old objects as
  fast as it makes new ones (the telemetry logs: a sample in, the oldest out) keeps it near
  zero while its youngest generation grows without bound. A lab worker of 16 arms at 500 Hz
  had 64,000 samples' containers there after 4 s, and the young collection that came at last
  took 20-30 ms of CPU with every thread stopped: an estop's 50-140 ms tail (bench/lab.py);
- a command in flight holds automatic collections off (`hold`): a pass-through goal
  (`ArmService.command_passthrough`) from the facade's call until `HOLD_S` later, by when its
  write, the poll after it and the sample that shows the move are through; the collection its
  allocations made due runs when the hold ends. No hold is granted while more than
  `HOLD_MAX_PENDING` times generation 0's threshold waits, so commands back to back cannot put
  collections off for good; the timer and a due full collection wait for no hold to be active.

A full collection can still pause sampling (when it runs automatically, at most about once a
minute under heavy client churn, or a scheduled one); the motion executor then goes on from
its last setpoint (it never jumps, app/motion/stream.py). Without CPython's incremental
collector (3.14) only a process of its own would make the control loop immune: see the
README's reliability section.
"""

from __future__ import annotations

import asyncio
import gc
import logging
import threading
import time
from collections.abc import Callable, Mapping
from typing import Any

from app.runtime.tasks import cancel_and_wait, running_loop

log = logging.getLogger(__name__)

#: Collections of generation 1 between automatic full collections (CPython's default: 10).
GEN2_THRESHOLD = 1000
#: How often a full collection is run here, s.
FULL_EVERY_S = 60.0
#: Longest a due full collection waits for no arm to be moving, s.
FULL_DEFER_MAX_S = 600.0
#: How often a deferred collection looks again, s.
RETRY_S = 0.5

#: How often the policy runs a young collection, s: about 1,800 samples' containers a second
#: are kept by the arms' telemetry logs (three simulated arms), 90 in a timer's period; 16,000
#: in a lab worker of 16 arms at 500 Hz, 800 in a period (a collection of them: well under a
#: millisecond).
YOUNG_EVERY_S = 0.05
#: The policy's own timer wakes the loop for a young collection only once none has run for
#: this long: the loop's other wake-ups run a due one first (`young_if_due`: an arm at rest
#: hands its replies over every 100 ms, a moving or read arm polls every 2 ms), so an idle
#: control loop is not woken 20 times a second for it (issue 27: at rest, each wake-up of the
#: control loop cost it a few hundred microseconds of a slow hour's CPU; session 41).
YOUNG_TIMER_S = 0.15
#: Generation 0's collections after which the policy's next is of generation 1 (CPython's own
#: second threshold is 10): every sample a log keeps goes through generation 1, so a worker of
#: 16 arms had 8,000 containers there at 10, a 1-4.5 ms collection; at 3, about 2,400.
YOUNG_GEN1_AFTER = 3
#: How long a command in flight holds automatic collections off, s: a pass-through goal's
#: check, write and status reply, the poll after it (its wait for the servo's first tick, at
#: most a poll period: 5 ms at 200 Hz) and the moved sample's way to a WebSocket took 2-8 ms
#: in a traced run (bench/goal_trace.py); 20 ms leaves room for a loaded machine.
HOLD_S = 0.02
#: No hold is granted while more than this many times generation 0's threshold of
#: allocations wait for a collection (a stream of goals: collections run late, not never).
HOLD_MAX_PENDING = 4
#: A hold whose release did not come this long after its end (its loop closed) is let go.
HOLD_LOST_S = 1.0

_active = 0  # collectors running in this process (tests run several apps at once)
#: The collector whose young collections `young_if_due` runs (the last started), and when the
#: policy last ran one (`time.monotonic()`).
_young_by: Collector | None = None
_last_young = 0.0
_saved: tuple[int, int, int] | None = None
_hold_lock = threading.Lock()
_held = False  # automatic collections disabled by a hold (and by nothing else)
_held_until = 0.0  # time.monotonic() when the last hold ends
#: Holds granted and refused in this process (refused: collections due, or none running).
holds = {"granted": 0, "refused": 0}


def hold(seconds: float = HOLD_S) -> bool:
    """Hold CPython's automatic collections off for `seconds` from now: what a command in
    flight does so that no collection (which stops every thread) falls between it and the
    sample that shows it. Called on a running event loop (the release is its timer), from any
    thread; only while a server's policy runs (a `Collector` started), and not while more than
    `HOLD_MAX_PENDING` young generations of allocations wait. Explicit `gc.collect()` calls
    are not held. True if held."""
    global _held, _held_until
    loop = running_loop()
    now = time.monotonic()
    with _hold_lock:
        due = gc.get_count()[0] > HOLD_MAX_PENDING * max(1, gc.get_threshold()[0])
        if _held and (due or now > _held_until + HOLD_LOST_S):
            _let_go()  # commands back to back, or a release lost with its loop
        if not _held:
            if _active == 0 or loop is None or due or not gc.isenabled():
                holds["refused"] += 1
                return False
            gc.disable()
            _held = True
        _held_until = max(_held_until, now + seconds)
        holds["granted"] += 1
    assert loop is not None
    loop.call_later(seconds, _release)
    return True


def held() -> bool:
    """Whether a hold keeps automatic collections off now."""
    return _held


def _release() -> None:
    """A hold's timer: collections come back once the last hold has ended (the collection
    that came due meanwhile runs at the next allocation)."""
    with _hold_lock:
        if _held and time.monotonic() >= _held_until - 0.001:
            _let_go()


def _let_go() -> None:
    global _held, _held_until
    _held_until = 0.0
    if _held:
        _held = False
        gc.enable()


class Collector:
    """The server's garbage-collection policy; `busy()` says whether an arm is moving (a due
    full collection also waits while a command's `hold` is active)."""

    def __init__(self, busy: Callable[[], bool], every_s: float = FULL_EVERY_S,
                 defer_max_s: float = FULL_DEFER_MAX_S) -> None:
        self.busy = busy
        self.every_s = every_s
        self.defer_max_s = defer_max_s
        self.full_collections = 0
        #: Young collections run by the policy's timer (CPython's own are not counted).
        self.young_collections = 0
        #: The longest pause of a full collection run here, s.
        self.longest_s = 0.0
        self._task: asyncio.Task[None] | None = None
        self._young: asyncio.Task[None] | None = None

    def start(self, collect: bool = True) -> None:
        """Freeze what exists (the first collector of the process; `collect`: after a full
        collection, so no garbage is frozen with it) and start the timers."""
        global _active, _saved
        if self._task is not None:
            return
        if _active == 0:
            _saved = gc.get_threshold()
            if collect:
                gc.collect()
            gc.freeze()
            gc.set_threshold(_saved[0], _saved[1], GEN2_THRESHOLD)
        _active += 1
        loop = asyncio.get_running_loop()
        self._task = loop.create_task(self._run(), name="gc")
        self._young = loop.create_task(self._run_young(), name="gc-young")

    async def close(self) -> None:
        global _active, _saved, _young_by
        if self._task is None:
            return
        await cancel_and_wait(self._task)
        await cancel_and_wait(self._young)
        self._task = self._young = None
        if _young_by is self:
            _young_by = None
        _active -= 1
        if _active == 0:
            with _hold_lock:
                _let_go()
        if _active == 0 and _saved is not None:
            gc.set_threshold(*_saved)
            gc.unfreeze()
            _saved = None

    async def _run(self) -> None:
        while True:
            await asyncio.sleep(self.every_s)
            waited = 0.0
            while (self._busy() or _held) and waited < self.defer_max_s:
                await asyncio.sleep(RETRY_S)
                waited += RETRY_S
            self.collect_now()

    def _busy(self) -> bool:
        """`busy()`, or False (logged) if it fails: the policy's task must not end on an arm's
        reading it could not judge."""
        try:
            return bool(self.busy())
        except Exception:  # noqa: BLE001 - any arm's state; the collection then runs as due
            log.debug("gc policy: busy() failed", exc_info=True)
            return False

    async def _run_young(self) -> None:
        global _young_by
        _young_by = self
        while True:
            wait = _last_young + YOUNG_TIMER_S - time.monotonic()
            if wait > 0:  # (another wake-up ran one meanwhile)
                await asyncio.sleep(wait)
                continue
            if self.collect_young() is None:  # held off (or collection off): look again soon
                await asyncio.sleep(YOUNG_EVERY_S)

    def collect_young(self) -> int | None:
        """A young collection now, unless a hold is active or automatic collection is off (a
        threshold of 0): generation 1 once generation 0 has been collected `YOUNG_GEN1_AFTER`
        times since, else generation 0; whatever CPython's count of generation 0 says (the
        module doc: it stays near zero while old samples are freed as new ones come). The
        generation collected, or None."""
        global _last_young
        if _held or not gc.isenabled():
            return None
        _, c1, _ = gc.get_count()
        if gc.get_threshold()[0] <= 0:
            return None
        gen = 1 if c1 >= YOUNG_GEN1_AFTER else 0
        gc.collect(gen)
        _last_young = time.monotonic()
        self.young_collections += 1
        return gen

    def collect_now(self) -> int:
        """One full collection now; the number of unreachable objects found."""
        t0 = time.perf_counter()
        found = gc.collect()
        pause = time.perf_counter() - t0
        self.full_collections += 1
        self.longest_s = max(self.longest_s, pause)
        log.debug("full garbage collection: %d unreachable, %.1f ms", found, pause * 1e3)
        return found


def young_if_due() -> None:
    """A young collection now if the policy's is due (`YOUNG_EVERY_S` since its last): called
    at a wake-up the loop makes anyway (an arm's hand-over of replies, a poll's sample), so that
    the policy's own timer (`YOUNG_TIMER_S`) seldom has to wake it. From any thread."""
    col = _young_by
    if col is not None and time.monotonic() - _last_young >= YOUNG_EVERY_S:
        col.collect_young()


def moving(services: Mapping[str, Any]) -> Callable[[], bool]:
    """`busy()` for a Collector: whether any arm of `services` (name -> ArmService) is in
    motion, a planned one or its joints on their way after a pass-through goal (`in_motion`;
    read from another thread: a few attribute reads per arm)."""
    def busy() -> bool:
        return any(svc.in_motion for svc in list(services.values()))
    return busy
