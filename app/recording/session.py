"""One episode being recorded: the time grid, the telemetry resampled onto it, the commanded
setpoints, the cameras' frames encoded as they come; `finish` hands over what `Dataset.append`
writes.

Frame k is at wall-clock `t0 + k / fps` (`timestamp = k / fps` exactly). A task on the HTTP
loop wakes at each grid time and:

- takes the arms' telemetry samples since the last wake (`ArmService.subscribe`: a cursor in
  the hub's shared log, bounded backlog; the control thread is never waited for or slowed)
  and resamples their joint positions (then the gripper, where the arm has one) and their
  joints' velocities linearly at every grid time the samples already pass
  (app/recording/grid.py);
- notes the action of frame k: where each joint was last told to go (`ArmService.setpoint`,
  the arm's one commanded record; during teleoperation the follower's setpoint is the
  leader's mapped joints), then the gripper's last command (`ArmService.gripper_setpoint`;
  as measured before any);
- takes each camera's new frames (every frame, through the camera's listener) and, one period
  later, gives frame k the one nearest its grid time (app/recording/inputs.py); the image goes
  to a worker thread that encodes it (app/recording/encoder.py) through a bounded queue.

What is held per episode is bounded: the samples not yet resampled (a period's worth), one
state and action per frame, a few sampled images per camera for the stats, and at most
`MAX_EPISODE_S` of recording (the episode then ends and is written). A camera that gives no
new frame for `CAMERA_LOST_S` ends the episode with an error, as does an encoder that falls
`QUEUE_FRAMES` behind (app/recording/encoder.py).
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import av
import numpy as np

from app.recording.dataset import ArmLayout, EpisodeFrames
from app.recording.encoder import Encoder, RecordingError
from app.recording.inputs import ArmTrack, CameraFeed, CameraTrack
from app.recording.video import EpisodeVideo
from app.runtime.tasks import cancel_and_wait
from app.service import ArmService

log = logging.getLogger(__name__)

#: Longest episode, s: its states and actions stay in memory until it is written.
MAX_EPISODE_S = 1800.0
#: A camera whose newest frame is older than this is lost, s.
CAMERA_LOST_S = 2.0
#: Images kept per camera for its stats (lerobot samples about this many).
STAT_IMAGES = 50


class EpisodeRecorder:
    """Records one episode from `start()` until `stop()` (or until it ends itself: `ended`)."""

    def __init__(self, arms: list[tuple[ArmService, ArmLayout]], cameras: list[CameraFeed],
                 fps: int, task: str, partial: Path, on_end: Callable[[str], None]) -> None:
        self.fps, self.task = fps, task
        self.cameras = cameras
        self._arm_specs = arms
        self._partial = partial
        self._on_end = on_end
        self.tracks: list[ArmTrack] = []
        self.t0 = 0.0
        self.states: list[np.ndarray] = []  # (d,) per frame, resampled
        self.velocities: list[np.ndarray] = []  # (joints,) per frame, resampled
        self.actions: list[list[float]] = []
        self.ticks = 0  # frames whose action is noted
        self._cams: list[CameraTrack] = []
        self._imaged = 0  # frames whose images went to the encoder
        self._samples: dict[str, list[np.ndarray]] = {c.name: [] for c in cameras}
        self._encoder: Encoder | None = None
        self._task: asyncio.Task[None] | None = None
        #: Why the episode ended on its own (None: it records, or was stopped).
        self.error: str | None = None
        self.ended = False

    # ------------------------------------------------------------ lifecycle

    def start(self) -> None:
        """Open the episode's video files (OSError: nothing is left open), then record."""
        self._partial.mkdir(parents=True, exist_ok=True)
        stamp = f"{time.time_ns()}"
        videos: dict[str, EpisodeVideo] = {}
        try:
            for c in self.cameras:
                videos[c.name] = EpisodeVideo(self._partial / f"{stamp}-{c.name}.mp4", c.width,
                                              c.height, self.fps)
        except (OSError, av.FFmpegError):
            for v in videos.values():
                v.abort()
            raise
        self.tracks = [ArmTrack(svc, lay) for svc, lay in self._arm_specs]
        self._encoder = Encoder(videos)
        self.t0 = time.time()
        self._cams = [CameraTrack(c, self.t0, self.fps) for c in self.cameras]
        self._task = asyncio.get_running_loop().create_task(self._run(), name="recording")

    @property
    def length_s(self) -> float:
        return self.ticks / self.fps

    async def _run(self) -> None:
        try:
            while True:
                due = self.t0 + self.ticks / self.fps
                delay = due - time.time()
                if delay > 0:
                    await asyncio.sleep(delay)
                self._tick()
        except RecordingError as exc:
            self.error = str(exc)
            self.ended = True
            log.warning("recording: episode ended: %s", exc)
            self._on_end(str(exc))

    def _tick(self) -> None:
        if self.ticks / self.fps >= MAX_EPISODE_S:
            raise RecordingError(f"the episode reached {MAX_EPISODE_S:.0f} s")
        now = time.time()
        self.actions.append([x for t in self.tracks for x in t.action()])
        self.ticks += 1
        for t in self.tracks:
            t.take()
        self._resample(final=False)
        for cam in self._cams:
            cam.poll(self._imaged)
            last = cam.last_time
            if self.ticks * 1.0 / self.fps > CAMERA_LOST_S and (
                    last is None or now - last > CAMERA_LOST_S):
                raise RecordingError(f"camera {cam.feed.name} lost: no new frame for "
                                     f"{CAMERA_LOST_S:.0f} s")
        # frame k's image one period after its grid time, when a later frame may be nearer
        while self.cameras and self._imaged < self.ticks - 1 and self._image(self._imaged):
            pass

    def _image(self, k: int) -> bool:
        """Frame k's images to the encoder, each camera's seen frame nearest its grid time;
        False while a camera has given none yet (its first frame then stands in for the
        frames before it)."""
        if not all(c.recent for c in self._cams):
            if k / self.fps > CAMERA_LOST_S:
                missing = [c.feed.name for c in self._cams if not c.recent]
                raise RecordingError(f"camera {', '.join(missing)} gave no frame")
            return False
        assert self._encoder is not None
        for cam in self._cams:
            f = cam.frame_for(k)
            name = cam.feed.name
            self._encoder.put(name, f.image)
            if k % self.fps == 0 and len(self._samples[name]) < STAT_IMAGES:
                self._samples[name].append(_small(f.image))
        self._imaged = k + 1
        return True

    def _resample(self, final: bool) -> None:
        done = len(self.states)
        if done >= self.ticks:
            return
        at = self.t0 + np.arange(done, self.ticks) / self.fps
        if not final:
            upto = min(t.last_time for t in self.tracks)
            at = at[at <= upto]
        if len(at) == 0:
            return
        if any(not t.times for t in self.tracks):
            raise RecordingError("no telemetry from "
                                 + ", ".join(t.svc.name for t in self.tracks if not t.times))
        parts = [t.states_at(at) for t in self.tracks]
        self.states.extend(np.concatenate([p[0] for p in parts], axis=1))
        self.velocities.extend(np.concatenate([p[1] for p in parts], axis=1))

    async def _halt(self, settle: bool = False) -> None:
        """No more ticks; `settle`: then, wait until half a period after the last grid time,
        so that the last frame may get a camera frame taken after it, as every other does."""
        task, self._task = self._task, None
        if task is not None and not task.done():
            await cancel_and_wait(task)
        if settle and self.cameras and self.ticks:
            delay = self.t0 + (self.ticks - 0.5) / self.fps - time.time()
            if delay > 0:
                await asyncio.sleep(delay)
        for t in self.tracks:
            t.close()
        for c in self._cams:
            c.close()

    async def finish(self) -> EpisodeFrames:
        """Stop and hand over the episode (its videos closed: blocking work in a thread)."""
        await self._halt(settle=True)
        encoder = self._encoder
        assert encoder is not None
        try:
            self._complete()
        except BaseException:
            await asyncio.to_thread(encoder.abort)
            raise
        await asyncio.to_thread(encoder.finish)
        videos = {c: v.path for c, v in encoder.videos.items()}
        frames = {c: v.frames for c, v in encoder.videos.items()}
        n = self.ticks
        if any(f != n for f in frames.values()):
            await asyncio.to_thread(encoder.abort)
            raise RecordingError(f"video frames {frames} for {n} frames")
        samples = {c: np.stack(s) for c, s in self._samples.items()}
        return EpisodeFrames(np.asarray(self.states[:n]), np.asarray(self.actions[:n]),
                             self.task, videos, samples, np.asarray(self.velocities[:n]))

    def _complete(self) -> None:
        """The last samples resampled, the last frames' images (nearest of what was seen)."""
        for t in self.tracks:
            t.take()
        for c in self._cams:
            c.poll(self._imaged)
        if self.ticks == 0:
            raise RecordingError("the episode has no frame")
        self._resample(final=True)
        while self.cameras and self._imaged < self.ticks:
            if not self._image(self._imaged):
                raise RecordingError("no camera frame in the episode")

    async def discard(self) -> None:
        await self._halt()
        if self._encoder is not None:
            await asyncio.to_thread(self._encoder.abort)

    def describe(self) -> dict[str, Any]:
        return {"frames": self.ticks, "length_s": round(self.length_s, 3),
                "started": self.t0, "task": self.task}


def _small(image: np.ndarray) -> np.ndarray:
    """An image for the stats: RGB, at most about 150 px a side (lerobot's
    `auto_downsample_height_width`)."""
    h, w = image.shape[:2]
    step = max(1, max(h, w) // 150)
    return np.ascontiguousarray(image[::step, ::step, ::-1])
