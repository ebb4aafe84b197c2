"""The worker thread that encodes an episode's camera frames (app/recording/video.py), fed from
the HTTP loop through a bounded queue."""

from __future__ import annotations

import queue
import threading

import numpy as np

from app.recording.video import EpisodeVideo

#: Frames an encoder may fall behind (per episode, all cameras) before the episode ends.
QUEUE_FRAMES = 120


class RecordingError(Exception):
    """An episode ended on its own (camera lost, encoder behind, too long)."""


class Encoder:
    """The worker thread that encodes every camera's frames of one episode."""

    def __init__(self, videos: dict[str, EpisodeVideo]) -> None:
        self.videos = videos
        self.q: queue.Queue[tuple[str, np.ndarray] | None] = queue.Queue(QUEUE_FRAMES)
        self.error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name="recording-encoder", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while True:
            item = self.q.get()
            if item is None:
                return
            if self.error is not None:
                continue
            try:
                self.videos[item[0]].add(item[1])
            except Exception as exc:  # noqa: BLE001 - the episode reports it
                self.error = exc

    def put(self, cam: str, image: np.ndarray) -> None:
        try:
            self.q.put_nowait((cam, image))
        except queue.Full:
            raise RecordingError(f"the video encoder fell {QUEUE_FRAMES} frames behind") \
                from None
        if self.error is not None:
            raise RecordingError(f"video encoding failed: {self.error}")

    def finish(self) -> None:
        """Blocking: wait for the queue, close every file (worker thread)."""
        self.q.put(None)
        self._thread.join()
        if self.error is not None:
            raise RecordingError(f"video encoding failed: {self.error}")
        for v in self.videos.values():
            v.close()

    def abort(self) -> None:
        self.error = self.error or RecordingError("discarded")
        self.q.put(None)
        self._thread.join()
        for v in self.videos.values():
            v.abort()
