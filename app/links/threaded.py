"""A byte-stream link (any pyserial URL) whose scheduled polls run off the control loop (issue 27).

While the owner task has nothing else to do, the process's poll thread (app/links/poller.py:
one thread for every thread link of the worker, not one a link) runs the owner's poll itself
on the poll schedule (`arm`): at each slot it writes the poll request the owner task last made
and reads the reply (over the port's descriptor, until the reply's bytes have come or its
timeout has passed), and keeps it here (`prefetched`). Links of one period share their slots
(`aligned`), so one wake-up writes every due request and one `poll` waits for all the replies.
The owner tasks are woken for the replies together (one `call_soon_threadsafe` per event loop
for a batch of polls of every arm on it) and pass each through the driver as if they had made
the poll themselves (`begin_poll`): the same sans-IO parsing, matching and checks, in the same
order; a reply byte for byte the last poll's is the last sample again (`take_repeats`). An idle
arm then costs the control loop one wake-up a batch instead of a timer, a write, a read and two
wake-ups a poll.

The owner task's own calls (a request, a poll after a failure or a write, the driver's quiet
wait) pause the schedule and run on its loop over the port's descriptor, as an asyncio link's
do (`transact`: write, then one reader and one timer until the reply's bytes or its timeout).
Where pyserial gives no descriptor (URLs such as `loop://` and `rfc2217://`), they run on the
link's own thread with pyserial's own `write` and `read` with a timeout, and nothing is polled
on the schedule: the owner task makes every poll itself.

What the owner task relies on (app/device/owner.py `_session_scheduled`, tested in
tests/test_link_thread.py):
- The poll thread polls this link only while the owner task waits for it, or takes the
  replies it read ahead without any I/O of its own (replies that repeat the last poll's:
  `take_repeats`): every call the owner task makes (`transact`, `read`, `write`) first pauses
  the schedule and waits for the poll in flight, so a request waits behind at most one poll
  and no byte of one exchange is read by another; it polls again only after a good poll,
  every reply since whole (`can_schedule`).
- The owner task is woken at once for a reply that differs from the ones before (an arm that
  starts to move, a fault; for an arm at rest over a socket, once the thread reads it: at the
  link's next slot, app/links/_restpoll.c), for one that did not come whole within its timeout
  (and the schedule stops: the driver resynchronises as it does on any link, with its quiet
  wait, before anything is written again) and for a request; replies that go on changing (a
  moving arm) wait at most MOVING_BATCH_S, replies that repeat (an arm at rest) BATCH_S, or
  IDLE_BATCH_S while nobody takes the samples as they come (`batch_repeats`) (a batch that only
  repeats the last poll's reply is published in the hand-over itself, the owner task left
  waiting: app/device/owner.py `_on_replies`), and each carries the time it was complete
  (`Reply.at`; over a socket at rest, the kernel's time of its arrival).
- A reply is taken for the owner's poll only if the owner task asks for the same request
  bytes; otherwise the replies read ahead are dropped (they answer requests the driver never
  made).
- Closing the port waits for the poll in flight (the poll thread never reads a descriptor
  that was closed, or reused).

pyserial's port is opened as `app/links/serial.py` opens it (`serial_for_url`, exclusive), on
the thread. `[link] io = "asyncio"` in a profile keeps the asyncio link (app/links/serial.py).
"""

from __future__ import annotations

import asyncio
import logging
import math
import os
import queue
import select
import stat
import threading
import time
from collections import deque
from collections.abc import Callable
from typing import Any

from app.links.base import READ_CHUNK, Link, LinkError, LinkState, Reply
from app.links.poller import (
    CATCH_UP,
    EARLY_S,
    PollThread,
    RestPlan,
    Told,
    aligned,
    following,
    shared,
)
from app.links.serial import port_fileno
from app.runtime.control_thread import (
    CONTROL_NICE,
    TerminalHold,
    lower_priority,
    raise_priority,
    terminal_hold,
)
from app.runtime.tasks import resolve

log = logging.getLogger(__name__)

CLOSE_TIMEOUT_S = 1.0  # closing must not hang the owner task on a thread stuck in a call
#: Longest a scheduled poll's reply waits on the thread before the owner task is woken for it,
#: s: replies that repeat (an arm at rest) reach the owner task in batches this far apart at
#: most (a 50 Hz subscriber's period); a reply that differs, one that failed and a request
#: wake it at once.
BATCH_S = 0.02
#: ... and while nobody takes the arm's samples as they come (no telemetry subscriber and no
#: listener on its hub: the owner task says so, `batch_repeats`), every IDLE_BATCH_S: an arm at
#: rest that only answers reads of its latest sample then wakes its control loop ten times a
#: second, not fifty (issue 27: half its control loop's CPU at rest); that latest sample is
#: then up to this old, and the same reading (an arm at rest). A reader that comes gets the
#: batch being made within BATCH_S.
IDLE_BATCH_S = 0.1
#: ... and replies that go on changing (an arm that moves), after the first of them, which
#: wakes it at once: a subscriber at the poll rate sees a moving arm this much later at most.
MOVING_BATCH_S = 0.005
#: Replies the thread keeps for the owner task at most; then it stops polling on its own (a
#: stalled control loop gets no backlog to catch up on, as POLL_CATCH_UP bounds it). The rounds
#: in C read this many beyond those the owner task was already woken for (`rest_begin`): a
#: batch just handed over is taken within a wake-up of the control loop, and counting it cut
#: the next rounds short, a second return to Python every batch (docs/performance.md,
#: "Session 36"); a link still holding this many when its rounds end stops polling.
MAX_PREFETCHED = 64
#: Longest wait for a full transmit buffer to take a request, s: then the link is lost.
WRITE_WAIT_S = 1.0

_STOP = object()  # close the port and end the thread


class Repeats:
    """Replies the poll thread read in C (app/links/_restpoll.c) that all repeated the last
    one: its bytes once and the time each was read (`time.time()`, in order), kept as one
    entry of the replies read ahead instead of one `Reply` each."""

    __slots__ = ("ats", "data")

    def __init__(self, data: bytes, ats: list[float]) -> None:
        self.data, self.ats = data, ats


def _settle_once(fut: asyncio.Future[bool], ready: bool) -> None:
    if not fut.done():
        fut.set_result(ready)


class _Lost(Exception):
    """Raised on the thread: the transport failed; the loop side marks the link DOWN."""


class ThreadLink(Link):
    """A stream link (`read` returns whatever bytes have arrived) served by one thread."""

    kind = "serial"
    packetized = False

    def __init__(self, address: str, baudrate: int = 1_000_000) -> None:
        super().__init__(address)
        self.baudrate = baudrate
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._ended: asyncio.Future[None] | None = None  # resolved as the thread ends
        self._jobs: queue.SimpleQueue[Any] = queue.SimpleQueue()
        # on the thread only, once open
        self._port: Any = None
        self._fd: int | None = None
        self._socket = False  # the descriptor is a socket (`socket://`): b"" is its end
        self._terminal: TerminalHold | None = None  # the port is a terminal (a tty, a pty)
        self._poller: Any = None
        #: Bytes a call read for a caller that gave up (cancelled): read first, never lost.
        self._stash = bytearray()
        # the schedule: shared with the thread, under _lock
        self._lock = threading.Lock()
        self._armed = False
        self._in_flight = False
        self._slot = 0.0
        self._period = 0.0
        self._notify: Callable[[], None] | None = None
        self._paused: asyncio.Future[None] | None = None
        self._prefetched: deque[tuple[bytes, Reply | BaseException | Repeats]] = deque()
        #: The replies `_prefetched` holds (a `Repeats` entry holds several), and how many of
        #: them (the oldest) the owner task was woken for (`_polls_over`).
        self._held = 0
        self._told = 0
        #: The poll thread polls this link in C (`rest_begin` to `rest_ended`): a change the
        #: thread must see at once (a pause, closing, another batch) wakes it (`_wake_rest`).
        self._resting = False
        self._last_data = b""
        self._changing = False  # the last reply differed from the one before
        self._batch_since = 0.0
        #: How long repeats wait on the thread, s (BATCH_S or IDLE_BATCH_S: `batch_repeats`).
        self._repeat_batch_s = BATCH_S
        #: Signalled as a scheduled poll ends (`poll_ended`) while the port is closing.
        self._flight_ended = threading.Condition(self._lock)
        self._closing = False
        #: The process's poll thread (app/links/poller.py), from the first `arm`.
        self._polls: PollThread | None = None
        #: The owner's poll request (bytes, reply size, timeout), from its last poll.
        self._poll: tuple[bytes, int, float] | None = None
        #: What the poll thread does at each slot (descriptor, request, reply size, timeout):
        #: the owner's poll request on this port, made once per `arm` (None: closed).
        self._plan: tuple[int, bytes, int, float] | None = None
        #: Every reply whole by its timeout since the last poll's (the thread may poll alone).
        self._clean = False
        # the owner's current poll (loop side)
        self._poll_next = False
        self._use_prefetched = False
        #: `time.time()` when the reply handed to the current poll was read, where the thread
        #: read it ahead (None: just now).
        self.reply_time: float | None = None
        #: (request, reply) of the owner's last poll, if its reply came whole and nothing
        #: else was written or read since (None otherwise): what `take_repeats` compares with.
        self._last_poll: tuple[bytes, bytes] | None = None
        #: Scheduled polls made on the thread, and those of them dropped unused.
        self.stats = {"scheduled": 0, "dropped": 0, "wakes": 0}

    # ------------------------------------------------------------ the Link contract

    async def open(self) -> None:
        """Open the port on a new thread; LinkError naming the URL and the reason."""
        await self.close()
        self.state = LinkState.CONNECTING
        loop = asyncio.get_running_loop()
        self._loop = loop
        self._jobs = queue.SimpleQueue()
        self._stash.clear()
        with self._lock:
            self._armed = False
            self._in_flight = False
            self._prefetched.clear()
            self._held = self._told = 0
            self._plan = None
        self._poll = None
        self._clean = False
        self._last_data = b""
        self._last_poll = None
        self._changing = False
        self._ended = loop.create_future()
        self._thread = threading.Thread(target=self._main, args=(loop, self._ended),
                                        name=f"link {self.address}", daemon=True)
        self._thread.start()
        fut: asyncio.Future[Any] = loop.create_future()
        self._jobs.put((self._open_blocking, (), fut))
        try:
            await fut
        except (OSError, ValueError, _Lost) as exc:
            await self._stop_thread()
            from app.links.serial import cannot_open

            raise self._down(cannot_open(self.address, exc)) from exc
        self.state = LinkState.UP
        self.last_error = None
        log.info("serial link %s open at %d baud (on its own thread)", self.address,
                 self.baudrate)

    async def write(self, data: bytes) -> None:
        self._last_poll = None
        fd = await self._paused_fd()
        rest = bytes(data) if fd is None else self._write_here(fd, bytes(data))
        if rest:  # no descriptor, or a full transmit buffer: the thread waits for it
            await self._call(self._write_all, rest)

    async def read(self, timeout: float) -> bytes:
        self._last_poll = None
        if self._stash:
            data = bytes(self._stash[:READ_CHUNK])
            del self._stash[:READ_CHUNK]
            return data
        fd = await self._paused_fd()
        if fd is not None:
            return await self._read_here(fd, timeout, True)
        result: bytes = await self._call(self._read_some, timeout)
        return result

    async def transact(self, packet: bytes, reply_size: int, timeout: float) -> Reply:
        """Write `packet` and read until `reply_size` bytes or `timeout` (on the loop, the
        schedule paused); for the owner's poll (`begin_poll`), the reply the thread read
        ahead, if it answers the same request."""
        if self._poll_next:
            if self._use_prefetched:
                self._use_prefetched = False
                with self._lock:
                    head = self._take_one_locked() if (
                        self._prefetched and self._prefetched[0][0] == packet) else None
                if head is not None:
                    self._poll_next = False
                    entry = head
                    if isinstance(entry, BaseException):
                        self._last_poll = None
                        raise self._lost(str(entry))
                    self.reply_time = entry.at
                    self._last_poll = ((packet, entry.data) if len(entry.data) == reply_size
                                       else None)
                    return entry
                self.drop_prefetched()  # another request: the thread's replies are no answer
            self._poll = (bytes(packet), reply_size, timeout)
        polling, self._poll_next = self._poll_next, False
        self._last_poll = None
        try:
            fd = await self._paused_fd()
            if fd is not None:
                reply = await self._transact_here(fd, bytes(packet), reply_size, timeout)
            else:
                reply = await self._call(self._transact, bytes(packet), reply_size, timeout,
                                         False)
        except BaseException:
            self._clean = False
            raise
        if len(reply.data) < reply_size:
            self._clean = False  # its reply may still come: the driver's quiet wait is next
        elif polling:
            self._clean = True
        if self._stash:  # bytes read for a cancelled call came first on the wire
            reply = Reply(bytes(self._stash) + reply.data, reply.deadline, reply.at)
            self._stash.clear()
        elif polling and len(reply.data) == reply_size:
            self._last_poll = (bytes(packet), reply.data)
        return reply

    async def close(self) -> None:
        self.state = LinkState.DOWN
        with self._lock:
            self._armed = False
            self._prefetched.clear()
            self._held = self._told = 0
        await self._stop_thread()  # (`_close_port` wakes rounds in C: `_wake_rest`)

    # ------------------------------------------------------------ the owner's schedule

    def begin_poll(self, prefetched: bool) -> None:
        """The owner task's next `transact` is its poll: answered from the replies the thread
        read ahead if `prefetched` (the first of them, if it answers the same request), else
        made now and kept as the request `arm` repeats."""
        self._poll_next = True
        self._use_prefetched = prefetched
        self.reply_time = None

    def take_repeats(self) -> list[float]:
        """Take the replies read ahead, from the first on, that repeat the owner's last poll
        byte for byte (the same request, the same whole reply, nothing else written or read
        since: an arm at rest), and answer when each was read (`time.time()`, in order); none
        taken (an empty list) where the first does not. The owner task then publishes its
        last sample again for each instead of parsing the same bytes (app/device/owner.py
        `_repeat`)."""
        last = self._last_poll
        if last is None:
            return []
        request, reply = last
        ats: list[float] = []
        with self._lock:
            prefetched = self._prefetched
            while prefetched:
                packet, entry = prefetched[0]
                if packet != request:
                    break
                if isinstance(entry, Repeats):
                    if entry.data != reply:
                        break
                    ats += entry.ats
                    self._taken_locked(len(entry.ats))
                elif isinstance(entry, Reply) and entry.data == reply and entry.at is not None:
                    ats.append(entry.at)
                    self._taken_locked(1)
                else:
                    break
                prefetched.popleft()
        return ats

    def _taken_locked(self, n: int) -> None:
        """`n` replies taken by the owner task, the oldest first (those it was woken for)."""
        self._held -= n
        self._told = max(0, self._told - n)

    def _take_one_locked(self) -> Reply | BaseException:
        """The first reply read ahead, taken (a `Repeats` entry gives its first)."""
        packet, entry = self._prefetched[0]
        self._taken_locked(1)
        if not isinstance(entry, Repeats):
            self._prefetched.popleft()
            return entry
        at = entry.ats.pop(0)
        if not entry.ats:
            self._prefetched.popleft()
        return Reply(entry.data, time.monotonic(), at)

    @property
    def prefetched(self) -> int:
        """Replies the thread read ahead that the owner task has not taken yet."""
        return self._held

    @property
    def clean(self) -> bool:
        """The last exchange ended clean: every reply whole by its timeout. False after a poll
        read ahead failed: its late reply may still come, so the driver's quiet wait must
        come before anything else is written (the owner task passes the failed poll to the
        driver before a queued request, app/device/owner.py)."""
        return self._clean

    @property
    def can_schedule(self) -> bool:
        """`arm` would poll: a poll request is known, the last exchange ended clean (every
        reply whole by its timeout, the last poll's among them) and the port has a descriptor
        (without one, the owner task polls itself)."""
        return (self._clean and self._poll is not None and self.state is LinkState.UP
                and self._fd is not None)

    @property
    def next_slot(self) -> float:
        """The schedule's next slot (`time.monotonic()`), once paused."""
        return self._slot

    def arm(self, slot: float, period: float, notify: Callable[[], None]) -> bool:
        """Poll on the thread from `slot` (`time.monotonic()`) every `period` s with the last
        poll request, calling `notify` (from the thread) when the owner task should take the
        replies; False (nothing armed) before a poll request is known."""
        poll = self._poll
        if not self.can_schedule or self._thread is None or poll is None:
            return False
        slot = aligned(slot, period)  # the slots every link of this period shares
        packet, size, timeout = poll
        with self._lock:
            fd = self._fd
            if fd is None:  # (closed meanwhile, on the link's thread)
                return False
            self._plan = (fd, packet, size, timeout)
            self._armed = True
            self._slot, self._period, self._notify = slot, period, notify
            self._batch_since = time.monotonic()
        polls = self._polls
        if polls is None:
            polls = self._polls = shared()
        polls.add(self, slot)
        return True

    def batch_repeats(self, seconds: float) -> None:
        """Hand repeats over every `seconds` from the last hand-over on (BATCH_S while someone
        takes the samples as they come, IDLE_BATCH_S while nobody does): a reader that comes
        gets the batch being made within BATCH_S, as every reader did."""
        with self._lock:
            changed, self._repeat_batch_s = seconds != self._repeat_batch_s, seconds
        if changed:  # (a batch being read in C ends at the old time: the thread is told)
            self._wake_rest()

    @property
    def armed(self) -> bool:
        """The poll thread polls this link on its schedule (until `pause`)."""
        return self._armed

    def poll_due(self, now: float) -> tuple[int, bytes, int, float] | float | None:
        """For the poll thread (app/links/poller.py), at `now` (`time.monotonic()`): None if
        closed (forget the link until it is armed again); the time to wake for the next slot
        if it is not due yet, armed or not (an owner task that took a batch re-arms at that
        slot: the thread then needs no nudge), infinity for a slot gone by unarmed; else the
        poll is in flight from here, and (descriptor, request, reply size, timeout) says what
        to do (made once per `arm`)."""
        due = self._slot - EARLY_S
        if due > now and self._plan is not None:  # (no lock: one `arm` moves meanwhile nudges)
            return due
        with self._lock:
            if self._plan is None:
                self._armed = False
                return None
            if self._slot - EARLY_S > now:
                return self._slot - EARLY_S
            if not self._armed:
                return math.inf
            self._in_flight = True
            return self._plan

    def poll_ended(self, packet: bytes, entry: Reply | BaseException) -> Told:
        """For the poll thread: the scheduled poll of `packet` ended with `entry` (its reply,
        whole or short, or the failure). Keeps it for the owner task and moves the schedule
        on; answers the owner's loop and what to run there, in the batch (the owner's wake-up
        where it should take the replies now, a `pause` that waited for this poll), or None
        (nothing to run: a repeat within its batch)."""
        return self._polls_over(packet, entry, None, None)

    @property
    def at_rest(self) -> bool:
        """Armed, and its last replies repeated (read without the lock: `rest_begin` looks
        again under it): the poll thread may poll it in C."""
        return self._armed and not self._changing and self._clean and not self._in_flight

    def rest_begin(self) -> RestPlan | bool:
        """For the poll thread, before it polls its links in C (app/links/_restpoll.c): this
        link's rounds there, (descriptor, request, the reply expected, timeout, next slot,
        period, when its batch is due (`time.monotonic()`), the replies it may still hold),
        the poll in flight from here until `rest_ended`; True if it is not armed (nothing to
        poll: an `arm` wakes the thread); False if it is not at rest (its last reply was not a
        repeat, a failure waits, its owner pauses it): the rounds run in Python."""
        with self._lock:
            plan = self._plan
            if plan is None or not self._armed:
                return True
            if (self._in_flight or self._paused is not None or self._closing
                    or self._changing or not self._clean or self._untold >= MAX_PREFETCHED
                    or len(self._last_data) != plan[2] or self._period <= 0):
                return False
            self._in_flight = self._resting = True
            fd, packet, _, timeout = plan
            return (fd, packet, self._last_data, timeout, self._slot, self._period,
                    self._batch_since + self._repeat_batch_s, MAX_PREFETCHED - self._untold)

    @property
    def _untold(self) -> int:
        """The replies held that the owner task was not woken for yet (MAX_PREFETCHED)."""
        return self._held - self._told

    def rest_ended(self, packet: bytes, slot: float, ats: list[float],
                   entry: Reply | BaseException | None) -> Told:
        """For the poll thread: its rounds in C since `rest_begin` ended, the schedule at
        `slot`, with repeats read at `ats` and the last poll's `entry` if it was not one
        (as `poll_ended` takes it). Answers as `poll_ended`."""
        return self._polls_over(packet, entry, slot, ats)

    def _wake_rest(self) -> None:
        """Wake the poll thread out of its rounds in C for this link (they end after the polls
        in flight): a pause waits for one poll at most, a new batch time holds at once."""
        if self._resting and (polls := self._polls) is not None:
            polls.nudge()

    def _polls_over(self, packet: bytes, entry: Reply | BaseException | None,
                    slot: float | None, ats: list[float] | None) -> Told:
        """What `poll_ended` and `rest_ended` do: the replies kept (a poll's `entry`, the
        repeats read in C at `ats`), the schedule moved on (to `slot`, from C), the owner
        task told if it should take them now and a pause that waited let go."""
        now = time.monotonic()
        with self._lock:
            self._in_flight = self._resting = False
            if self._closing:
                self._flight_ended.notify_all()
            paused = self._paused
            prefetched = self._prefetched
            if ats:
                prefetched.append((packet, Repeats(self._last_data, ats)))
                self._held += len(ats)
                self.stats["scheduled"] += len(ats)
            if slot is not None:
                self._slot = slot
            if entry is None:  # repeats (or nothing) read in C: every batch, as below
                if self._held >= MAX_PREFETCHED:
                    self._armed = False
                due = now - self._batch_since >= self._repeat_batch_s
                wake = bool(self._held) and (due or bool(ats) and not self._armed)
                if due and not wake:  # nothing to hand over: the next batch starts now
                    self._batch_since = now
            else:
                wake = self._one_ended_locked(packet, entry, now)
            notify = self._notify
            if wake:
                self._batch_since = now
                if notify is not None:  # (the owner takes what it was woken for, soon)
                    self._told = self._held
            if paused is not None:
                self._paused = None
            elif not wake or notify is None:
                return None
        calls: list[Callable[[], None]] = []
        if paused is not None:
            calls.append(lambda: resolve(paused))
        if wake and notify is not None:
            self.stats["wakes"] += 1
            calls.append(notify)
        loop = self._loop
        return None if loop is None else (loop, calls)

    def _one_ended_locked(self, packet: bytes, entry: Reply | BaseException, now: float) -> bool:
        """One scheduled poll's `entry` kept and the schedule moved on (`poll_ended`); whether
        the owner task should be woken now."""
        self._prefetched.append((packet, entry))
        self._held += 1
        self.stats["scheduled"] += 1
        period = self._period
        self._slot = following(self._slot, period)
        if self._slot < now - CATCH_UP * period:  # far behind: skip ahead, on the grid
            self._slot = aligned(now + period, period)
        data = entry.data if isinstance(entry, Reply) else b""
        plan = self._plan
        failed = len(data) != (plan[2] if plan is not None else 0) \
            or not isinstance(entry, Reply)
        if failed:
            self._clean = False
        if failed or self._held >= MAX_PREFETCHED:
            self._armed = False  # the owner task takes it from here
        changed = data != self._last_data
        # a reading that changes after repeats (a move starts: the samples a goal's or a
        # teleoperation's latency waits for) at once; while it goes on changing, every
        # MOVING_BATCH_S; repeats every BATCH_S (IDLE_BATCH_S with no reader)
        wake = (failed or not self._armed or (changed and not self._changing)
                or now - self._batch_since >= (MOVING_BATCH_S if changed
                                               else self._repeat_batch_s))
        self._changing = changed
        self._last_data = data
        return wake

    async def pause(self) -> None:
        """Stop the schedule; return once no scheduled poll is in flight."""
        loop = asyncio.get_running_loop()
        with self._lock:
            self._armed = False
            if not self._in_flight:
                return
            fut = self._paused = loop.create_future()
        self._wake_rest()
        await fut

    def drop_prefetched(self) -> None:
        """Forget the replies read ahead (after a failed poll: the driver's quiet wait would
        have discarded them as input it did not ask for)."""
        self._last_poll = None
        with self._lock:
            self.stats["dropped"] += self._held
            self._prefetched.clear()
            self._held = self._told = 0

    # ------------------------------------------------------------ loop side

    async def _call(self, fn: Callable[..., Any], *args: Any) -> Any:
        if self._thread is None or self.state is not LinkState.UP or self._loop is None:
            raise LinkError(self.last_error or f"serial link {self.address} is not open")
        if self._armed or self._in_flight:
            await self.pause()
        fut = self._loop.create_future()
        self._jobs.put((fn, args, fut))
        try:
            return await fut
        except (OSError, _Lost) as exc:
            raise self._lost(str(exc)) from exc

    async def _paused_fd(self) -> int | None:
        """The port's descriptor once the schedule is paused (None: pyserial without one):
        the owner task's own calls run on its loop, as an asyncio link's do; only the
        scheduled polls run on the thread."""
        if self._thread is None or self.state is not LinkState.UP or self._loop is None:
            raise LinkError(self.last_error or f"serial link {self.address} is not open")
        if self._armed or self._in_flight:
            await self.pause()
        return self._fd

    async def _transact_here(self, fd: int, packet: bytes, size: int, timeout: float) -> Reply:
        deadline = time.monotonic() + timeout
        rest = self._write_here(fd, packet)
        if rest:
            await self._call(self._write_all, rest)
        self.written_at = time.monotonic()
        data = b""
        first = True
        while len(data) < size:
            left = deadline - time.monotonic()
            if left <= 0:
                break
            chunk = await self._read_here(fd, left, not first)  # (just written: not there yet)
            first = False
            if not chunk:
                break
            data += chunk
        return Reply(data, deadline)

    def _write_here(self, fd: int, data: bytes) -> bytes:
        """Write what the descriptor takes now; the rest (a full transmit buffer)."""
        try:
            n = os.write(fd, data)
        except BlockingIOError:
            n = 0
        except OSError as exc:
            raise self._lost(str(exc)) from exc
        return data[n:]

    async def _read_here(self, fd: int, timeout: float, now_first: bool) -> bytes:
        """What arrives within `timeout` s, on the loop (one reader and one timer, no task)."""
        if now_first and (data := self._read_now(fd)) is not None:
            return data
        assert self._loop is not None
        loop = self._loop
        deadline = loop.time() + max(0.0, timeout)
        while True:
            fut: asyncio.Future[bool] = loop.create_future()
            loop.add_reader(fd, _settle_once, fut, True)
            timer = loop.call_at(deadline, _settle_once, fut, False)
            try:
                ready = await fut
            finally:
                timer.cancel()
                loop.remove_reader(fd)
            data = self._read_now(fd, ready)
            if data is not None:
                return data
            if loop.time() >= deadline:
                return b""

    def _read_now(self, fd: int, ready: bool = False) -> bytes | None:
        """The bytes waiting (None: none yet). Nothing read where the descriptor said it was
        ready is a lost port (a socket's end of file; a tty whose other end is gone, as
        pyserial's own read says)."""
        try:
            data = os.read(fd, READ_CHUNK)
        except BlockingIOError:
            return None
        except OSError as exc:  # a tty whose other end is gone: EIO
            raise self._lost(str(exc)) from exc
        if not data:
            if ready or self._socket:  # (a tty reads nothing when it has nothing)
                raise self._lost("closed by the peer (end of file)")
            return None
        return data

    def _settle(self, fut: asyncio.Future[Any], result: Any, exc: BaseException | None) -> None:
        """A job's outcome, on the loop. A caller that gave up leaves its bytes to the next."""
        if fut.done():
            if isinstance(result, bytes):
                self._stash += result
            elif isinstance(result, Reply):
                self._stash += result.data
            return
        if exc is not None:
            fut.set_exception(exc)
        else:
            fut.set_result(result)

    def _lost(self, reason: str) -> LinkError:
        """Mark the link DOWN and end its thread (which closes the port)."""
        with self._lock:
            self._armed = False
        if self._thread is not None:  # (its `_close_port` wakes rounds in C)
            self._jobs.put(_STOP)
        log.warning("serial link %s lost: %s", self.address, reason)
        return self._down(f"serial link {self.address} lost: {reason}")

    async def _stop_thread(self) -> None:
        thread, ended = self._thread, self._ended
        self._thread = None
        if thread is None or ended is None:
            return
        self._jobs.put(_STOP)
        if not ended.done():
            try:
                async with asyncio.timeout(CLOSE_TIMEOUT_S):
                    await asyncio.shield(ended)
            except TimeoutError:
                log.debug("serial link %s: its thread did not end within %.1f s",
                          self.address, CLOSE_TIMEOUT_S)

    # ------------------------------------------------------------ the thread

    def _main(self, loop: asyncio.AbstractEventLoop, ended: asyncio.Future[None]) -> None:
        # The owner's requests (the estop's hold among them) go out on this thread: it ranks
        # with the control thread, and says so, so that a terminal's hold brings it to the
        # default with the others. (Started from the control thread, it would otherwise keep
        # the -10 it inherits, unseen by the hold, above the kworker that delivers this very
        # port's bytes: docs/performance.md, "Session 29".)
        raise_priority(CONTROL_NICE)
        jobs = self._jobs
        try:
            while True:
                job = jobs.get()
                if job is _STOP:
                    return
                fn, args, fut = job
                result: Any = None
                error: BaseException | None = None
                try:
                    result = fn(*args)
                except Exception as exc:  # noqa: BLE001 - delivered to the caller, who raises it
                    error = exc
                loop.call_soon_threadsafe(self._settle, fut, result, error)
        except RuntimeError:  # the loop is closed: nobody is left to answer
            pass
        finally:
            self._close_port()
            lower_priority()
            try:
                loop.call_soon_threadsafe(resolve, ended)
            except RuntimeError:
                pass

    def _open_blocking(self) -> None:
        import serial

        # Exclusive (flock): a second server on the same port would break this one's link
        # mid-move; it is refused instead, told who holds the port.
        try:
            port = serial.serial_for_url(self.address, baudrate=self.baudrate, exclusive=True)
        except serial.SerialException as exc:
            raise _Lost(str(exc)) from exc
        fd = port_fileno(port)
        self._port, self._fd = port, fd
        self._socket = fd is not None and stat.S_ISSOCK(os.fstat(fd).st_mode)
        self._terminal = terminal_hold(fd)  # (the raised threads at 0 meanwhile)
        if fd is not None:
            self._poller = select.poll()
            self._poller.register(fd, select.POLLIN)

    def _close_port(self) -> None:
        with self._lock:  # the poll thread's poll in flight ends first (its own timeout)
            self._armed = False
            self._closing = True
            self._wake_rest()  # (rounds in C: back after the polls in flight)
            self._flight_ended.wait_for(lambda: not self._in_flight, CLOSE_TIMEOUT_S)
            self._closing = False
            port, self._port, self._fd, self._poller = self._port, None, None, None
            self._plan = None
            terminal, self._terminal = self._terminal, None
        if port is not None:
            try:
                port.close()
            except Exception as exc:  # noqa: BLE001 - a lost port: nothing left to do
                log.debug("serial link %s closed with %r", self.address, exc)
        if terminal is not None:
            terminal.release()

    def _transact(self, packet: bytes, size: int, timeout: float, stamp: bool) -> Reply:
        deadline = time.monotonic() + timeout
        self._write_all(packet)
        self.written_at = time.monotonic()
        data = b""
        while len(data) < size:
            left = deadline - time.monotonic()
            if left <= 0:
                break
            chunk = self._read_some(left)
            if not chunk:
                break
            data += chunk
        return Reply(data, deadline, time.time() if stamp else None)

    def _write_all(self, data: bytes) -> None:
        fd = self._fd
        if fd is None:
            if self._port is None:
                raise _Lost("closed")
            self._port.write(data)
            return
        view = memoryview(data)
        while view:
            try:
                view = view[os.write(fd, view):]
            except BlockingIOError:
                pass
            if view and not select.select([], [fd], [], WRITE_WAIT_S)[1]:
                raise _Lost(f"the port took no bytes for {WRITE_WAIT_S:.0f} s")

    def _read_some(self, timeout: float) -> bytes:
        """What arrives within `timeout` s (up to READ_CHUNK bytes), b"" if nothing."""
        fd, poller = self._fd, self._poller
        if fd is None or poller is None:
            port = self._port
            if port is None:
                raise _Lost("closed")
            port.timeout = timeout
            first: bytes = port.read(1)
            waiting = port.in_waiting if first else 0
            return first + (port.read(min(waiting, READ_CHUNK - 1)) if waiting else b"")
        if not poller.poll(max(0.0, timeout) * 1000.0):
            return b""
        try:
            data = os.read(fd, READ_CHUNK)
        except BlockingIOError:
            return b""
        if not data:
            raise _Lost("closed by the peer (end of file)")
        return data
