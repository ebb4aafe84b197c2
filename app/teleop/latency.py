"""A teleoperation session's figures: the latency from a leader sample to the follower's
command (p50, p99 over the last WINDOW commands) and the achieved command rate (over the last
RATE_WINDOW_S seconds). Plain numbers in, plain numbers out; no clock of its own."""

from __future__ import annotations

from collections import deque

import numpy as np

#: Latencies kept for the percentiles: the last 30 s at 100 Hz.
WINDOW = 3000
#: The achieved rate is measured over this many seconds of ticks.
RATE_WINDOW_S = 2.0


class TeleopStats:
    """Counts and the latency window of one session."""

    def __init__(self) -> None:
        self.commands = 0
        self.holds = 0
        self._latency: deque[float] = deque(maxlen=WINDOW)
        self._ticks: deque[float] = deque()

    def command(self, now: float, latency_s: float) -> None:
        """A setpoint sent at `now` (s, monotonic), `latency_s` after its leader sample."""
        self.commands += 1
        self._latency.append(latency_s)
        self._tick(now)

    def hold(self, now: float) -> None:
        """A tick that sent nothing: the follower holds its last command."""
        self.holds += 1
        self._tick(now)

    def _tick(self, now: float) -> None:
        self._ticks.append(now)
        while self._ticks and self._ticks[0] < now - RATE_WINDOW_S:
            self._ticks.popleft()

    def achieved_hz(self) -> float:
        """Ticks (commands and holds) per second over the last RATE_WINDOW_S s."""
        t = list(self._ticks)
        if len(t) < 2 or t[-1] <= t[0]:
            return 0.0
        return (len(t) - 1) / (t[-1] - t[0])

    def latency_ms(self) -> tuple[float, float] | None:
        """(p50, p99) in ms of the window, None before the first command."""
        lat = list(self._latency)
        if not lat:
            return None
        p50, p99 = np.percentile(np.asarray(lat, dtype=float) * 1e3, [50.0, 99.0])
        return float(p50), float(p99)
