"""One camera: the thread that owns its source, its latest frame, and that frame as JPEG,
encoded once (on the first request for it) however many clients look.

The thread is the only caller of the source (OpenCV's capture blocks); everyone else reads
`latest` (one attribute, replaced whole) or asks `jpeg()`. A source that fails makes the camera
down with its last error; it is opened again with capped exponential backoff. Nothing here runs
on the arms' control thread or the HTTP loop.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np

from app.cameras.config import CameraConfig
from app.cameras.sources import Source, SourceError

__all__ = ["BACKOFF_MAX_S", "BACKOFF_S", "Camera", "Frame"]

log = logging.getLogger(__name__)

#: First wait before opening a failed source again, s; doubles up to BACKOFF_MAX_S (a camera
#: plugged back in is seen within about that long; an absent one costs one open per 5 s).
BACKOFF_S = 0.1
BACKOFF_MAX_S = 5.0
#: An on-demand camera (a simulated one) stops rendering this long after the last request, s.
IDLE_AFTER_S = 5.0


@dataclass(frozen=True)
class Frame:
    seq: int
    #: Wall-clock time it was taken (s since the epoch), and the monotonic clock's.
    time: float
    mono: float
    image: np.ndarray


Listener = Callable[[Frame], None]


class Camera:
    """The owner thread of one camera's source and its latest frame."""

    def __init__(self, config: CameraConfig, source: Source, *, on_demand: bool = False) -> None:
        self.config = config
        self.name = config.name
        self.source = source
        #: Render only while someone asks (a simulated camera: no work while nobody looks).
        self.on_demand = on_demand
        self.latest: Frame | None = None
        self.up = False
        self.last_error: str | None = "not started"
        self.frames = 0
        self.connects = 0
        #: JPEG encodings done (one per frame asked for, whatever the number of clients).
        self.encodes = 0
        self._listeners: list[Listener] = []
        self._jpeg_lock = threading.Lock()
        self._jpeg: tuple[int, bytes] | None = None
        self._stop = threading.Event()
        self._wake = threading.Event()
        self._demand_at = 0.0
        self._thread = threading.Thread(target=self._run, name=f"camera-{self.name}",
                                        daemon=True)

    # ------------------------------------------------------------ any thread

    def start(self) -> None:
        self._thread.start()

    def stop(self, timeout: float = 2.0) -> None:
        """Stop the thread (a stream read blocked in FFmpeg ends within its read timeout; the
        thread is a daemon, so a stuck device never holds up the server's exit)."""
        self._stop.set()
        self._wake.set()
        if self._thread.is_alive():
            self._thread.join(timeout)

    def demand(self) -> None:
        """Someone wants frames now (an on-demand camera renders for IDLE_AFTER_S more)."""
        self._demand_at = time.monotonic()
        if self.on_demand:
            self._wake.set()

    def add_listener(self, fn: Listener) -> Callable[[], None]:
        """Call `fn(frame)` on the camera's thread for each new frame (keep it short: hand the
        frame over); returns the unsubscribe."""
        self._listeners = [*self._listeners, fn]

        def remove() -> None:
            self._listeners = [f for f in self._listeners if f is not fn]
        return remove

    def jpeg(self) -> tuple[int, bytes] | None:
        """The latest frame as (seq, JPEG bytes), encoded on the first call for that frame and
        kept; None before the first frame. Blocking: call it from a worker thread."""
        frame = self.latest
        if frame is None:
            return None
        with self._jpeg_lock:
            cached = self._jpeg
            if cached is not None and cached[0] >= frame.seq:
                return cached
            ok, buf = cv2.imencode(".jpg", frame.image,
                                   [cv2.IMWRITE_JPEG_QUALITY, self.config.jpeg_quality])
            if not ok:
                return cached
            self._jpeg = (frame.seq, buf.tobytes())
            self.encodes += 1
            return self._jpeg

    # ------------------------------------------------------------ the camera's thread

    def _idle(self) -> bool:
        return self.on_demand and time.monotonic() - self._demand_at > IDLE_AFTER_S

    def _run(self) -> None:
        backoff = BACKOFF_S
        while not self._stop.is_set():
            try:
                self.source.open()
            except SourceError as exc:
                self._down(str(exc))
            except Exception as exc:  # noqa: BLE001 - a camera bug is its state, never a crash
                log.exception("camera %s: open failed", self.name)
                self._down(f"open failed: {exc}")
            else:
                self.connects += 1
                try:
                    if self._serve():
                        backoff = BACKOFF_S
                finally:
                    self.source.close()
            if self._stop.wait(backoff):
                break
            backoff = min(backoff * 2.0, BACKOFF_MAX_S)

    def _serve(self) -> bool:
        """Read frames until the source fails or the camera stops; True if it gave any."""
        period = 1.0 / self.config.fps
        next_at = time.monotonic()
        gave = False
        while not self._stop.is_set():
            if gave and self._idle():  # an idle on-demand camera still shows its first frame
                self._wake.clear()
                if self._idle():
                    self._wake.wait(1.0)
                next_at = time.monotonic()
                continue
            try:
                image = self.source.read()
            except SourceError as exc:
                self._down(str(exc))
                return gave
            except Exception as exc:  # noqa: BLE001 - as above
                log.exception("camera %s: read failed", self.name)
                self._down(f"read failed: {exc}")
                return gave
            gave = True
            self._publish(image)
            if not self.source.paced:  # an absolute schedule at fps; late: skip ahead
                next_at += period
                delay = next_at - time.monotonic()
                if delay < -period:
                    next_at, delay = time.monotonic(), 0.0
                if delay > 0 and self._stop.wait(delay):
                    break
        return gave

    def _publish(self, image: np.ndarray) -> None:
        image.setflags(write=False)
        self.frames += 1
        frame = Frame(self.frames, time.time(), time.monotonic(), image)
        self.latest = frame
        if not self.up:
            self.up, self.last_error = True, None
            log.info("camera %s: up (%s)", self.name, self.config.source)
        for fn in self._listeners:
            try:
                fn(frame)
            except Exception:  # noqa: BLE001 - one listener's bug stops no camera
                log.exception("camera %s: listener failed", self.name)

    def _down(self, why: str) -> None:
        if self.up or self.last_error != why:
            level = logging.WARNING if self.up or self.last_error == "not started" else \
                logging.DEBUG
            log.log(level, "camera %s: down: %s", self.name, why)
        self.up, self.last_error = False, why
