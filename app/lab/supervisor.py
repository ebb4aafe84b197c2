"""The lab's worker processes: start each, see it ready, restart it when it dies, stop them all.

A worker is `python -m app.lab.worker` on its own Unix socket in the lab's 0700 folder. Its
watcher task awaits the process's exit; unless the lab is stopping, it starts it again at once
(then after RESTART_BACKOFF_S, doubling to RESTART_MAX_S while it keeps dying young), so a
killed worker's arms are back in about the time the server takes to start (its imports and its
arms: about 2 s here). The other workers are separate processes with their own control threads
and links: a death elsewhere costs them nothing (tests/test_lab_workers.py kills one with
SIGKILL and reads the other's samples throughout).

A worker that hangs without exiting (SIGSTOP, a deadlock) is found by its prober: once ready,
the worker's `GET /api/v1/health` is asked every PROBE_EVERY_S over its socket and must answer
within PROBE_DEADLINE_S (after a miss, it is asked again at once). A slow answer is not a hang:
a live worker's HTTP loop has been seen silent for over 2 s during the tests at load average
10 on two cores (it took its SIGTERM within 60 ms: it was running), and killing it would stop
its arms for nothing. So a worker is taken for hung when
- a probe went unanswered and the process is stopped by a signal (`is_stopped`: state `T`,
  SIGSTOP or SIGTSTP; it gets SIGKILL at once, as a SIGTERM would wait for it to continue), or
- PROBE_MISSES probes in a row went unanswered and during the last one the process neither
  ran nor waited on a run queue to run (`activity`: a stopped or wholly deadlocked process;
  a live one, its control thread polling its arms, runs every second, or waits for a CPU on
  a machine busy beyond its cores), or
- nothing answered for SILENT_S although it runs (its HTTP loop stuck, its control thread
  still holding the arms).
Then it gets SIGTERM, SIGKILL after KILL_GRACE_S (a stopped or deadlocked process runs no
handler), and is restarted as a dead one is; `ready` is false from the kill (its arms 503
`link_down`). A stopped worker's arms are back within about 3.5 s (at most 1.5 s of probes,
then its start: 1.5-2 s), a frozen one's within about 5 s (2.5 s of probes, 0.5 s of grace,
its start); tests/test_lab_workers.py stops one with SIGSTOP. A worker
that hangs in its start, before its first answer, is killed and restarted the same way once it
has neither run nor waited to run for START_FROZEN_S, or after START_S without an answer.

`ready` is the front's one question: has the worker answered its health since it last started
(and not been taken for hung since).

An estop press the front could not hand to a down worker is kept on it (`Worker.keep_press`)
and sent to the worker once it answers its health again, before it is `ready`: before any
other request reaches its arms. A press that found the arm's worker restarting latches the arm
as it comes back, as a press on a single server latches an arm whose link is down.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import signal
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

from app.lab.headers import credentials
from app.lab.upstream import Upstream, UpstreamError
from app.runtime.tasks import cancel_and_wait

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
#: PROBE_MISSES misses in a row with no activity during the last, or SILENT_S s without an
#: answer, and it is killed and restarted (a hung worker: see the module doc).
PROBE_EVERY_S = 0.5
PROBE_DEADLINE_S = 1.0
PROBE_MISSES = 2
SILENT_S = 10.0
#: A starting worker (not yet answering) is hung once it has had no activity for START_FROZEN_S
#: (its start is imports and set-up, all CPU; a store locked by another process waits 1 s at
#: most, app/store.py), or when it has not answered for START_S.
START_FROZEN_S = 5.0
START_S = 120.0
#: How long a hung worker gets after its SIGTERM before its SIGKILL, s.
KILL_GRACE_S = 0.5
#: How long a stopping worker gets after its SIGTERM (beyond the server's own graceful
#: shutdown) before it is killed, s.
STOP_GRACE_S = 5.0
#: An estop press kept for a down worker is sent when it is back within this, s (a restart
#: takes seconds; a press from long before is not what anyone at the arm now expects).
KEEP_PRESS_S = 60.0
#: Presses kept per worker at most (one per arm and token is all a latch needs).
MAX_KEPT_PRESSES = 32
#: How long a kept press may take to answer once the worker is back, s.
KEPT_PRESS_ASK_S = 10.0


def _stat(pid: int) -> list[bytes] | None:
    """The fields of /proc/PID/stat after the command name (proc(5): state first), or None."""
    try:
        with open(f"/proc/{pid}/stat", "rb") as f:
            return f.read().rsplit(b")", 1)[1].split()
    except (OSError, IndexError):
        return None


def thread_activity(pid: int | str) -> dict[int, tuple[int, int]] | None:
    """Each thread of process `pid` (or "self") by its id: (time on a CPU, time waiting on a
    run queue for one), ns, the scheduler's own count (Linux: /proc/PID/task/TID/schedstat,
    proc(5)); a thread that ended meanwhile is left out; None where the process cannot be read
    (gone). (The benches read their threads' CPU from here too: bench/_machine.py.)"""
    try:
        tids = os.listdir(f"/proc/{pid}/task")
    except OSError:
        return None
    out: dict[int, tuple[int, int]] = {}
    for tid in tids:
        try:
            with open(f"/proc/{pid}/task/{tid}/schedstat", "rb") as f:
                fields = f.read().split()
            out[int(tid)] = int(fields[0]), int(fields[1])
        except (OSError, IndexError, ValueError):  # (a thread that ended meanwhile)
            continue
    return out


def activity(pid: int) -> tuple[int, int] | None:
    """What the threads of process `pid` have done, summed, ns: (time on a CPU, time waiting
    on a run queue for one) (`thread_activity`); None where it cannot be read (gone). A
    process whose count does not move neither ran nor waited to run: stopped, or wholly
    blocked (a deadlock). One starved by a machine busy beyond its cores waits on a run queue:
    not hung. (The CPU ticks of /proc/PID/stat are sampled at the timer's tick: a live worker
    that ran in short bursts on such a machine once showed none through a probe, and was
    killed for it.)"""
    threads = thread_activity(pid)
    if threads is None:
        return None
    return sum(t[0] for t in threads.values()), sum(t[1] for t in threads.values())


def is_stopped(pid: int) -> bool:
    """Whether process `pid` is stopped by a signal (SIGSTOP, SIGTSTP: state `T` in
    /proc/PID/stat, proc(5)); not `t`, a debugger's tracing stop, which is someone's on
    purpose."""
    fields = _stat(pid)
    return fields is not None and fields[0] == b"T"


def is_hung(misses: int, frozen: bool, silent_s: float, stopped: bool = False) -> bool:
    """After `misses` unanswered probes in a row, the last with no activity (`frozen`), and
    `silent_s` s since the last answer, the process `stopped` by a signal or not: is the
    worker hung (see the module doc)?"""
    return ((misses >= 1 and stopped) or (misses >= PROBE_MISSES and frozen)
            or silent_s >= SILENT_S)


@dataclass
class KeptPress:
    """An estop press (`POST target`, the client's headers) that found its worker down."""

    target: str
    headers: list[tuple[bytes, bytes]]
    at: float  # time.monotonic()


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
    #: Times it was killed for not answering its health (a hung worker), and how it hung.
    hangs: int = 0
    hung: str = ""
    #: Estop presses for its arms that came while it was down, oldest first (`keep_press`).
    kept: list[KeptPress] = field(default_factory=list)

    def keep_press(self, target: str, headers: list[tuple[bytes, bytes]],
                   now: float | None = None) -> bool:
        """Keep an estop press for when the worker is back (the supervisor sends it before
        the worker is ready). One per target and credentials: a second is the same press.
        False when MAX_KEPT_PRESSES are kept already (it is not). `now`: time.monotonic()'s."""
        now = time.monotonic() if now is None else now
        self.forget_old_presses(now)
        auth = credentials(headers)
        if any(p.target == target and credentials(p.headers) == auth for p in self.kept):
            return True
        if len(self.kept) >= MAX_KEPT_PRESSES:
            return False
        self.kept.append(KeptPress(target, headers, now))
        return True

    def forget_old_presses(self, now: float) -> None:
        """Drop the kept presses older than KEEP_PRESS_S at `now` (time.monotonic()'s)."""
        self.kept = [p for p in self.kept if now - p.at <= KEEP_PRESS_S]

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
            await cancel_and_wait(prober)
            w.ready = False
            w.client.reset()  # its kept-alive connections lead nowhere now
            if self._stopping:
                return
            w.last_error = (f"worker {w.index} " + (f"{w.hung}: killed" if w.hangs != hangs
                                                     else f"exited with {code}")
                            + "; restarting")
            log.error("worker %d (pid %d) exited with %s: restarting its arms (%s)", w.index,
                      w.proc.pid, code, ", ".join(w.arms))
            backoff = backoff * 2 if time.monotonic() - started < YOUNG_S else RESTART_BACKOFF_S
            backoff = min(backoff, RESTART_MAX_S)
            await asyncio.sleep(backoff)

    async def _probe(self, w: Worker, proc: asyncio.subprocess.Process) -> None:
        """Until `proc` exits or the lab stops: see it ready, then ask its health every
        PROBE_EVERY_S; kill it once it is taken for hung (the module doc; the watcher
        restarts it)."""
        ready = await self._until_ready(w, proc)
        if self._stopping:  # the lab stops: a worker's silence now is on purpose
            return
        if not ready:
            w.hangs, w.hung = w.hangs + 1, "hung in its start"
            await self._kill(proc)
            return
        misses = 0
        answered_at = time.monotonic()
        act = activity(proc.pid)
        while True:
            if not misses:  # after a miss, ask again at once
                await asyncio.sleep(PROBE_EVERY_S)
            answered = await self._answers(w)
            if self._stopping:  # the lab stops: its workers stop answering, on purpose
                return
            now, before, act = time.monotonic(), act, activity(proc.pid)
            if answered:
                if misses:
                    log.info("worker %d answers again after %.1f s", w.index,
                             now - answered_at)
                misses, answered_at = 0, now
                continue
            misses += 1
            frozen = act is not None and act == before
            stopped = is_stopped(proc.pid)
            silent = now - answered_at
            log.warning("worker %d (pid %d): no health answer for %.1f s (%s)", w.index,
                        proc.pid, silent, "stopped by a signal" if stopped else
                        "neither ran nor waited to" if frozen else "it runs")
            if is_hung(misses, frozen, silent, stopped):
                w.hangs, w.hung = w.hangs + 1, "hung (no health answer)"
                w.ready = False
                why = ("stopped by a signal" if stopped else "it neither ran nor waited to"
                       if frozen else f"nothing answered for {silent:.0f} s")
                log.error("worker %d (pid %d) hangs (%s): killing it to restart its arms "
                          "(%s)", w.index, proc.pid, why, ", ".join(w.arms))
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
        """SIGTERM, then SIGKILL after KILL_GRACE_S (a deadlocked process runs no handler;
        one that does stops its arms as `POST /stop` does); SIGKILL at once to a process
        stopped by a signal (its SIGTERM would wait, pending, until it is continued)."""
        if is_stopped(proc.pid):
            with contextlib.suppress(ProcessLookupError):
                proc.kill()
            return
        with contextlib.suppress(ProcessLookupError):
            proc.send_signal(signal.SIGTERM)
        with contextlib.suppress(TimeoutError):
            async with asyncio.timeout(KILL_GRACE_S):
                await proc.wait()
                return
        with contextlib.suppress(ProcessLookupError):
            proc.kill()

    async def _send_kept(self, w: Worker) -> bool:
        """The estop presses kept while `w` was down, sent to it in order (each answered
        before the next; the worker checks each as it would have: token, Host, arm). False
        if its socket failed meanwhile: the rest stay kept for its next start."""
        w.forget_old_presses(time.monotonic())
        while w.kept:
            p = w.kept[0]
            try:
                r = await w.client.request("POST", p.target, p.headers, b"",
                                           timeout=KEPT_PRESS_ASK_S, retry=True)
                await r.read()
            except (UpstreamError, TimeoutError) as exc:
                log.warning("worker %d: a kept estop press not sent: %r", w.index, exc)
                return False
            del w.kept[0]
            log.warning("worker %d: an estop press kept while it was down (%.1f s ago) sent: "
                        "POST %s answered %d", w.index, time.monotonic() - p.at, p.target,
                        r.status_code)
        return True

    async def _until_ready(self, w: Worker, proc: asyncio.subprocess.Process) -> bool:
        """Ask a starting worker's health until it answers (True), or until it has had no
        activity for START_FROZEN_S or not answered for START_S (False: it hangs in its start)."""
        started = changed = time.monotonic()
        act = activity(proc.pid)
        while True:
            with contextlib.suppress(UpstreamError, TimeoutError):
                r = await w.client.request("GET", "/api/v1/health",
                                           [(b"host", b"localhost")], timeout=READY_ASK_S)
                await r.read()
                if r.status_code == 200 and await self._send_kept(w):
                    w.ready, w.last_error = True, None
                    self._first_ready.set()
                    log.info("worker %d ready", w.index)
                    return True
            await asyncio.sleep(READY_POLL_S)
            if self._stopping:
                return False
            now, before, act = time.monotonic(), act, activity(proc.pid)
            if act is None or act != before:
                changed = now
            if now - changed >= START_FROZEN_S or now - started >= START_S:
                log.error("worker %d (pid %d) hangs in its start (%s): killing it", w.index,
                          proc.pid, f"it neither ran nor waited to for {now - changed:.0f} s"
                          if now - changed >= START_FROZEN_S else f"{START_S:.0f} s")
                return False

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
