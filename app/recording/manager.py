"""The server's datasets (`app.state.recordings`): one folder each under
`<data_dir>/recordings/`, created, listed, and one episode at a time recorded into each.

A dataset's own settings (its arms, cameras, rate and default task) are kept beside the format's
files in `armserver.json`, so a restarted server finds its datasets and appends to them. The
folder is private (0700, as app/store.py makes the data folder). Episodes are written when they
end, in a worker thread, one write at a time per dataset (app/recording/dataset.py); an episode
that ends on its own (a camera lost, too long) is written all the same, up to that point, and
its reason kept as the dataset's `last_error`. A write that fails (disk full: OSError ENOSPC)
loses that episode only: 503 `recording_failed`, the dataset keeps every earlier one.
"""

from __future__ import annotations

import asyncio
import json
import logging
import os
import re
import time
from collections.abc import Callable, Iterator, Mapping
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import av

from app.errors import Busy, Conflict, InvalidRequest, NotFound, RecordingFailed, UnknownArm
from app.recording.dataset import ArmLayout, Dataset, EpisodeInfo
from app.recording.encoder import RecordingError
from app.recording.inputs import CameraFeed
from app.recording.layout import PARTIAL_DIR, write_json
from app.recording.session import EpisodeRecorder
from app.service import ArmService

log = logging.getLogger(__name__)

CONFIG = "armserver.json"
NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")


@dataclass
class RecordingConfig:
    name: str
    arms: list[str]
    cameras: list[str]
    fps: int
    task: str
    created: float = field(default_factory=time.time)


@dataclass
class Recording:
    """One dataset and the episode it records, if any."""
    config: RecordingConfig
    dataset: Dataset
    recorder: EpisodeRecorder | None = None
    last_error: str | None = None
    writing: bool = False
    lock: asyncio.Lock = field(default_factory=asyncio.Lock)
    #: Episodes and frames written, as of the last finished write (the dataset's own lists
    #: grow during a write, in a worker thread).
    episodes: int = 0
    frames: int = 0

    def written(self) -> None:
        self.episodes, self.frames = len(self.dataset.rows), self.dataset.total_frames

    @property
    def id(self) -> str:
        return self.config.name

    @property
    def path(self) -> Path:
        return self.dataset.root


def layout_of(svc: ArmService) -> ArmLayout:
    p = svc.profile
    return ArmLayout(svc.name, tuple(j.name for j in p.joints), p.gripper.actuated)


class Recordings:
    """Every dataset of the server, by id (its name)."""

    def __init__(self, folder: Path, services: Mapping[str, ArmService],
                 cameras: Callable[[str], CameraFeed | None]) -> None:
        self.folder = folder
        self.services = services
        self.cameras = cameras
        self._all: dict[str, Recording] = {}
        self._ends: set[asyncio.Task[None]] = set()

    def load(self) -> None:
        """The datasets already in the folder (blocking: at start-up or in a thread)."""
        self.folder.mkdir(mode=0o700, parents=True, exist_ok=True)
        for sub in sorted(self.folder.iterdir()):
            cfg = sub / CONFIG
            if not cfg.is_file() or sub.name in self._all:
                continue
            try:
                config = RecordingConfig(**json.loads(cfg.read_text()))
                rec = Recording(config, Dataset.open(sub))
                rec.written()
                self._all[sub.name] = rec
            except (OSError, ValueError, TypeError, KeyError, av.FFmpegError) as exc:
                log.warning("recordings: %s cannot be opened: %s", sub, exc)

    def __iter__(self) -> Iterator[Recording]:
        return iter(list(self._all.values()))

    def get(self, rid: str) -> Recording:
        rec = self._all.get(rid)
        if rec is None:
            raise NotFound(f"no recording {rid!r}")
        return rec

    # ------------------------------------------------------------ create

    def _arms(self, names: list[str]) -> list[ArmService]:
        out = []
        for n in names:
            svc = self.services.get(n)
            if svc is None:
                raise UnknownArm(f"no arm {n!r}; this server hosts "
                                 f"{', '.join(sorted(self.services))}")
            out.append(svc)
        if len(set(names)) != len(names):
            raise InvalidRequest("an arm is named twice")
        return out

    def _feeds(self, names: list[str]) -> list[CameraFeed]:
        out = []
        for n in names:
            feed = self.cameras(n)
            if feed is None:
                raise NotFound(f"no camera {n!r}")
            out.append(feed)
        if len(set(names)) != len(names):
            raise InvalidRequest("a camera is named twice")
        return out

    async def create(self, name: str, arms: list[str], cameras: list[str], fps: int,
                     task: str) -> Recording:
        if not NAME.match(name):
            raise InvalidRequest(f"a recording's name is letters, digits, '_', '-', '.': {name!r}")
        services = self._arms(arms)
        feeds = self._feeds(cameras)
        if name in self._all or (self.folder / name).exists():
            raise Conflict(f"a recording named {name!r} exists")
        layouts = [layout_of(s) for s in services]
        robot_type = "+".join(dict.fromkeys(s.profile.model for s in services))
        config = RecordingConfig(name, arms, cameras, fps, task)
        root = self.folder / name

        def make() -> Dataset:
            self.folder.mkdir(mode=0o700, parents=True, exist_ok=True)
            ds = Dataset.create(root, fps, layouts,
                                {f.name: (f.width, f.height) for f in feeds}, robot_type,
                                velocity=True)
            write_json(root / CONFIG, asdict(config))
            return ds
        try:
            ds = await asyncio.to_thread(make)
        except FileExistsError as exc:
            raise Conflict(f"a recording named {name!r} exists") from exc
        except OSError as exc:
            raise RecordingFailed(f"cannot create {root}: {exc}") from exc
        rec = Recording(config, ds)
        self._all[name] = rec
        return rec

    # ------------------------------------------------------------ episodes

    def start(self, rid: str, task: str | None) -> Recording:
        rec = self.get(rid)
        if rec.recorder is not None or rec.writing:
            raise Busy(f"recording {rid!r}: an episode is "
                       + ("being written" if rec.writing else "recording") + ": stop it first")
        services = self._arms(rec.config.arms)
        feeds = self._feeds(rec.config.cameras)
        arms = [(svc, layout_of(svc)) for svc in services]
        if [n for _, a in arms for n in a.names] != rec.dataset.names:
            raise Conflict(f"recording {rid!r}: its arms' joints are not those it was made with")

        def ended(why: str) -> None:
            task_ = asyncio.get_running_loop().create_task(self._ended(rec, why))
            self._ends.add(task_)
            task_.add_done_callback(self._ends.discard)
        recorder = EpisodeRecorder(arms, feeds, rec.dataset.fps, task or rec.config.task,
                                   rec.dataset.root / PARTIAL_DIR, ended)
        try:
            recorder.start()
        except (OSError, av.FFmpegError) as exc:
            raise RecordingFailed(f"recording {rid!r}: the episode cannot start: {exc}") \
                from exc
        rec.recorder = recorder
        rec.last_error = None
        return rec

    async def _ended(self, rec: Recording, why: str) -> None:
        """An episode that ended on its own: written up to there, `why` kept (a failed write
        keeps its own reason instead)."""
        rec.last_error = why
        try:
            await self.stop(rec.id)
        except Exception as exc:  # noqa: BLE001 - kept as the dataset's error
            log.warning("recording %s: the ended episode was not written: %s", rec.id, exc)

    async def stop(self, rid: str) -> EpisodeInfo:
        """End the current episode and write it."""
        rec = self.get(rid)
        recorder = rec.recorder
        if recorder is None:
            raise Conflict(f"recording {rid!r}: no episode is recording")
        rec.recorder, rec.writing = None, True  # a second stop now finds none
        # shielded: a caller that goes away does not leave the episode half handled
        return await asyncio.shield(self._write(rec, recorder))

    async def _write(self, rec: Recording, recorder: EpisodeRecorder) -> EpisodeInfo:
        async with rec.lock:
            try:
                try:
                    frames = await recorder.finish()
                except RecordingError as exc:
                    rec.last_error = str(exc)
                    raise Conflict(f"recording {rec.id!r}: the episode cannot be kept: "
                                   f"{exc}") from exc
                try:
                    return await asyncio.to_thread(rec.dataset.append, frames)
                except OSError as exc:
                    rec.last_error = f"the episode was not written: {exc}"
                    raise RecordingFailed(f"recording {rec.id!r}: the episode was not written "
                                          f"({exc}); the dataset keeps its "
                                          f"{len(rec.dataset.rows)} earlier episodes") from exc
                finally:
                    rec.written()
                    for p in frames.videos.values():
                        _unlink(p)
            finally:
                rec.writing = False

    async def discard(self, rid: str) -> None:
        rec = self.get(rid)
        recorder = rec.recorder
        if recorder is None:
            raise Conflict(f"recording {rid!r}: no episode is recording")
        rec.recorder = None
        await recorder.discard()

    async def close(self) -> None:
        """At shutdown: every episode that records is ended and written."""
        for rec in self:
            if rec.recorder is not None:
                try:
                    await self.stop(rec.id)
                except Exception as exc:  # noqa: BLE001 - the other datasets all the same
                    log.warning("recording %s: not written at shutdown: %s", rec.id, exc)
        for t in list(self._ends):
            await t

    def describe(self, rec: Recording, detail: bool = False) -> dict[str, Any]:
        ds = rec.dataset
        out: dict[str, Any] = {
            "id": rec.id, "name": rec.config.name, "arms": rec.config.arms,
            "cameras": rec.config.cameras, "fps": ds.fps, "task": rec.config.task,
            "episodes": rec.episodes, "frames": rec.frames, "path": str(ds.root),
            "recording": rec.recorder is not None, "last_error": rec.last_error,
        }
        if detail:
            out["current"] = None if rec.recorder is None else rec.recorder.describe()
            out["names"] = ds.names
            out["episode_list"] = [asdict(e) for e in ds.episodes()[:rec.episodes]]
        return out


def _unlink(p: Path) -> None:
    try:
        os.unlink(p)
    except FileNotFoundError:
        pass
