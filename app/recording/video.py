"""An episode's camera frames as H.264 MP4 (PyAV), and the dataset's video files that hold
several episodes each.

The format (huggingface/lerobot `src/lerobot/datasets/video_utils.py`, `dataset_writer.py`
`_save_episode_video`): one MP4 per camera per (chunk, file), `yuv420p`, the episodes one
after the other; an episode's frames are at `from_timestamp + frame_index / fps` of its file,
`from_timestamp` the file's duration before it. lerobot joins an episode's MP4 to the file by
remuxing packets without decoding (`concatenate_video_files`); so does `append_episode`, with
each packet's time shifted by `from_timestamp` so that frame k of the episode is exactly at
`from_timestamp + k / fps`, and into a temporary file renamed over the old one.

An episode is encoded as it records (`EpisodeVideo`, fed from a worker thread) so that no
episode's frames are held in memory; frame k has pts k in a 1/fps time base. The GOP is one
second (`g` = fps) and there are no B-frames (`bf` 0): a reader seeks to a key frame and
decodes forward to the frame it wants (lerobot's `decode_video_frames_pyav`).
"""

from __future__ import annotations

import os
import shutil
from fractions import Fraction
from pathlib import Path
from typing import cast

import av
import numpy as np

from app.recording.layout import replace_synced

CODEC = "libx264"
PIX_FMT = "yuv420p"


class EpisodeVideo:
    """One camera's frames of one episode, encoded to `path` as they come."""

    def __init__(self, path: Path, width: int, height: int, fps: int) -> None:
        self.path = path
        self.fps = fps
        self.width, self.height = width, height
        path.parent.mkdir(parents=True, exist_ok=True)
        self._out = av.open(str(path), mode="w")
        stream = cast(av.video.stream.VideoStream, self._out.add_stream(CODEC, rate=fps))
        stream.width, stream.height = width, height
        stream.pix_fmt = PIX_FMT
        stream.time_base = Fraction(1, fps)
        stream.codec_context.options = {"preset": "ultrafast", "g": str(fps), "bf": "0"}
        self._stream = stream
        self.frames = 0
        self._closed = False

    def add(self, bgr: np.ndarray) -> None:
        """The next frame, (H, W, 3) uint8 BGR (OpenCV's order), at pts `frames`."""
        frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(bgr), format="bgr24")
        if frame.width != self.width or frame.height != self.height:
            frame = frame.reformat(width=self.width, height=self.height)
        frame.pts = self.frames
        frame.time_base = Fraction(1, self.fps)
        for packet in self._stream.encode(frame):
            self._out.mux(packet)
        self.frames += 1

    def close(self) -> None:
        """Flush the encoder and close the file (its bytes on disk: fsync)."""
        if self._closed:
            return
        self._closed = True
        try:
            for packet in self._stream.encode(None):
                self._out.mux(packet)
        finally:
            self._out.close()
        fd = os.open(self.path, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)

    def abort(self) -> None:
        """Close without caring for the file (the episode is discarded)."""
        if not self._closed:
            self._closed = True
            try:
                self._out.close()
            except (OSError, av.FFmpegError):
                pass
        self.path.unlink(missing_ok=True)


def append_episode(dest: Path, episode: Path, offset_s: float) -> None:
    """Join the episode's MP4 to the end of `dest` (which holds `offset_s` seconds of earlier
    episodes; `dest` absent: the episode becomes the file), without re-encoding."""
    dest.parent.mkdir(parents=True, exist_ok=True)
    tmp = dest.with_name(f".{dest.name}.tmp")
    if not dest.exists():
        shutil.copyfile(episode, tmp)
        replace_synced(tmp, dest)
        return
    with av.open(str(tmp), mode="w", format="mp4") as out:
        with av.open(str(dest)) as first:
            src = first.streams.video[0]
            stream = out.add_stream_from_template(src)
            stream.time_base = src.time_base
            _copy(first, out, stream, 0.0)
        with av.open(str(episode)) as second:
            _copy(second, out, stream, offset_s)
    replace_synced(tmp, dest)


def _copy(src: av.container.InputContainer, out: av.container.OutputContainer,
          stream: av.video.stream.VideoStream, offset_s: float) -> None:
    vin = src.streams.video[0]
    tb = vin.time_base
    assert tb is not None
    shift = round(Fraction(offset_s).limit_denominator(1_000_000) / tb)
    for packet in src.demux(vin):
        if packet.dts is None:
            continue
        if packet.pts is not None:
            packet.pts += shift
        packet.dts += shift
        packet.time_base = tb
        packet.stream = stream
        out.mux(packet)


def decode_at(path: Path, timestamps: list[float], fps: int) -> list[np.ndarray]:
    """The frames of `path` at `timestamps` (s in the file), RGB (H, W, 3) uint8: each the
    decoded frame nearest in time, within half a period (a reader's check)."""
    want = sorted(timestamps)
    frames: dict[float, np.ndarray] = {}
    with av.open(str(path)) as f:
        vs = f.streams.video[0]
        tb = vs.time_base
        assert tb is not None
        f.seek(max(0, int((want[0] - 1.0) * av.time_base)))
        i = 0
        for frame in f.decode(vs):
            if frame.pts is None:
                continue
            t = float(frame.pts * tb)
            while i < len(want) and t >= want[i] - 0.5 / fps:
                if abs(t - want[i]) <= 0.5 / fps:
                    frames[want[i]] = frame.to_ndarray(format="rgb24")
                i += 1
            if i >= len(want):
                break
    missing = [t for t in timestamps if t not in frames]
    if missing:
        raise ValueError(f"{path}: no frame at {missing[:5]} s")
    return [frames[t] for t in timestamps]
