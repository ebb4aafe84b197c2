"""One thread that runs the scheduled polls of every thread link of the process (issue 27).

A worker with 16 arms had 16 link threads, each woken twice a poll (its slot, its reply) and
each taking the GIL back from the others: 16,000 wake-ups a second at 500 Hz. Here one thread
serves them all. Its slots are on one grid per period (`aligned`: a link armed between two
grid points polls at the next one, never before its owner task asked and less than a period
after, so never twice in a row), so at each slot it writes every due poll request, then
waits for the replies of all of them in one `select.poll` over their descriptors (and its own
wake-up pipe), and hands the owner tasks what they should take in one `call_soon_threadsafe`
per event loop for the whole batch, not one per arm.

What a link keeps of its own (app/links/threaded.py): its schedule and its replies read
ahead, under its lock; `begin` and `end` there say what a poll is, this thread only does the
I/O. A link is polled here only while its owner task waits (armed); `ThreadLink.pause`
returns once the poll in flight has ended, so the owner task and this thread never read or
write the same descriptor at once.
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import logging
import math
import os
import select
import socket
import threading
import time
from collections.abc import Callable
from typing import Protocol

from app.links.base import READ_CHUNK, Reply
from app.runtime.control_thread import CONTROL_NICE, raise_priority

try:  # the rounds of links at rest in C (app/links/_restpoll.c), where it was built
    import app.links._restpoll as _restpoll
except ImportError:  # (no C compiler at install: the same rounds in Python)
    _restpoll = None  # type: ignore[assignment]

log = logging.getLogger(__name__)

#: Whether links at rest are polled in C (`PollThread._rest`): where the module was built,
#: unless ARMSERVER_POLL_REST=python (the rounds in Python, for a before/after measure).
REST_IN_C = _restpoll is not None and os.environ.get("ARMSERVER_POLL_REST", "c") != "python"

#: Longest a full transmit buffer may hold back a poll request, s: then the link is lost.
WRITE_WAIT_S = 1.0
#: Periods a schedule may fall behind (a stalled machine) before it skips ahead, as the owner
#: task's POLL_CATCH_UP.
CATCH_UP = 10
#: A poll may go this much before its slot (s): `poll` waits in whole milliseconds, and the
#: owner task's own polls may run as early (app/device/owner.py POLL_EARLY_S); the schedule
#: itself stays absolute.
EARLY_S = 0.001
_ERR = select.POLLERR | select.POLLHUP | select.POLLNVAL
#: The niceness the poll thread asks for as it starts, where the system allows it (root or
#: CAP_SYS_NICE): the control thread's. It does the I/O of every arm's polls, so it is set
#: here, not inherited from whichever thread armed the process's first link (a server's
#: control thread, at that niceness; a bench's or an in-process server's own thread, at 0).
#: None: it keeps its starter's (the tests whose simulators answer from their own thread).
NICENESS: int | None = CONTROL_NICE

#: What a round of polls asks of each event loop (the owners' wake-ups, paused schedules).
_Handover = dict[asyncio.AbstractEventLoop, list[Callable[[], None]]]


#: What a link asks of its owner's event loop as a poll ends (`poll_ended`, `rest_ended`): the
#: loop and the calls to run there, or None (nothing).
Told = tuple[asyncio.AbstractEventLoop, list[Callable[[], None]]] | None
#: A link's rounds in C (`rest_begin`): descriptor, request, the reply expected, timeout, next
#: slot, period, when its batch is due, the replies it may still hold.
RestPlan = tuple[int, bytes, bytes, float, float, float, float, int]


class Polled(Protocol):
    """What the poll thread asks of a link (app/links/threaded.py `ThreadLink`)."""

    @property
    def armed(self) -> bool: ...

    def poll_due(self, now: float) -> tuple[int, bytes, int, float] | float | None: ...

    def poll_ended(self, packet: bytes, entry: Reply | BaseException) -> Told: ...

    @property
    def at_rest(self) -> bool: ...

    def rest_begin(self) -> RestPlan | bool: ...

    def rest_ended(self, packet: bytes, slot: float, ats: list[float],
                   entry: Reply | BaseException | None) -> Told: ...


class PollLost(Exception):
    """A scheduled poll found the transport failed (the owner task marks the link DOWN)."""


#: A slot this close to its period's grid is on it (`following`), s.
GRID_TOL_S = 1e-6


def following(slot: float, period: float) -> float:
    """The slot a period after `slot`: where `slot` is on its period's grid (within
    GRID_TOL_S), the grid point itself (`k * period`, one rounding), so that a schedule does
    not drift off the grid as a sum of periods does (about one ulp a poll: some 0.6 ms a day
    at a monotonic clock of 69,000 s, and links of one period share a slot within EARLY_S);
    else `slot + period`. As `_restpoll.c`'s `following`."""
    after = slot + period
    on = round(after / period) * period
    return on if abs(on - after) < GRID_TOL_S else after


def aligned(slot: float, period: float) -> float:
    """The first grid point (a multiple of `period` of `time.monotonic()`) at or after `slot`
    (within a nanosecond): links of one period share their slots, so that one wake-up serves
    all of them."""
    return math.ceil((slot - 1e-9) / period) * period


class _Flight:
    """One poll in flight: its request still to write, its reply so far, its deadline."""

    __slots__ = ("data", "deadline", "fd", "link", "lowat", "out", "packet", "size", "write_by")

    def __init__(self, link: Polled, fd: int, packet: bytes, size: int, deadline: float,
                 out: bytes, write_by: float) -> None:
        self.link, self.fd, self.packet, self.size = link, fd, packet, size
        self.deadline, self.out, self.write_by = deadline, out, write_by
        self.data = b""
        #: Whether the socket's SO_RCVLOWAT is set to what the reply still lacks (None: not
        #: yet tried; False: not a socket).
        self.lowat: bool | None = None


class PollThread:
    """The process's scheduled polls (module doc). `add` a link when its owner arms it."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        #: The links served, replaced whole under the lock (the thread reads it without).
        self._links: tuple[Polled, ...] = ()
        self._wake_r, self._wake_w = os.pipe()
        os.set_blocking(self._wake_r, False)
        os.set_blocking(self._wake_w, False)
        self._poller = select.poll()
        self._poller.register(self._wake_r, select.POLLIN)
        #: When the thread wakes by itself next (monotonic s; None: only when nudged).
        self._sleeps_until: float | None = None
        self._nudged = False
        #: Wake-ups of the thread, and the batches it handed to event loops.
        #: (`rest_runs`: calls of the rounds in C)
        self.stats = {"wakes": 0, "handovers": 0, "polls": 0, "rest_runs": 0}
        #: The niceness the thread got (None: its starter's: NICENESS None, or not allowed).
        self.niceness: int | None = None
        started = threading.Event()
        self._thread = threading.Thread(target=self._main, args=(started,), name="link polls",
                                        daemon=True)
        self._thread.start()
        started.wait()  # (its niceness set before any link is served)

    def add(self, link: Polled, slot: float) -> None:
        """Serve `link`'s schedule (armed, its first slot `slot`); wakes the thread if it
        sleeps past that slot, or is awake (it may have walked its links already).

        No lock against the thread: it clears `_sleeps_until` when it wakes, before it walks
        `_links`, and sets it just before it sleeps; `add` replaces `_links` before it reads
        `_sleeps_until` (statements of either thread run in order under the GIL), so the
        thread either sees the link or is nudged."""
        with self._lock:  # (adders on several loops)
            if link not in self._links:
                self._links = (*self._links, link)
        until = self._sleeps_until
        if not self._nudged and (until is None or until > slot):
            self.nudge()

    def _forget(self, link: Polled) -> None:
        """Stop serving `link` (closed) unless its owner armed it again meanwhile."""
        with self._lock:
            if not link.armed:
                self._links = tuple(k for k in self._links if k is not link)

    # ------------------------------------------------------------ the thread

    def _main(self, started: threading.Event) -> None:
        try:
            if NICENESS is not None:
                self.niceness = raise_priority(NICENESS)
        finally:
            started.set()
        flights: dict[int, _Flight] = {}
        while True:
            try:
                self._round(flights)
            except Exception:  # a bug must not end every arm's polls: log, drop, go on
                log.exception("the link poll thread failed a round")
                handover: _Handover = {}
                for f in list(flights.values()):  # each owner told (and a pause let go)
                    self._finish(f, PollLost("internal error in the poll thread"), handover,
                                 flights)
                self._hand_over(handover)
                time.sleep(0.01)

    def _round(self, flights: dict[int, _Flight]) -> None:
        """Write the due polls' requests, wait for their replies, a slot or a nudge, take what
        came. The hot path of every arm's sample, run cold after each sleep: a few attribute
        reads besides the syscalls (each link's poll is made once per arm: `poll_due` answers
        it whole), no lock but a due link's own."""
        handover: _Handover = {}
        wake_at = math.inf
        self._sleeps_until = None  # awake: an `add` from here on nudges (before the walk)
        self._nudged = False
        if REST_IN_C and not flights and self._rest():
            return
        now = time.monotonic()
        flying = {f.link for f in flights.values()} if flights else ()
        for link in self._links:
            if link in flying:
                continue
            state = link.poll_due(now)
            if state is None:  # closed: served again when its owner arms it
                self._forget(link)
            elif isinstance(state, float):
                if state < wake_at:
                    wake_at = state
            else:
                self._start(link, state, flights, handover)
        for f in flights.values():
            if f.deadline < wake_at:
                wake_at = f.deadline
        if handover:  # (a write that failed: told before waiting)
            events = []
        elif wake_at == math.inf:
            self._sleeps_until = None
            events = self._poller.poll()
        else:  # whole milliseconds, rounded up: never a spin; a slot's wake-up is EARLY_S early
            self._sleeps_until = wake_at
            events = self._poller.poll(max(0, math.ceil((wake_at - time.monotonic()) * 1e3)))
        self._sleeps_until = None
        self.stats["wakes"] += 1
        for fd, ev in events:
            got = flights.get(fd)
            if got is None:
                if fd == self._wake_r:
                    try:
                        os.read(self._wake_r, 512)
                    except BlockingIOError:
                        pass
                continue
            try:
                if ev & select.POLLOUT and got.out:
                    self._write(got)
                    if not got.out:  # all written: the reply is all it waits for now
                        self._poller.modify(fd, select.POLLIN)
                if ev & (select.POLLIN | _ERR):
                    self._read(got)
            except (OSError, PollLost) as exc:
                self._finish(got, exc, handover, flights)
                continue
            if len(got.data) >= got.size:
                self._finish(got, None, handover, flights)
            elif got.data and got.lowat is not False:  # a part of a reply: wake for the rest
                # (again after a second part, which the kernel gives early under memory
                # pressure: a mark left at the larger rest would hold the reply to its deadline)
                got.lowat = _set_lowat(fd, got.size - len(got.data))
        if flights:
            now = time.monotonic()
            for f in [f for f in flights.values() if now >= f.deadline]:
                if f.out:
                    if now >= f.write_by:
                        self._finish(f, PollLost("the port took no bytes for "
                                                 f"{WRITE_WAIT_S:.0f} s"), handover, flights)
                    else:  # short: the owner task resyncs
                        self._finish(f, None, handover, flights)
                    continue
                # what arrived by the time the thread looks counts, as where the owner task
                # reads itself (threaded.py `_read_here` reads once more as its timer ends):
                # a thread that got the GIL back only after its wait timed out (a loaded
                # machine) finds the reply there, and takes it
                try:
                    self._read(f, ready=False)
                except (OSError, PollLost) as exc:
                    self._finish(f, exc, handover, flights)
                    continue
                self._finish(f, None, handover, flights)  # whole, or short: the owner resyncs
        if handover:
            self._hand_over(handover)

    def _rest(self) -> bool:
        """Every armed link at rest (its last replies repeated): their rounds in C until one
        of them is not (app/links/_restpoll.c), then each link told what was read
        (`rest_ended`), as `_round` tells it of each poll; False (nothing done) where an armed
        link is not at rest or none is armed: the round runs in Python. An `add`, a pause, a
        link closing or a new batch time wakes the rounds in C (`nudge`: `_sleeps_until`
        stays None meanwhile), which end once the polls in flight have."""
        links = self._links
        if not any(link.at_rest for link in links) or any(
                link.armed and not link.at_rest for link in links):
            return False  # (a first look without the links' locks)
        taken: list[tuple[Polled, RestPlan]] = []
        for link in links:
            plan = link.rest_begin()
            if plan is True:
                continue  # not armed: its owner's `arm` nudges
            if plan is False:
                break
            taken.append((link, plan))
        else:
            if taken:
                self._rest_rounds(taken)
                return True
        handover: _Handover = {}
        for link, plan in taken:  # (nothing read: only a pause that waited is told)
            _told(handover, link.rest_ended(plan[1], plan[4], [], None))
        self._hand_over(handover)
        return False

    def _rest_rounds(self, taken: list[tuple[Polled, RestPlan]]) -> None:
        assert _restpoll is not None
        handover: _Handover = {}
        try:
            ended = _restpoll.run([plan for _, plan in taken], self._wake_r, EARLY_S,
                                  float(CATCH_UP), WRITE_WAIT_S, READ_CHUNK)
        except Exception:  # (a bug: every link's owner is told its poll failed)
            log.exception("the link poll thread's rounds in C failed")
            ended = [(plan[4], [], ("lost", "internal error in the poll thread"))
                     for _, plan in taken]
        self.stats["wakes"] += 1
        for (link, plan), (slot, ats, end) in zip(taken, ended, strict=True):
            self.stats["polls"] += len(ats) + (end is not None)
            entry: Reply | BaseException | None = None
            if end is not None:  # ("reply", data, deadline, at) or ("lost", reason)
                entry = Reply(*end[1:]) if len(end) == 4 else PollLost(end[1])
            _told(handover, link.rest_ended(plan[1], slot, ats, entry))
        self.stats["rest_runs"] += 1  # (once no link is in them: tests/test_rest_rounds.py)
        if handover:
            self._hand_over(handover)

    def nudge(self) -> None:
        """Wake the thread now (a link added, `add`; a link's rounds in C must end:
        app/links/threaded.py `_wake_rest`)."""
        self._nudged = True
        try:
            os.write(self._wake_w, b"x")
        except BlockingIOError:  # (the pipe is full of nudges already)
            pass

    def _start(self, link: Polled, poll: tuple[int, bytes, int, float],
               flights: dict[int, _Flight], handover: _Handover) -> None:
        """Put `link`'s poll in flight: its request written (what the port takes now), its
        descriptor watched for the reply (and the rest of the request) until its deadline,
        counted from the write."""
        fd, packet, size, timeout = poll
        t = time.monotonic()
        f = _Flight(link, fd, packet, size, t + timeout, packet, t + WRITE_WAIT_S)
        flights[fd] = f
        try:
            self._write(f)
        except (OSError, PollLost) as exc:
            self._finish(f, exc, handover, flights)
            return
        self._poller.register(fd, select.POLLIN | (select.POLLOUT if f.out else 0))

    def _hand_over(self, handover: _Handover) -> None:
        """One `call_soon_threadsafe` per event loop for what this round asks of it."""
        for loop, calls in handover.items():
            self.stats["handovers"] += 1
            with contextlib.suppress(RuntimeError):  # a closed loop: nobody left to tell
                loop.call_soon_threadsafe(_run_all, calls)

    def _write(self, f: _Flight) -> None:
        try:
            n = os.write(f.fd, f.out)
        except BlockingIOError:
            n = 0
        f.out = f.out[n:] if n < len(f.out) else b""

    def _read(self, f: _Flight, ready: bool = True) -> None:
        """What `f`'s port has; `ready`: poll said it had something. Nothing read where it
        said so is a lost port (a socket's end, a tty whose other end is gone); nothing read
        unasked is nothing yet: a tty with no input reads 0 bytes (VMIN 0), not EAGAIN."""
        try:
            data = os.read(f.fd, READ_CHUNK)
        except BlockingIOError:
            return
        except OSError as exc:
            if exc.errno == errno.EAGAIN:
                return
            raise
        if not data:
            if ready:
                raise PollLost("closed by the peer (end of file)")
            return
        f.data = f.data + data if f.data else data

    def _finish(self, f: _Flight, error: BaseException | None,
                handover: _Handover,
                flights: dict[int, _Flight]) -> None:
        flights.pop(f.fd, None)
        try:
            self._poller.unregister(f.fd)
        except KeyError:  # (a write that failed: never registered)
            pass
        if f.lowat:  # before the owner task may read the port itself (its `pause` ends)
            _set_lowat(f.fd, 1)
        self.stats["polls"] += 1
        entry: Reply | BaseException = (
            error if error is not None else Reply(f.data, f.deadline, time.time()))
        _told(handover, f.link.poll_ended(f.packet, entry))


def _told(handover: _Handover, told: Told) -> None:
    """Add to `handover` what a link asked of its owner's loop (`poll_ended`)."""
    if told is not None:
        loop, calls = told
        handover.setdefault(loop, []).extend(calls)


def _set_lowat(fd: int, n: int) -> bool:
    """Have `poll` report socket `fd` readable only once `n` bytes are there (SO_RCVLOWAT;
    Linux's TCP honours it in `poll` and wakes no reader before): a reply that comes in parts
    (a Dynamixel bus's statuses one after another, each timed by the simulator as on the wire)
    wakes the thread for its first part and its last, not for each. False if `fd` is no
    socket (a tty: each part wakes it)."""
    try:  # (a socket object over the descriptor, no syscall, then let go of it)
        sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM, 0, fd)
    except OSError:
        return False
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVLOWAT, n)
    except OSError:  # not a socket (ENOTSOCK), or closed under us
        return False
    finally:
        sock.detach()
    return True


def _run_all(calls: list[Callable[[], None]]) -> None:
    """On an event loop: what one batch of polls asks of it (wake-ups, paused schedules)."""
    for call in calls:
        try:
            call()
        except Exception:
            log.exception("a link poll hand-over failed")


_shared: tuple[int, PollThread] | None = None
_shared_lock = threading.Lock()


def shared() -> PollThread:
    """The process's poll thread, started at its first use (again in a forked child)."""
    global _shared
    with _shared_lock:
        if _shared is None or _shared[0] != os.getpid():
            _shared = (os.getpid(), PollThread())
        return _shared[1]

