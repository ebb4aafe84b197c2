"""The lab's worker processes: start each, see it ready, restart it when it dies, stop them all.

A worker is `python -m app.lab.worker` on its own Unix socket in the lab's 0700 folder. Its
watcher task awaits the process's exit; unless the lab is stopping, it starts it again at once
(then after RESTART_BACKOFF_S, doubling to RESTART_MAX_S while it keeps dying young), so a
killed worker's arms are back in about the time the server takes to start (its imports and its
arms: about 2 s here). The other workers are separate processes with their own control threads
and links: a death elsewhere costs them nothing (tests/test_lab_workers.py kills one with
SIGKILL and reads the other's samples throughout).

A worker that hangs without exiting (a deadlock, SIGSTOP) is found by its prober: once ready,
the worker's `GET /api/v1/health` is asked every PROBE_EVERY_S over its socket and must answer
within PROBE_DEADLINE_S. At the first miss the worker is not `ready` (its arms are 503
`link_down`, the lab-wide lists leave it out instead of waiting for it) and is asked again at
once; an answer makes it ready again; PROBE_MISSES misses in a row and it is stopped
(SIGTERM, then SIGKILL after KILL_GRACE_S: a stopped or deadlocked process runs no handler)
and restarted as a dead one is (tests/test_lab_workers.py stops one with SIGSTOP). The
figures put a hung worker's arms back within about 5 s (at most 2.5 s to be sure it
hangs, 0.5 s of grace, then its start: 1.5-2 s), while a loaded worker, whose health answers
in milliseconds, would have to miss a whole second twice in a row to be taken for hung.

`ready` is the front's one question: has the worker answered its health since it last started
(and its last probe).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import signal
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from app.lab.upstream import Upstream, UpstreamError

log = logging.getLogger("armserver.lab")

#: Wait before restarting a worker that died, s; doubles while it dies within YOUNG_S of its
#: start, up to RESTART_MAX_S (a worker that cannot start does not spin a core).
RESTART_BACKOFF_S = 0.05
RESTART_MAX_S = 5.0
YOUNG_S = 10.0
#: How often a starting worker's health is asked, s, and how long one answer may take.
READY_POLL_S = 0.05
READY_ASK_S = 1.0
#: How long the other workers wait for the first one at start-up, s (then they start anyway).
FIRST_READY_S = 60.0
#: A ready worker's health is asked this often, s, and must answer within PROBE_DEADLINE_S;
#: PROBE_MISSES misses in a row and it is killed and restarted (a hung worker).
PROBE_EVERY_S = 0.5
PROBE_DEADLINE_S = 1.0
PROBE_MISSES = 2
#: How long a hung worker gets after its SIGTERM before its SIGKILL, s.
KILL_GRACE_S = 0.5
#: How long a stopping worker gets after its SIGTERM (beyond the server's own graceful
#: shutdown) before it is killed, s.
STOP_GRACE_S = 5.0


@dataclass
class Worker:
    """One worker process and the front's connection pool to it."""

    index: int
    arms: tuple[str, ...]
    uds: Path
    client: Upstream
    proc: asyncio.subprocess.Process | None = None
    ready: bool = False
    starts: int = 0
    last_error: str | None = None
    #: Times it was killed for not answering its health (a hung worker).
    hangs: int = 0

    @property
    def pid(self) -> int | None:
        return self.proc.pid if self.proc is not None else None


class Supervisor:
    """Runs `workers` (their arms fixed by the plan) until `stop()`."""

    def __init__(self, workers: list[Worker], settings_file: Path, count: int) -> None:
        self.workers = workers
        self._settings_file = settings_file
        self._count = count
        self._stopping = False
        self._tasks: list[asyncio.Task[None]] = []
        #: Set once the first worker answered: it has opened (made, migrated) the store, which
        #: the others then open as it is (SQLite's journal-mode switch and the migrations of
        #: a fresh database are not safe to race from several processes).
        self._first_ready = asyncio.Event()

    def start(self) -> None:
        """Start every worker's watcher (it starts the worker, and again when it dies): the
        first worker, then the others once it answers (`_first_ready`). The front serves at
        once: until a worker is ready its arms are `down` in health and 503 `link_down` (a
        client waits for health `ok`)."""
        self._tasks = [asyncio.create_task(self._watch(w), name=f"lab-worker-{w.index}")
                       for w in self.workers]

    async def _spawn(self, w: Worker) -> asyncio.subprocess.Process:
        w.uds.unlink(missing_ok=True)
        return await asyncio.create_subprocess_exec(
            sys.executable, "-m", "app.lab.worker", "--settings", str(self._settings_file),
            "--index", str(w.index), "--workers", str(self._count), "--uds", str(w.uds),
            "--parent", str(os.getpid()), start_new_session=True)

    async def _watch(self, w: Worker) -> None:
        backoff = RESTART_BACKOFF_S
        if w is not self.workers[0]:
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(FIRST_READY_S):
                    await self._first_ready.wait()
        while not self._stopping:
            started = time.monotonic()
            w.proc = await self._spawn(w)
            w.starts += 1
            log.info("worker %d (pid %d): %s", w.index, w.proc.pid, ", ".join(w.arms))
            hangs = w.hangs
            prober = asyncio.create_task(self._probe(w, w.proc))
            code = await w.proc.wait()
            prober.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await prober
            w.ready = False
            w.client.reset()  # its kept-alive connections lead nowhere now
            if self._stopping:
                return
            w.last_error = (f"worker {w.index} " + ("stopped answering its health: killed"
                            if w.hangs != hangs else f"exited with {code}") + "; restarting")
            log.error("worker %d (pid %d) exited with %s: restarting its arms (%s)", w.index,
                      w.proc.pid, code, ", ".join(w.arms))
            backoff = backoff * 2 if time.monotonic() - started < YOUNG_S else RESTART_BACKOFF_S
            backoff = min(backoff, RESTART_MAX_S)
            await asyncio.sleep(backoff)

    async def _probe(self, w: Worker, proc: asyncio.subprocess.Process) -> None:
        """Until `proc` exits or the lab stops: see it ready, then ask its health every
        PROBE_EVERY_S; kill it after PROBE_MISSES misses in a row (the watcher restarts
        it)."""
        await self._until_ready(w)
        misses = 0
        while True:
            if not misses:  # after a miss, ask again at once
                await asyncio.sleep(PROBE_EVERY_S)
            answered = await self._answers(w)
            if self._stopping:  # the lab stops: its workers stop answering, on purpose
                return
            if answered:
                misses = 0
                w.ready, w.last_error = True, None
                continue
            misses += 1
            w.ready = False
            w.last_error = (f"worker {w.index} is not answering its health ({misses} "
                            f"probe(s) of {PROBE_DEADLINE_S:g} s)")
            log.warning("worker %d (pid %d): no health answer within %g s (%d in a row)",
                        w.index, proc.pid, PROBE_DEADLINE_S, misses)
            if misses >= PROBE_MISSES:
                w.hangs += 1
                log.error("worker %d (pid %d) stopped answering: killing it to restart its "
                          "arms (%s)", w.index, proc.pid, ", ".join(w.arms))
                await self._kill(proc)
                return

    async def _answers(self, w: Worker) -> bool:
        """Whether the worker's health answers 200 within PROBE_DEADLINE_S."""
        try:
            async with asyncio.timeout(PROBE_DEADLINE_S):
                r = await w.client.request("GET", "/api/v1/health", [(b"host", b"localhost")])
                try:
                    await r.read()
                finally:
                    await r.aclose()
        except (UpstreamError, TimeoutError):
            return False
        return r.status_code == 200

    @staticmethod
    async def _kill(proc: asyncio.subprocess.Process) -> None:
        """SIGTERM, then SIGKILL after KILL_GRACE_S (a stopped or deadlocked process runs no
        handler; one that does stops its arms as `POST /stop` does)."""
        with contextlib.suppress(ProcessLookupError):
            proc.send_signal(signal.SIGTERM)
        with contextlib.suppress(TimeoutError):
            async with asyncio.timeout(KILL_GRACE_S):
                await proc.wait()
                return
        with contextlib.suppress(ProcessLookupError):
            proc.kill()

    async def _until_ready(self, w: Worker) -> None:
        while True:
            with contextlib.suppress(UpstreamError, TimeoutError):
                r = await w.client.request("GET", "/api/v1/health",
                                           [(b"host", b"localhost")], timeout=READY_ASK_S)
                await r.read()
                if r.status_code == 200:
                    w.ready, w.last_error = True, None
                    self._first_ready.set()
                    log.info("worker %d ready", w.index)
                    return
            await asyncio.sleep(READY_POLL_S)

    def signal_all(self, sig: int) -> None:
        """Send `sig` to every running worker now (from a signal handler: no awaiting). The
        front relays its own signals so: the first stops every arm as `POST /stop` does at
        once, not after the front's graceful wait for its connections; a second holds them."""
        self._stopping = True  # a worker that exits now is not restarted
        for w in self.workers:
            if w.proc is not None and w.proc.returncode is None:
                with contextlib.suppress(ProcessLookupError):
                    os.kill(w.proc.pid, sig)

    async def stop(self, grace: float) -> None:
        """SIGTERM every worker once (its arms stop as `POST /stop` does, then it exits);
        SIGKILL one still running after `grace` + STOP_GRACE_S s."""
        already = self._stopping  # the first signal went to the workers already
        self._stopping = True
        procs = [w.proc for w in self.workers if w.proc is not None and w.proc.returncode is None]
        for proc in procs if not already else []:
            with contextlib.suppress(ProcessLookupError):
                proc.send_signal(signal.SIGTERM)
        if procs:
            _, pending = await asyncio.wait([asyncio.create_task(p.wait()) for p in procs],
                                            timeout=grace + STOP_GRACE_S)
            if pending:
                for proc in procs:
                    if proc.returncode is None:
                        log.error("worker pid %d did not stop: killing it", proc.pid)
                        with contextlib.suppress(ProcessLookupError):
                            proc.kill()
                await asyncio.wait(pending, timeout=STOP_GRACE_S)
        for t in self._tasks:
            t.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        for w in self.workers:
            await w.client.aclose()
            w.uds.unlink(missing_ok=True)
        # here, not after uvicorn returns: after a signal it re-raises it and the process ends
        self._settings_file.unlink(missing_ok=True)  # it holds the tokens
        with contextlib.suppress(OSError):
            self._settings_file.parent.rmdir()
