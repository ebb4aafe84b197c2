"""Each camera's image of frame k is the frame nearest the grid time `t0 + k / fps` of all the
camera gave: a camera made here (a thread producing numbered frames at 50 Hz, each told to the
recording as it comes) behind the simulated arms, the recording's video decoded back."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from app.recording.inputs import CameraFeed, CameraFrame, CameraTrack
from app.recording.manager import Recordings
from tests._lerobot import check_dataset, decode
from tests._wait import wait_for
from tests.conftest import running_client

W, H, CAM_HZ, FPS = 64, 48, 50.0, 10


def colour(k: int) -> tuple[int, int]:
    return (k * 15) % 210 + 20, (k // 14 * 15) % 210 + 20


class Numbered:
    """A camera of numbered frames: seq k is blue/green `colour(k)`."""

    def __init__(self) -> None:
        self.frames: list[CameraFrame] = []
        self.listeners: list[Callable[[CameraFrame], None]] = []
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self.run, daemon=True)

    def run(self) -> None:
        k = 0
        while not self.stop.wait(1 / CAM_HZ):
            img = np.zeros((H, W, 3), np.uint8)
            img[..., 0], img[..., 1] = colour(k)
            f = CameraFrame(k, time.time(), img)
            self.frames.append(f)
            for fn in list(self.listeners):
                fn(f)
            k += 1

    def feed(self) -> CameraFeed:
        def listen(fn: Callable[[CameraFrame], None]) -> Callable[[], None]:
            self.listeners.append(fn)
            return lambda: self.listeners.remove(fn)
        return CameraFeed("num", W, H, lambda: self.frames[-1] if self.frames else None, listen)


async def test_each_image_is_the_frame_nearest_its_grid_time(tmp_path: Path) -> None:
    cam = Numbered()
    cam.thread.start()
    try:
        async with running_client() as (app, _):
            recs = Recordings(tmp_path, app.state.services, lambda n: cam.feed())
            arm = next(iter(app.state.services))
            rec = await recs.create("n", [arm], ["num"], FPS, "t")
            recs.start("n", None)
            assert rec.recorder is not None
            t0 = rec.recorder.t0
            await wait_for(lambda: rec.recorder is not None and rec.recorder.ticks >= 20,
                           what="20 frames")
            await recs.stop("n")
    finally:
        cam.stop.set()
        cam.thread.join(5)
    read = check_dataset(rec.path)
    n = read.info["total_frames"]
    images = decode(rec.path / "videos/observation.images.num/chunk-000/file-000.mp4",
                    [k / FPS for k in range(n)], FPS)
    times = np.array([f.time for f in cam.frames])
    for k, img in enumerate(images):
        got = (int(round(img[..., 2].mean())), int(round(img[..., 1].mean())))
        want = int(np.argmin(np.abs(times - (t0 + k / FPS))))
        assert np.allclose(got, colour(want), atol=5), (k, got, colour(want))


def test_frame_zero_can_be_the_frame_the_camera_gave_just_before_the_episode() -> None:
    """The latest frame as a track starts (taken before t0) is a candidate for frame 0: with
    the first tick late, after a frame 15 ms past t0 came, the one 5 ms before t0 is nearer
    and is the image (it was the later one before: the listener never hears the earlier)."""
    img = np.zeros((H, W, 3), np.uint8)
    before, after = CameraFrame(10, 99.995, img), CameraFrame(11, 100.015, img)
    frames = [before]
    heard: list[Callable[[CameraFrame], None]] = []

    def listen(fn: Callable[[CameraFrame], None]) -> Callable[[], None]:
        heard.append(fn)
        return lambda: heard.remove(fn)

    track = CameraTrack(CameraFeed("num", W, H, lambda: frames[-1], listen), 100.0, FPS)
    frames.append(after)  # the camera's next frame, told to the track as it comes
    for fn in heard:
        fn(after)
    track.poll(0)  # the first tick, late: the latest frame is the later one now
    assert track.frame_for(0).seq == 10
    track.close()
    assert heard == []
