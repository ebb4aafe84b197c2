"""Garbage collection that cannot stall control for long (issue 11).

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
The young generations are collected automatically as before. A full collection can still
pause sampling (when it runs automatically, at most about once a minute under heavy client
churn, or a scheduled one); the motion executor then goes on from its last setpoint (it never
jumps, app/motion/stream.py). Without CPython's incremental collector (3.14) only a process
of its own would make the control loop immune: see the README's reliability section.
"""

from __future__ import annotations

import asyncio
import gc
import logging
import time
from collections.abc import Callable, Mapping
from typing import Any

from app.runtime.tasks import cancel_and_wait

log = logging.getLogger(__name__)

#: Collections of generation 1 between automatic full collections (CPython's default: 10).
GEN2_THRESHOLD = 1000
#: How often a full collection is run here, s.
FULL_EVERY_S = 60.0
#: Longest a due full collection waits for no arm to be moving, s.
FULL_DEFER_MAX_S = 600.0
#: How often a deferred collection looks again, s.
RETRY_S = 0.5

_active = 0  # collectors running in this process (tests run several apps at once)
_saved: tuple[int, int, int] | None = None


class Collector:
    """The server's garbage-collection policy; `busy()` says whether an arm is moving."""

    def __init__(self, busy: Callable[[], bool], every_s: float = FULL_EVERY_S,
                 defer_max_s: float = FULL_DEFER_MAX_S) -> None:
        self.busy = busy
        self.every_s = every_s
        self.defer_max_s = defer_max_s
        self.full_collections = 0
        #: The longest pause of a full collection run here, s.
        self.longest_s = 0.0
        self._task: asyncio.Task[None] | None = None

    def start(self) -> None:
        global _active, _saved
        if self._task is not None:
            return
        if _active == 0:
            _saved = gc.get_threshold()
            gc.collect()
            gc.freeze()
            gc.set_threshold(_saved[0], _saved[1], GEN2_THRESHOLD)
        _active += 1
        self._task = asyncio.get_running_loop().create_task(self._run(), name="gc")

    async def close(self) -> None:
        global _active, _saved
        if self._task is None:
            return
        await cancel_and_wait(self._task)
        self._task = None
        _active -= 1
        if _active == 0 and _saved is not None:
            gc.set_threshold(*_saved)
            gc.unfreeze()
            _saved = None

    async def _run(self) -> None:
        while True:
            await asyncio.sleep(self.every_s)
            waited = 0.0
            while self.busy() and waited < self.defer_max_s:
                await asyncio.sleep(RETRY_S)
                waited += RETRY_S
            self.collect_now()

    def collect_now(self) -> int:
        """One full collection now; the number of unreachable objects found."""
        t0 = time.perf_counter()
        found = gc.collect()
        pause = time.perf_counter() - t0
        self.full_collections += 1
        self.longest_s = max(self.longest_s, pause)
        log.debug("full garbage collection: %d unreachable, %.1f ms", found, pause * 1e3)
        return found


def moving(services: Mapping[str, Any]) -> Callable[[], bool]:
    """`busy()` for a Collector: whether any arm of `services` (name -> ArmService) is
    executing a motion (read from another thread: one attribute read per arm)."""
    def busy() -> bool:
        return any(svc.moving for svc in list(services.values()))
    return busy
