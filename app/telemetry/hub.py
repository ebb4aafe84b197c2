"""Per-arm telemetry hub: the latest sample, and fan-out to subscribers with bounded backlogs.

The driver publishes every device sample here (synchronously, never awaiting), so a slow
subscriber can never slow the link task (ARCHITECTURE rule 9). Each sample is encoded to JSON
once, at publish time (orjson), into ONE shared log; the cost of a publish does not grow with
the number of subscribers. A subscriber is a cursor into that log: `take` returns the encoded
strings since its cursor, and a telemetry message is those strings joined. Subscribers that
batch the same range of samples (the WebSocket senders wake on a shared clock, see
`take_message`) share one built message, so the cost per client is one send.

A subscriber has a bounded backlog: when it falls further behind than that, the oldest samples
are skipped and its `dropped` count grows, which it reports in its next message. Events have
their own bounded backlog per subscriber and are never batched away.

Threads: `publish` and `event` may be called from another thread than the subscribers'
(the control thread); the log is guarded by a lock held only for a few list operations, and a
subscriber waiting in `wait()` is woken on its own loop.

Derived fields at the readers' rate (issue 27). A publisher that gives `inputs` (the sample's
joint readings) and a hub with a `deriver` (`derive_with(model)`: app/telemetry/derive.py)
publishes the sample without its tip, tip velocity and tip force: they are computed, and the
sample encoded, when it is first read (a subscriber's take, `latest`, `GET /state`), for every
sample not yet read in one vectorised call, outside the lock. A sample nobody reads (no
subscriber, a log entry that ages out) costs no kinematics at all; one read costs the same
bytes as before. While a listener (`add_listener`: an estop's wait for its sample) is there,
each sample is derived as it is published, so a listener sees whole samples.

Repeats nobody reads, kept as the collector cannot see them (issue 27). An arm at rest
publishes the same reading again for each poll (`publish_run`); while the hub has no
subscriber, the log keeps each such copy as its own (seq, time) pair, a tuple of two numbers
that CPython's collector stops tracking at its first collection, instead of an object of its
own a sample. A lab worker's 16 arms at rest kept 32,000 of those objects alive, most of what
each full collection walked (20-29 ms with every thread of the worker stopped, once a minute:
docs/performance.md "Session 22"). Nobody reads such an entry: a subscriber's cursor starts at
the number of samples published when it subscribes and only moves on, so its ranges hold only
samples published while it was there (made as before); the entry keeps the log's numbering.
The run's last copy stays whole: it is the latest.
"""

from __future__ import annotations

import asyncio
import threading
import time
from collections import deque
from collections.abc import Callable
from typing import Any

import orjson

from app.runtime.tasks import resolve, soon_on

#: Samples a subscriber may fall behind before the oldest are dropped: 4 s at 500 Hz.
DEFAULT_BACKLOG = 2000
#: Events a subscriber may fall behind (events are rare: motion, estop, link).
EVENT_BACKLOG = 256
#: Built telemetry messages kept for reuse by subscribers that batch the same samples.
MESSAGE_CACHE = 8

_OPTIONS = orjson.OPT_SERIALIZE_NUMPY

#: Fills the derived fields of (sample, readings) pairs in place (app/telemetry/derive.py).
Deriver = Callable[[list[tuple[dict[str, Any], Any]]], None]


class _Lazy:
    """A published sample whose derived fields and encoding wait for its first reader. A run's
    copy (`publish_run`) holds the run's sample, its own seq and time, and its dict is made
    at its first read too (`_whole`): one small object a sample, no dict, in the log."""

    __slots__ = ("base", "data", "encoded", "inputs", "sample", "seq", "time")

    def __init__(self, sample: dict[str, Any] | None, inputs: Any,
                 base: dict[str, Any] | None = None, seq: int = 0, time: float = 0.0) -> None:
        #: The sample (None: `base` with `seq` and `time`, until `_whole` makes it).
        self.sample = sample
        self.inputs = inputs
        self.base, self.seq, self.time = base, seq, time
        self.encoded: str | None = None
        self.data: bytes | None = None


_WHOLE = threading.Lock()


def _whole(entries: list[_Lazy]) -> None:
    """Make the sample dicts of a run's copies (`TelemetryHub.publish_run`) among `entries`,
    once: under a lock of its own, as two readers may reach the same entries at once (and one
    of them may hold the hub's lock)."""
    with _WHOLE:
        for e in entries:
            if e.sample is None and e.base is not None:
                sample = dict(e.base)
                sample["seq"], sample["time"] = e.seq, e.time
                e.sample, e.base = sample, None


def _encode(obj: Any) -> tuple[str, bytes]:
    """A sample's JSON as text and as bytes, each its own size. orjson (3.13) returns bytes
    that keep the buffer it wrote into, 4 KiB for a 560-byte sample (tracemalloc): kept in
    the log, that was 4 KiB a sample read, the soak's memory growth (docs/performance.md).
    The bytes are made again from the text (one copy of a few hundred bytes)."""
    encoded = _dumps(obj)
    return encoded, encoded.encode()


def _dumps(obj: Any) -> str:
    """Compact JSON text (orjson; numpy scalars and arrays allowed, NaN becomes null)."""
    return orjson.dumps(obj, option=_OPTIONS).decode()


class Subscription:
    """One subscriber's view of a hub. `take()` (or `take_message()`), `close()` when done."""

    def __init__(self, hub: TelemetryHub, backlog: int, cursor: int, initial: str | None) -> None:
        self._hub = hub
        self.backlog = backlog
        #: Index in the hub's log of the next sample this subscriber has not taken.
        self.cursor = cursor
        #: The latest sample when subscribing (None before the first): sent first, and never
        #: again, since the log from `cursor` on holds only later samples.
        self.initial = initial
        self._events: deque[str] = deque(maxlen=EVENT_BACKLOG)
        self._waiter: asyncio.Future[None] | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self.dropped = 0
        self.delivered = 0
        self.closed = False

    @property
    def hub(self) -> TelemetryHub:
        """The log this subscription reads (a broadcast groups its members by it)."""
        return self._hub

    def _push_event(self, encoded: str) -> None:
        self._events.append(encoded)
        self._wake()

    def _wake(self) -> None:
        fut, loop = self._waiter, self._loop
        if fut is None or loop is None or fut.done():
            return
        soon_on(loop, resolve, fut)

    @property
    def has_events(self) -> bool:
        return bool(self._events)

    @property
    def pending(self) -> bool:
        return bool(self._events) or self.cursor < self._hub.published

    async def wait(self, timeout: float | None = None) -> bool:
        """Wait until a sample or event is pending; False on timeout."""
        if self.pending:
            return True
        loop = asyncio.get_running_loop()
        self._loop = loop
        self._waiter = fut = loop.create_future()
        self._hub._add_waiter(self)
        timer = None if timeout is None else loop.call_at(loop.time() + timeout, resolve, fut)
        try:
            if self.pending:  # published between the check and the registration
                return True
            await fut
        finally:
            self._waiter = None
            self._hub._remove_waiter(self)
            if timer is not None:
                timer.cancel()
        return self.pending

    def take(self) -> tuple[list[str], list[str], int]:
        """Pending encoded samples and events, and the drop count since the last take."""
        samples, lost = self._hub._take(self, None)
        dropped, self.dropped = self.dropped + lost, 0
        self.delivered += len(samples)
        return samples, self.take_events(), dropped

    def take_events(self) -> list[str]:
        """Pending encoded events (oldest first)."""
        events = list(self._events)
        self._events.clear()
        return events

    def take_message(self, until: float | None = None) -> str | None:
        """The telemetry message (encoded) for every sample published before monotonic time
        `until` (all if None) since the last take, or None if there is nothing to say.
        Subscribers that take the same range with no drops share one built message."""
        return self._hub._message(self, until)

    def telemetry_message(self, samples: list[str], dropped: int) -> str:
        """The wire message for a batch, built from pre-encoded samples."""
        return self._hub._build(samples, dropped)

    def close(self) -> None:
        if not self.closed:
            self.closed = True
            self._hub._unsubscribe(self)


class TelemetryHub:
    """Latest sample and subscribers of one arm."""

    def __init__(self, arm: str, backlog: int = DEFAULT_BACKLOG) -> None:
        self.arm = arm
        self.arm_json = _dumps(arm)
        self.backlog = backlog
        self._lock = threading.Lock()
        self._subs: set[Subscription] = set()
        self._waiting: set[Subscription] = set()
        self._listeners: list[Callable[[dict[str, Any]], None]] = []
        #: The shared log: encoded samples and their publish times (monotonic), oldest first;
        #: entry i of the deques is sample number `published - len(_log) + i`.
        self._log: deque[str | _Lazy | tuple[int, float]] = deque(maxlen=backlog)
        self._stamps: deque[float] = deque(maxlen=backlog)
        self._cache: dict[tuple[int, int, int], str] = {}
        #: (sample dict, encoded str, encoded bytes) of the latest sample, replaced as a whole.
        self._latest: tuple[dict[str, Any], str, bytes] | _Lazy | None = None
        #: Computes published samples' derived fields at their first read (None: the
        #: publisher gives whole samples). `derive_with` sets it.
        self.deriver: Deriver | None = None
        #: Lazy samples in the log not yet read, oldest first (bounded like the log).
        self._unread: deque[_Lazy] = deque(maxlen=backlog)
        self.published = 0
        #: Samples subscribers have lost to their backlog bound, all of them together (what
        #: their `dropped` fields told them): 0 means every subscriber got every sample.
        self.dropped_total = 0
        #: Called with the number of readers (`readers`) whenever it changes, from the thread
        #: that changed it and under the hub's lock (changes told in the order they were made;
        #: it must not take that lock): the owner task's hook (how often an arm at rest hands
        #: over the replies that repeat, app/links/threaded.py `batch_repeats`).
        self.on_readers: Callable[[int], None] | None = None
        #: The fan-out's loop and thread (the HTTP loop), when the publisher runs elsewhere.
        self._fanout_loop: asyncio.AbstractEventLoop | None = None
        self._fanout_thread: int | None = None

    def bind_fanout(self) -> None:
        """Fan events out on the running loop (the HTTP loop) whatever thread sends them: from
        the control thread they cross with `call_soon_threadsafe` (rare, never dropped; each
        subscriber's event backlog is bounded). Samples need no crossing: the shared log is
        locked and a waiting subscriber is woken with `call_soon_threadsafe`."""
        self._fanout_loop = asyncio.get_running_loop()
        self._fanout_thread = threading.get_ident()

    def _cross(self, fn: Callable[[Any], None], item: Any) -> bool:
        """Hand `fn(item)` to the fan-out loop if called from another thread; False if the
        caller is on the fan-out thread (or none is bound) and should run it itself."""
        loop = self._fanout_loop
        if loop is None or threading.get_ident() == self._fanout_thread:
            return False
        try:
            loop.call_soon_threadsafe(fn, item)
        except RuntimeError:  # the HTTP loop is closed: nobody to fan out to
            pass
        return True

    # ---------------------------------------------------------------- latest sample

    def derive_with(self, model: Callable[[], Any]) -> None:
        """Publish samples with `inputs` lazily: their tip, tip velocity and tip force from
        `model()` (the arm's `KinematicsModel` as it is then) at their first read (module
        doc)."""
        from app.telemetry.derive import Derivation

        self.deriver = Derivation(model)

    def _ready(self, entries: list[_Lazy]) -> None:
        """Derive and encode the entries not done yet, in one batch. Outside the lock: two
        readers racing on the same entries compute the same values twice, harmlessly."""
        # inputs taken once: another reader that finished an entry has encoded it first and
        # then let its inputs go (None)
        pairs = [(e, e.inputs) for e in entries if e.encoded is None]
        todo = [e for e, inputs in pairs if inputs is not None]
        if not todo:
            return
        _whole(todo)
        if self.deriver is not None:
            self.deriver([(e.sample, inputs) for e, inputs in pairs
                          if inputs is not None and e.sample is not None])
        for e in todo:
            encoded, data = _encode(e.sample)
            e.data = data  # before `encoded`: a reader that sees it set finds both
            e.encoded = encoded
            e.inputs = None

    def _ready_unread(self) -> None:
        """Derive every sample in the log not read yet (before a take, outside the lock)."""
        if not self._unread:
            return
        with self._lock:
            entries = list(self._unread)
            self._unread.clear()
        self._ready(entries)

    def _snapshot(self) -> tuple[dict[str, Any], str, bytes] | None:
        snap = self._latest
        if snap is None or isinstance(snap, tuple):
            return snap
        self._ready([snap])
        assert snap.encoded is not None and snap.data is not None and snap.sample is not None
        return snap.sample, snap.encoded, snap.data

    @property
    def latest(self) -> dict[str, Any] | None:
        snap = self._snapshot()
        return None if snap is None else snap[0]

    @property
    def latest_json(self) -> str | None:
        snap = self._snapshot()
        return None if snap is None else snap[1]

    @property
    def latest_bytes(self) -> bytes | None:
        """The latest sample as encoded JSON bytes, ready for an HTTP body."""
        snap = self._snapshot()
        return None if snap is None else snap[2]

    # ---------------------------------------------------------------- subscribers

    @property
    def subscriber_count(self) -> int:
        return len(self._subs)

    @property
    def readers(self) -> int:
        """Who takes the samples as they are published: subscribers and listeners."""
        return len(self._subs) + len(self._listeners)

    def _readers_changed(self) -> None:
        """Tell `on_readers` (under the lock)."""
        hook = self.on_readers
        if hook is not None:
            hook(self.readers)

    def subscribe(self, backlog: int | None = None) -> Subscription:
        backlog = backlog or self.backlog
        with self._lock:
            if backlog > (self._log.maxlen or 0):  # the shared log holds the longest backlog
                self._log = deque(self._log, maxlen=backlog)
                self._stamps = deque(self._stamps, maxlen=backlog)
                self._unread = deque(self._unread, maxlen=backlog)
            snap = self._latest  # the latest as of the cursor, taken with it
            sub = Subscription(self, backlog, self.published, None)
            self._subs.add(sub)
            self._readers_changed()
        # derived after the lock (a sample published meanwhile is in the log after the cursor:
        # none lost, none twice). Deriving "the latest" before the lock and reading it again
        # under it began the subscription with no initial sample when the publisher's thread
        # published in between (a loaded machine).
        if isinstance(snap, _Lazy):
            self._ready([snap])
            sub.initial = snap.encoded
        elif snap is not None:
            sub.initial = snap[1]
        return sub

    def _unsubscribe(self, sub: Subscription) -> None:
        with self._lock:
            self._subs.discard(sub)
            self._readers_changed()
        self._remove_waiter(sub)

    def _add_waiter(self, sub: Subscription) -> None:
        with self._lock:
            self._waiting.add(sub)

    def _remove_waiter(self, sub: Subscription) -> None:
        with self._lock:
            self._waiting.discard(sub)

    def add_listener(self, fn: Callable[[dict[str, Any]], None]) -> Callable[[], None]:
        """Call `fn(sample)` on every sample, in the publisher's task (on the control thread
        when there is one); returns an unsubscribe."""
        with self._lock:
            self._listeners.append(fn)
            self._readers_changed()

        def remove() -> None:
            with self._lock:
                if fn in self._listeners:
                    self._listeners.remove(fn)
                    self._readers_changed()
        return remove

    async def sample_where(self, pred: Callable[[dict[str, Any]], bool], timeout: float,
                           then: Callable[[], None] | None = None) -> bool:
        """Call `then()` (if given), and wait on this loop until a sample satisfying `pred` is
        published (True) or `timeout` seconds pass (False); the subscribers that sample wakes
        on this loop run first. `pred` runs in the publisher's thread; it sees every sample
        published after `then` is called."""
        loop = asyncio.get_running_loop()
        seen = loop.create_future()

        def check(sample: dict[str, Any]) -> None:
            if pred(sample):  # resumed after the subscribers this sample wakes have run
                loop.call_soon_threadsafe(loop.call_soon, resolve, seen)

        remove = self.add_listener(check)
        try:
            if then is not None:
                then()
            async with asyncio.timeout(timeout):
                await seen
        except TimeoutError:
            return False
        else:
            return True
        finally:
            remove()

    # ---------------------------------------------------------------- publishing

    def publish(self, sample: dict[str, Any], inputs: Any = None) -> None:
        """Publish one sample (a dict in the `Sample` schema's shape). Never blocks. With
        `inputs` (its joint readings) and a `deriver`, its derived fields wait for its first
        reader (module doc)."""
        if inputs is not None and self.deriver is not None:
            lazy = _Lazy(sample, inputs)
            with self._lock:
                self._latest = lazy
                self._log.append(lazy)
                if self._subs:  # a new subscriber starts after it: with none, none reads it
                    self._unread.append(lazy)
                self._stamps.append(time.monotonic())
                self.published += 1
                waiting = list(self._waiting) if self._waiting else None
            if self._listeners:  # they see whole samples (rare: an estop's wait, a test's)
                self._ready([lazy])
            self._after_publish(sample, waiting)
            return
        encoded, data = _encode(sample)
        with self._lock:
            self._latest = (sample, encoded, data)
            self._log.append(encoded)
            self._stamps.append(time.monotonic())
            self.published += 1
            waiting = list(self._waiting) if self._waiting else None
        self._after_publish(sample, waiting)

    def publish_run(self, sample: dict[str, Any], stamps: list[tuple[int, float]],
                    inputs: Any = None) -> None:
        """Publish `sample` again once for each (seq, time) of `stamps`, in order: what
        `publish` of each copy in turn gives (the log, `latest`, every subscriber's messages),
        in one step (a run of replies that repeat the last one: app/device/owner.py `_repeat`).
        Copies share the fields `sample` holds (never changed once published); with derived
        fields to wait for, each copy's dict is made at its first read too (`_Lazy`), and
        while nobody subscribes each copy but the last (the latest) is kept as its (seq,
        time) pair from `stamps` (module doc)."""
        if inputs is None or self.deriver is None or self._listeners:
            for seq, t in stamps:  # whole samples, or a listener to call for each: one by one
                again = dict(sample)
                again["seq"], again["time"] = seq, t
                self.publish(again, inputs)
            return
        n = len(stamps)
        last = _Lazy(None, inputs, sample, *stamps[-1])  # dicts when read
        now = time.monotonic()
        with self._lock:
            self._latest = last
            if self._subs:  # read as they come
                run = [_Lazy(None, inputs, sample, seq, t) for seq, t in stamps[:-1]]
                run.append(last)
                self._log.extend(run)
                self._unread.extend(run)
            else:  # read by nobody: a subscriber's range begins after it came (module doc)
                self._log.extend(stamps[:-1])
                self._log.append(last)
            self._stamps.extend([now] * n)
            self.published += n
            waiting = list(self._waiting) if self._waiting else None
        if waiting:
            for sub in waiting:
                sub._wake()

    def _after_publish(self, sample: dict[str, Any], waiting: list[Subscription] | None) -> None:
        for fn in list(self._listeners):
            fn(sample)
        if waiting:
            for sub in waiting:
                sub._wake()

    def event(self, name: str, **data: Any) -> dict[str, Any]:
        """Send an event (motion_started, estop, link_lost, ...) to every subscriber."""
        msg = {"type": "event", "arm": self.arm, "event": name, "time": time.time(), "data": data}
        if not self._cross(self._fan_out_event, msg):
            self._fan_out_event(msg)
        return msg

    def _fan_out_event(self, msg: dict[str, Any]) -> None:
        encoded = _dumps(msg)
        with self._lock:
            subs = list(self._subs)
        for sub in subs:
            sub._push_event(encoded)

    # ---------------------------------------------------------------- taking

    def _take(self, sub: Subscription, until: float | None) -> tuple[list[str], int]:
        """The encoded samples for `sub` since its cursor (published before `until`), and how
        many it lost to its backlog bound; advances its cursor."""
        self._ready_unread()
        with self._lock:
            return self._take_locked(sub, until)

    def _end_locked(self, until: float | None) -> int:
        """One past the number of the last sample published before `until` (all if None)."""
        end = self.published
        if until is not None:
            stamps = self._stamps
            k = len(stamps)
            while k > 0 and stamps[k - 1] >= until:
                k -= 1
            end -= len(stamps) - k
        return end

    def _range_locked(self, sub: Subscription, end: int) -> tuple[int, int, int]:
        """(first, end, lost): `sub`'s next samples are numbers first..end-1 (`end` from
        `_end_locked`); `lost` were skipped by its backlog bound. Advances its cursor."""
        oldest = max(self.published - len(self._log), end - sub.backlog)
        lost = 0
        if sub.cursor < oldest:
            lost = oldest - sub.cursor
            sub.cursor = oldest
            self.dropped_total += lost
        first = sub.cursor
        if end > first:
            sub.cursor = end
        return first, max(first, end), lost

    def _slice_locked(self, first: int, end: int) -> list[str]:
        log = self._log
        start = first - (self.published - len(log))
        out = [log[i] for i in range(start, start + end - first)]
        late = [e for e in out if isinstance(e, _Lazy) and e.encoded is None]
        if late:  # published after `_ready_unread` (rare): derived here, under the lock
            self._ready(late)
        return [e if isinstance(e, str) else e.encoded for e in out]  # type: ignore[union-attr,misc]

    def _take_locked(self, sub: Subscription, until: float | None) -> tuple[list[str], int]:
        first, end, lost = self._range_locked(sub, self._end_locked(until))
        return self._slice_locked(first, end), lost

    def _message(self, sub: Subscription, until: float | None) -> str | None:
        self._ready_unread()
        with self._lock:
            return self._message_locked(sub, self._end_locked(until))

    def messages(self, subs: list[Subscription], until: float | None) -> list[str | None]:
        """`take_message(until)` for each of `subs`, under one acquisition of the lock (the
        broadcast fan-out: subscribers at the same cursor get the same str object)."""
        self._ready_unread()
        with self._lock:
            end = self._end_locked(until)  # the same for every one of them
            return [self._message_locked(sub, end) for sub in subs]

    def _message_locked(self, sub: Subscription, end_until: int) -> str | None:
        first, end, lost = self._range_locked(sub, end_until)
        dropped = sub.dropped + lost
        sub.dropped = 0
        if end == first and not dropped:
            return None
        sub.delivered += end - first
        key = (first, end, dropped)
        msg = self._cache.get(key)
        if msg is None:
            msg = self._build(self._slice_locked(first, end), dropped)
            if len(self._cache) >= MESSAGE_CACHE:
                self._cache.clear()
            self._cache[key] = msg
        return msg

    def _build(self, samples: list[str], dropped: int) -> str:
        return (f'{{"type":"telemetry","arm":{self.arm_json},'
                f'"samples":[{",".join(samples)}],"dropped":{dropped}}}')

