"""What an episode reads: each arm's telemetry samples (`ArmTrack`, resampled onto the grid)
and each camera's frames (`CameraFeed`, `CameraTrack`: the frame nearest each grid time)."""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import orjson

from app.recording.dataset import ArmLayout
from app.recording.grid import resample
from app.service import ArmService

#: Telemetry samples a recording may fall behind before the oldest are dropped (the hub's
#: backlog for this subscriber: 8 s at 500 Hz).
SAMPLE_BACKLOG = 4000


@dataclass(frozen=True)
class CameraFrame:
    seq: int
    time: float  # wall clock, s
    image: np.ndarray  # (H, W, 3) uint8 BGR


@dataclass
class CameraFeed:
    """What a recording needs of a camera: its size, its latest frame (None before any) and,
    where the camera offers it, a call for every new frame (`listen(fn)` -> the unsubscribe;
    `fn` runs on the camera's thread)."""
    name: str
    width: int
    height: int
    latest: Callable[[], CameraFrame | None]
    listen: Callable[[Callable[[CameraFrame], None]], Callable[[], None]] | None = None


class ArmTrack:
    """One arm's samples not yet resampled: per sample its state (joints, then gripper) and
    its joints' velocities, in one row."""

    def __init__(self, svc: ArmService, layout: ArmLayout) -> None:
        self.svc, self.layout = svc, layout
        self.sub = svc.subscribe(SAMPLE_BACKLOG)
        self.times: deque[float] = deque()
        self.values: deque[list[float]] = deque()
        self.gripper: float = 0.0
        if self.sub.initial is not None:
            self._add(self.sub.initial)

    def _add(self, encoded: str) -> None:
        s = orjson.loads(encoded)
        if s.get("positions") is None or s.get("time") is None:
            return
        row = [float(x) for x in s["positions"]]
        if self.layout.gripper:
            g = s.get("gripper")
            self.gripper = float(g) if g is not None else self.gripper
            row.append(self.gripper)
        v = s.get("velocities")
        row.extend([float(x) for x in v] if v is not None else [0.0] * len(self.layout.joints))
        if self.times and s["time"] <= self.times[-1]:
            return
        self.times.append(float(s["time"]))
        self.values.append(row)

    def take(self) -> None:
        samples, _, _ = self.sub.take()
        for enc in samples:
            self._add(enc)

    @property
    def last_time(self) -> float:
        return self.times[-1] if self.times else -np.inf

    def states_at(self, at: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """States and velocities resampled at `at` (all before `last_time`, or the episode's
        end); then the samples older than the one just before `at[-1]` are dropped."""
        out = resample(list(self.times), np.asarray(self.values), at)
        while len(self.times) > 2 and self.times[1] <= at[-1]:
            self.times.popleft()
            self.values.popleft()
        d = len(self.layout.names)
        return out[:, :d], out[:, d:]

    def action(self) -> list[float]:
        q = self.svc.setpoint()
        if q is None:
            q = np.asarray(self.values[-1][:len(self.layout.joints)]) if self.values else \
                np.zeros(len(self.layout.joints))
        out = [float(x) for x in q]
        if not self.layout.gripper:
            return out
        g = self.svc.gripper_setpoint()
        return out + [self.gripper if g is None else float(g)]  # measured until commanded

    def close(self) -> None:
        self.sub.close()


class CameraTrack:
    """One camera's frames during an episode: for each grid point not yet imaged, the frame
    nearest it of all the camera gave (every frame, where it can be listened to; else those
    seen at the ticks)."""

    def __init__(self, feed: CameraFeed, t0: float, fps: int) -> None:
        self.feed, self.t0, self.fps = feed, t0, fps
        #: Filled by the camera's thread (deque appends are atomic), drained at each tick.
        self.incoming: deque[CameraFrame] = deque(maxlen=256)
        self.recent: deque[CameraFrame] = deque(maxlen=4)
        self.best: dict[int, CameraFrame] = {}
        self.last_seq = -1
        self._unlisten = feed.listen(self.incoming.append) if feed.listen is not None else None
        # the camera's latest frame as the episode starts: taken before t0, it may be the
        # nearest to frame 0's grid time, and the listener never hears it (a first tick late
        # on a loaded machine found a later frame as the latest, and imaged that one)
        first = feed.latest()
        if first is not None:
            self.incoming.append(first)

    def at(self, k: int) -> float:
        return self.t0 + k / self.fps

    def poll(self, imaged: int) -> None:
        f = self.feed.latest()
        if f is not None:
            self.incoming.append(f)
        while self.incoming:
            f = self.incoming.popleft()
            if f.seq <= self.last_seq:
                continue
            self.last_seq = f.seq
            self.recent.append(f)
            below = math.floor((f.time - self.t0) * self.fps)
            for k in (below, below + 1):
                cur = self.best.get(k)
                if k >= imaged and (cur is None or
                                    abs(f.time - self.at(k)) < abs(cur.time - self.at(k))):
                    self.best[k] = f

    @property
    def last_time(self) -> float | None:
        return self.recent[-1].time if self.recent else None

    def frame_for(self, k: int) -> CameraFrame:
        """Frame k's image (a frame must have been seen)."""
        f = self.best.pop(k, None)
        for j in [j for j in self.best if j < k]:
            del self.best[j]
        if f is None:
            f = min(self.recent, key=lambda fr: abs(fr.time - self.at(k)))
        return f

    def close(self) -> None:
        if self._unlisten is not None:
            self._unlisten()
            self._unlisten = None
