"""Per-arm telemetry hub: the latest sample, and fan-out to subscribers with bounded backlogs.

The driver task publishes every device sample here (synchronously, never awaiting), so a slow
subscriber can never slow the link task (ARCHITECTURE rule 9). Each sample is encoded to JSON
once, at publish time; a subscriber's message is those pre-encoded strings joined, so the cost
per client is a string join, not a re-serialisation.

A subscriber has a bounded backlog: when it is full the oldest sample is discarded and the
subscriber's `dropped` count grows, which it reports in its next message. Events have their own
bounded backlog and are never batched away.
"""

from __future__ import annotations

import asyncio
import json
import threading
import time
from collections import deque
from collections.abc import Callable
from typing import Any

#: Samples a subscriber may fall behind before the oldest are dropped: 4 s at 500 Hz.
DEFAULT_BACKLOG = 2000
#: Events a subscriber may fall behind (events are rare: motion, estop, link).
EVENT_BACKLOG = 256
#: Samples and events published on the control thread that may wait for the HTTP loop's
#: fan-out (1 s at 500 Hz): past it the fan-out is late and new samples skip it (counted in
#: `crossing_dropped`); the latest sample is always current.
CROSSING_BACKLOG = 500


def _dumps(obj: Any) -> str:
    return json.dumps(obj, separators=(",", ":"), allow_nan=False)


class Subscription:
    """One subscriber's view of a hub. Use `async for` or `next_batch()`; `close()` when done."""

    def __init__(self, hub: TelemetryHub, backlog: int) -> None:
        self._hub = hub
        self._samples: deque[str] = deque(maxlen=backlog)
        self._events: deque[str] = deque(maxlen=EVENT_BACKLOG)
        self._wake = asyncio.Event()
        self.dropped = 0
        self.delivered = 0
        self.closed = False

    def _push_sample(self, encoded: str) -> None:
        if len(self._samples) == self._samples.maxlen:
            self.dropped += 1
        self._samples.append(encoded)
        self._wake.set()

    def _push_event(self, encoded: str) -> None:
        self._events.append(encoded)
        self._wake.set()

    async def wait(self, timeout: float | None = None) -> bool:
        """Wait until a sample or event is pending; False on timeout."""
        if self._samples or self._events:
            return True
        self._wake.clear()
        try:
            await asyncio.wait_for(self._wake.wait(), timeout)
        except TimeoutError:
            return False
        return True

    def take(self) -> tuple[list[str], list[str], int]:
        """Pending encoded samples and events, and the drop count since the last take."""
        samples = list(self._samples)
        self._samples.clear()
        events = list(self._events)
        self._events.clear()
        dropped, self.dropped = self.dropped, 0
        self.delivered += len(samples)
        self._wake.clear()
        return samples, events, dropped

    def telemetry_message(self, samples: list[str], dropped: int) -> str:
        """The wire message for a batch, built from pre-encoded samples."""
        return (
            f'{{"type":"telemetry","arm":{self._hub.arm_json},'
            f'"samples":[{",".join(samples)}],"dropped":{dropped}}}'
        )

    def close(self) -> None:
        if not self.closed:
            self.closed = True
            self._hub._subs.discard(self)


class TelemetryHub:
    """Latest sample and subscribers of one arm."""

    def __init__(self, arm: str, backlog: int = DEFAULT_BACKLOG) -> None:
        self.arm = arm
        self.arm_json = _dumps(arm)
        self.backlog = backlog
        self._subs: set[Subscription] = set()
        self._listeners: list[Callable[[dict[str, Any]], None]] = []
        self.latest: dict[str, Any] | None = None
        self.latest_json: str | None = None
        self.published = 0
        #: The fan-out's loop and thread (the HTTP loop), when the publisher runs elsewhere.
        self._fanout_loop: asyncio.AbstractEventLoop | None = None
        self._fanout_thread: int | None = None
        self._crossed = 0  # written by the publishing thread only
        self._arrived = 0  # written by the fan-out thread only
        self.crossing_dropped = 0

    def bind_fanout(self) -> None:
        """Fan out on the running loop (the HTTP loop) whatever thread publishes: samples and
        events from the control thread cross with `call_soon_threadsafe`, bounded."""
        self._fanout_loop = asyncio.get_running_loop()
        self._fanout_thread = threading.get_ident()

    def _cross(self, fn: Callable[[Any], None], item: Any, droppable: bool) -> bool:
        """Hand `fn(item)` to the fan-out loop if called from another thread; False if the
        caller is on the fan-out thread (or none is bound) and should run it itself."""
        loop = self._fanout_loop
        if loop is None or threading.get_ident() == self._fanout_thread:
            return False
        if droppable and self._crossed - self._arrived >= CROSSING_BACKLOG:
            self.crossing_dropped += 1
            return True
        self._crossed += 1
        try:
            loop.call_soon_threadsafe(self._arrive, fn, item)
        except RuntimeError:  # the HTTP loop is closed: nobody to fan out to
            pass
        return True

    def _arrive(self, fn: Callable[[Any], None], item: Any) -> None:
        self._arrived += 1
        fn(item)

    @property
    def subscriber_count(self) -> int:
        return len(self._subs)

    def subscribe(self, backlog: int | None = None) -> Subscription:
        sub = Subscription(self, backlog or self.backlog)
        self._subs.add(sub)
        return sub

    def add_listener(self, fn: Callable[[dict[str, Any]], None]) -> Callable[[], None]:
        """Call `fn(sample)` on every sample, in the publisher's task (on the control thread
        when there is one); returns an unsubscribe."""
        self._listeners.append(fn)
        return lambda: self._listeners.remove(fn) if fn in self._listeners else None

    def publish(self, sample: dict[str, Any]) -> None:
        """Publish one sample (a dict in the `Sample` schema's shape), from any thread. Never
        blocks: `latest` is current at once, the fan-out happens on the fan-out loop."""
        self.latest = sample
        for fn in list(self._listeners):
            fn(sample)
        if not self._cross(self._fan_out, sample, droppable=True):
            self._fan_out(sample)

    def _fan_out(self, sample: dict[str, Any]) -> None:
        encoded = _dumps(sample)
        self.latest_json = encoded
        self.published += 1
        for sub in self._subs:
            sub._push_sample(encoded)

    def event(self, name: str, **data: Any) -> dict[str, Any]:
        """Send an event (motion_started, estop, link_lost, ...) to every subscriber."""
        msg = {"type": "event", "arm": self.arm, "event": name, "time": time.time(), "data": data}
        if not self._cross(self._fan_out_event, msg, droppable=False):
            self._fan_out_event(msg)
        return msg

    def _fan_out_event(self, msg: dict[str, Any]) -> None:
        encoded = _dumps(msg)
        for sub in self._subs:
            sub._push_event(encoded)
