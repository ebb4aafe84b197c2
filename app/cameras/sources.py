"""Where frames come from: OpenCV's `VideoCapture` (a V4L2 device, a network stream, a video
file), a folder of images, or a simulated arm's rendered table. Each call blocks; only the
camera's own thread (app/cameras/camera.py) calls them.

OpenCV's headless build does the capture (V4L2 and FFmpeg backends, `cv2.VideoCapture`) and the
decoding; its calls release the GIL while they wait or decode, so a camera thread costs the
arms' control thread little.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from app.cameras.config import CameraConfig

__all__ = ["IMAGE_SUFFIXES", "CaptureSource", "FolderSource", "RenderSource", "Source",
           "SourceError"]

#: Image files a folder source plays (what `cv2.imread` decodes).
IMAGE_SUFFIXES = frozenset({".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp"})
#: How long FFmpeg may take to open a stream or to read one frame of it, ms: a stream that
#: stops is noticed within this, rather than blocking the camera's thread for FFmpeg's default.
STREAM_TIMEOUT_MS = 3000


class SourceError(Exception):
    """The source gives no frame now (the reason is the camera's `last_error`)."""


class Source:
    """Open, read frames, close. `paced`: reads wait for the device's own next frame (a
    camera, a stream); otherwise the camera's thread paces reads at the configured fps."""

    paced = False

    def open(self) -> None:
        """Raises `SourceError` when the source cannot be opened."""

    def read(self) -> np.ndarray:
        """The next frame, BGR uint8 (H, W, 3); raises `SourceError`."""
        raise NotImplementedError

    def close(self) -> None:
        """Release the device (never raises)."""


def _fit(image: np.ndarray, width: int, height: int) -> np.ndarray:
    if image.ndim == 2:
        image = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    elif image.shape[2] == 4:
        image = cv2.cvtColor(image, cv2.COLOR_BGRA2BGR)
    if image.shape[1] != width or image.shape[0] != height:
        image = cv2.resize(image, (width, height), interpolation=cv2.INTER_AREA)
    return image


class CaptureSource(Source):
    """`cv2.VideoCapture` on a V4L2 device (`/dev/video0` or an index), a stream URL or a video
    file. A file is played at the camera's fps and starts again at its end (opened anew: a
    file that is gone by then makes the camera down until it is back)."""

    def __init__(self, config: CameraConfig) -> None:
        self.config = config
        self.kind = config.kind
        self.paced = self.kind in ("device", "stream")
        self._cap: Any = None

    def open(self) -> None:
        src = self.config.source
        if self.kind == "file" and not os.path.isfile(src):
            raise SourceError(f"no video file {src}")
        if self.kind == "device":
            if not src.isdigit() and not os.path.exists(src):
                raise SourceError(f"no device {src} (unplugged?)")
            cap = cv2.VideoCapture(int(src) if src.isdigit() else src, cv2.CAP_V4L2)
        elif self.kind == "stream":
            cap = cv2.VideoCapture(src, cv2.CAP_FFMPEG, [
                cv2.CAP_PROP_OPEN_TIMEOUT_MSEC, STREAM_TIMEOUT_MS,
                cv2.CAP_PROP_READ_TIMEOUT_MSEC, STREAM_TIMEOUT_MS])
        else:
            cap = cv2.VideoCapture(src)
        if not cap.isOpened():
            cap.release()
            what = {"device": "device", "stream": "stream", "file": "video file"}[self.kind]
            raise SourceError(f"cannot open {what} {src}")
        if self.kind == "device":
            cap.set(cv2.CAP_PROP_FRAME_WIDTH, self.config.width)
            cap.set(cv2.CAP_PROP_FRAME_HEIGHT, self.config.height)
            cap.set(cv2.CAP_PROP_FPS, self.config.fps)
            cap.set(cv2.CAP_PROP_BUFFERSIZE, 1)  # the latest frame, not a queue of old ones
        self._cap = cap

    def read(self) -> np.ndarray:
        if self._cap is None:
            raise SourceError("not open")
        ok, image = self._cap.read()
        if not ok and self.kind == "file":  # the end: play it again from a fresh open
            self.close()
            self.open()
            ok, image = self._cap.read()
        if not ok or image is None:
            what = {"device": "the device gives no frame (unplugged?)",
                    "stream": "the stream stopped", "file": "the video file has no frame"}
            raise SourceError(f"{self.config.source}: {what[self.kind]}")
        return _fit(image, self.config.width, self.config.height)

    def close(self) -> None:
        if self._cap is not None:
            self._cap.release()
            self._cap = None


class FolderSource(Source):
    """A folder of images played in name order, looping; listed anew at each loop, so files
    added or removed count from the next round. An empty or missing folder is a down camera."""

    def __init__(self, config: CameraConfig) -> None:
        self.config = config
        self.folder = Path(config.source)
        self._files: list[Path] = []
        self._next = 0

    def _list(self) -> list[Path]:
        try:
            files = sorted(p for p in self.folder.iterdir()
                           if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file())
        except OSError as exc:
            raise SourceError(f"folder {self.folder}: {exc.strerror or exc}") from None
        if not files:
            raise SourceError(f"folder {self.folder} has no images")
        return files

    def open(self) -> None:
        self._files = self._list()
        self._next = 0

    def read(self) -> np.ndarray:
        if self._next >= len(self._files):
            self._files, self._next = self._list(), 0
        path = self._files[self._next]
        self._next += 1
        image = cv2.imread(str(path), cv2.IMREAD_COLOR)
        if image is None:
            self._files = self._list()  # gone meanwhile? the next read finds out
            self._next = 0
            raise SourceError(f"cannot read image {path}")
        return _fit(image, self.config.width, self.config.height)


class RenderSource(Source):
    """Frames from a function (the simulated camera: `sim:<arm>`); `make` builds that function
    at open and raises `SourceError` when there is nothing to render."""

    def __init__(self, make: Callable[[], Callable[[], np.ndarray]]) -> None:
        self._make = make
        self._render: Callable[[], np.ndarray] | None = None

    def open(self) -> None:
        self._render = self._make()

    def read(self) -> np.ndarray:
        if self._render is None:
            raise SourceError("not open")
        try:
            image = self._render()
        except SourceError:
            raise
        except Exception as exc:  # noqa: BLE001 - the renderer's failure is the camera's state
            raise SourceError(f"render failed: {exc}") from exc
        return np.ascontiguousarray(image, dtype=np.uint8)
