"""Every camera of the server (`app.state.cameras`): their threads, calibrations (in the store,
scope `camera:<name>`), detections in a bounded worker pool, and the MJPEG feeds.

Built and started by the lifespan (app/web/factory.py) on the HTTP loop; the routes
(app/web/routes/cameras.py) call it. Blocking work (JPEG encoding, detection) runs in its pool
of worker threads, never on the HTTP loop or the arms' control thread.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import AsyncIterator, Callable, Mapping
from concurrent.futures import ThreadPoolExecutor
from typing import Any, Protocol

import numpy as np

from app.cameras.calibration import Calibration, fit, to_table
from app.cameras.camera import Camera, Frame
from app.cameras.config import CameraConfig
from app.cameras.detect import Blob, detect
from app.cameras.mjpeg import MjpegFeed
from app.cameras.sources import CaptureSource, FolderSource, RenderSource, Source, SourceError
from app.errors import Busy, CameraDown, InvalidRequest, NotFound
from app.service import ArmService
from app.sim.camera import SimView, render
from app.store import CALIBRATION_KEY, CAMERA_SCOPE, StoreError

__all__ = ["CALIBRATION_KEY", "CameraHub", "Store", "scope"]

log = logging.getLogger(__name__)

#: Detections waiting or running at once, all cameras; more is 409 `busy` (bounded work).
MAX_DETECTIONS = 8
#: Worker threads for JPEG encoding and detection (the machine has few cores to share with the
#: arms).
WORKERS = 2
#: How long a request waits for a camera's first (or, on demand, a fresh) frame, s.
FIRST_FRAME_S = 3.0


class Store(Protocol):
    def get_setting_sync(self, scope: str, key: str) -> Any: ...
    async def put_setting(self, scope: str, key: str, value: Any) -> bool: ...


def scope(camera: str) -> str:
    return CAMERA_SCOPE.format(camera)


def sim_renderer(svc: ArmService, config: CameraConfig) -> Callable[[], Callable[[], np.ndarray]]:
    """The function that opens a `sim:<arm>` camera: the arm's simulated world seen from the
    default view of its table (app/sim/camera.py: `SimView.default_for`, `render`)."""
    def make() -> Callable[[], np.ndarray]:
        world = svc.world
        if world is None:
            raise SourceError(f"arm {svc.name}: no simulated world (its link is not simulated)")
        view = SimView.default_for(svc.profile, config.width, config.height)

        def frame() -> np.ndarray:
            return render(world, view, config.width, config.height)
        return frame
    return make


def make_source(config: CameraConfig, services: Mapping[str, ArmService]) -> Source:
    kind = config.kind
    if kind == "sim":
        return RenderSource(sim_renderer(services[config.source[4:]], config))
    if kind == "folder":
        return FolderSource(config)
    return CaptureSource(config)


class CameraHub:
    """The server's cameras by name."""

    def __init__(self, configs: list[CameraConfig], services: Mapping[str, ArmService],
                 store: Store | None = None) -> None:
        self.configs = {c.name: c for c in configs}
        self.cameras = {c.name: Camera(c, make_source(c, services), on_demand=c.kind == "sim")
                        for c in configs}
        self.calibrations: dict[str, Calibration] = {}
        self._store = store
        self._pool = ThreadPoolExecutor(WORKERS, thread_name_prefix="camera-work")
        self._feeds: dict[str, MjpegFeed] = {}
        self._running = 0

    # ------------------------------------------------------------ life

    def start(self, loop: asyncio.AbstractEventLoop) -> None:
        """Load the stored calibrations (blocking: at start-up) and start every camera."""
        for name in self.cameras:
            if self._store is not None:
                self._load(name)
            self._feeds[name] = MjpegFeed(self.cameras[name], self._pool, loop)
        for cam in self.cameras.values():
            cam.start()

    def _load(self, name: str) -> None:
        assert self._store is not None
        try:
            data = self._store.get_setting_sync(scope(name), CALIBRATION_KEY)
            if data is not None:
                self.calibrations[name] = Calibration.from_dict(data)
        except Exception:  # noqa: BLE001 - a bad stored value: uncalibrated, said once
            log.exception("camera %s: stored calibration unreadable; uncalibrated", name)

    def end_streams(self) -> None:
        """End every MJPEG response (the server is shutting down). On the event loop."""
        for feed in self._feeds.values():
            feed.end_streams()

    async def close(self) -> None:
        for feed in self._feeds.values():
            await feed.close()
        for cam in self.cameras.values():
            cam.stop(timeout=0.0)
        await asyncio.get_running_loop().run_in_executor(None, self._join)
        self._pool.shutdown(wait=False, cancel_futures=True)

    def _join(self) -> None:
        for cam in self.cameras.values():
            cam.stop()

    # ------------------------------------------------------------ reads

    def get(self, name: str) -> Camera:
        cam = self.cameras.get(name)
        if cam is None:
            known = ", ".join(sorted(self.cameras)) or "none"
            raise NotFound(f"no camera {name!r}; this server has {known}")
        return cam

    def up(self, name: str) -> Camera:
        """The camera, or 503 `camera_down` with its last error."""
        cam = self.get(name)
        if not cam.up:
            raise CameraDown(f"camera {name} is down: {cam.last_error}")
        return cam

    async def frame(self, name: str) -> Frame:
        """The latest frame (fresh, for an on-demand camera: one taken after this asks), or
        503 `camera_down`."""
        cam = self.get(name)
        cam.demand()
        last = cam.latest
        stale = last is None or (cam.on_demand and
                                 time.monotonic() - last.mono > 2.0 / cam.config.fps)
        if stale and (cam.up or cam.last_error == "not started"):
            await self._next_frame(cam, last)
        frame = cam.latest
        if frame is None or not cam.up:
            raise CameraDown(f"camera {name} is down: {cam.last_error or 'no frame yet'}")
        return frame

    async def _next_frame(self, cam: Camera, last: Frame | None) -> None:
        """Until a frame newer than `last`, at most FIRST_FRAME_S."""
        loop = asyncio.get_running_loop()
        arrived = asyncio.Event()

        def wake(_: Frame) -> None:
            loop.call_soon_threadsafe(arrived.set)
        remove = cam.add_listener(wake)
        try:
            if cam.latest is last:
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(arrived.wait(), FIRST_FRAME_S)
        finally:
            remove()

    async def jpeg(self, name: str) -> tuple[int, bytes]:
        """The latest frame's JPEG, encoded once (in a worker thread) for every client."""
        await self.frame(name)
        got = await asyncio.get_running_loop().run_in_executor(self._pool, self.get(name).jpeg)
        if got is None:
            raise CameraDown(f"camera {name}: no frame yet")
        return got

    async def stream(self, name: str) -> AsyncIterator[bytes]:
        """A client's MJPEG parts (503 `camera_down` first if the camera gives no frame)."""
        await self.frame(name)
        return self._feeds[name].frames()

    def feed(self, name: str) -> MjpegFeed:
        return self._feeds[name]

    # ------------------------------------------------------------ detection

    async def detect(self, name: str, colors: list[str] | None, min_area: int
                     ) -> tuple[Frame, list[Blob], np.ndarray | None, float]:
        """Objects in the latest frame; with their table positions (x, y) when calibrated.
        Runs in the worker pool; 409 `busy` when MAX_DETECTIONS are waiting already."""
        config = self.configs.get(name)
        self.get(name)
        assert config is not None
        palette = config.palette()
        if colors is None:
            colors = list(palette)
        unknown = [c for c in colors if c not in palette]
        if unknown:
            raise InvalidRequest(f"unknown colour {', '.join(unknown)}; camera {name} knows "
                                 f"{', '.join(palette)}")
        frame = await self.frame(name)
        if self._running >= MAX_DETECTIONS:
            raise Busy(f"{MAX_DETECTIONS} detections are running: try again")
        self._running += 1
        try:
            t0 = time.perf_counter()
            blobs = await asyncio.get_running_loop().run_in_executor(
                self._pool, detect, frame.image, palette, colors, min_area)
            took = time.perf_counter() - t0
        finally:
            self._running -= 1
        cal = self.calibrations.get(name)
        xy = None
        if cal is not None and blobs:
            xy = to_table(cal, np.array([[b.u, b.v] for b in blobs]))
        return frame, blobs, xy, took

    # ------------------------------------------------------------ calibration

    async def calibrate(self, name: str, uv: np.ndarray, xyz: np.ndarray) -> Calibration:
        """Fit, keep and store a camera's calibration; 422 `invalid_request` with the reason
        when the points are degenerate (nothing changes then)."""
        self.get(name)
        cal = fit(uv, xyz)
        self.calibrations[name] = cal
        if self._store is not None:
            try:  # a store that cannot take it now keeps it and retries (app/store.py)
                await self._store.put_setting(scope(name), CALIBRATION_KEY, cal.as_dict())
            except StoreError as exc:
                log.warning("camera %s: calibration not stored (in use until a restart): %s",
                            name, exc)
        log.info("camera %s: calibrated from %d points, rms %.2f px", name, cal.points,
                 cal.rms_px)
        return cal

    def status(self) -> dict[str, tuple[bool, str | None]]:
        """name -> (up, last error), for /health."""
        return {n: (c.up, c.last_error) for n, c in self.cameras.items()}
