"""Recordings (API.md "Recordings (v1.2)"): LeRobot v3.0 datasets under the data folder and
the episode being recorded into one."""

from __future__ import annotations

from typing import Annotated

from pydantic import Field

from app.schemas.common import Int, Model

RecordingName = Annotated[str, Field(pattern=r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$",
                                     description="the dataset's name and id: letters, digits, "
                                     "`_`, `-`, `.`; its folder under the data folder")]
TaskText = Annotated[str, Field(min_length=1, max_length=1000,
                                description="what the demonstration shows (LeRobot's task)")]
ShortName = Annotated[str, Field(min_length=1, max_length=64)]


class RecordingCreate(Model):
    name: RecordingName
    arms: list[ShortName] = Field(min_length=1, max_length=8,
                                  description="arms whose state and action are recorded, "
                                  "concatenated in this order")
    cameras: list[ShortName] = Field(default_factory=list, max_length=8,
                                     description="cameras recorded as `observation.images.<name>`")
    fps: Annotated[int, Field(ge=1, le=120, strict=True)] = 30
    task: TaskText = "demonstration"


class EpisodeStart(Model):
    task: TaskText | None = Field(None, description="this episode's task (default: the "
                                  "dataset's)")


class CurrentEpisode(Model):
    frames: Int = Field(description="frames recorded so far")
    length_s: float = Field(description="the episode's length so far, s")
    started: float = Field(description="Unix time of its first frame")
    task: str


class EpisodeSummary(Model):
    index: Int
    length: Int = Field(description="frames")
    tasks: list[str]
    from_index: Int = Field(description="its first frame's `index` in the dataset")
    to_index: Int = Field(description="one past its last frame's `index`")


class RecordingSummary(Model):
    id: str
    name: str
    arms: list[str]
    cameras: list[str]
    fps: Int
    task: str
    episodes: Int = Field(description="episodes written")
    frames: Int = Field(description="frames written, all episodes")
    path: str = Field(description="the dataset's folder on the server")
    recording: bool = Field(description="an episode is recording now")
    last_error: str | None = Field(description="why the last episode ended on its own or was "
                                   "not written (a camera lost, disk full), null when all went "
                                   "well")


class RecordingDetail(RecordingSummary):
    current: CurrentEpisode | None = Field(description="the episode recording now")
    names: list[str] = Field(description="what each column of `observation.state` and "
                             "`action` is: `<arm>.<joint>.pos`, `<arm>.gripper.pos`")
    episode_list: list[EpisodeSummary]
