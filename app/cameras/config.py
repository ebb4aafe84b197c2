"""The `[[cameras]]` tables of a server config file, and the default cameras (one simulated
camera per simulated arm).

Colours are HSV ranges on OpenCV's scale (H 0..179, S and V 0..255: see OpenCV's
"Changing Colorspaces" tutorial, `cv2.cvtColor(..., cv2.COLOR_BGR2HSV)`); a colour is one or
more `[low, high]` bands (red wraps around H = 0, so it has two).
"""

from __future__ import annotations

import re
import tomllib
from pathlib import Path
from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from app.config.profiles import ArmProfile, ConfigError, invalid_config

__all__ = ["DEFAULT_COLORS", "CameraConfig", "SourceKind", "Band", "default_cameras",
           "load_cameras", "parse_cameras", "source_kind"]

SourceKind = Literal["device", "stream", "file", "folder", "sim"]
#: One HSV band: ((h, s, v) low, (h, s, v) high), OpenCV scale.
Band = tuple[tuple[int, int, int], tuple[int, int, int]]

#: The default colours, tuned for saturated objects under room light. Red wraps around H = 0.
DEFAULT_COLORS: dict[str, list[Band]] = {
    "red": [((0, 120, 70), (8, 255, 255)), ((170, 120, 70), (179, 255, 255))],
    "yellow": [((20, 100, 100), (34, 255, 255))],
    "green": [((40, 80, 50), (85, 255, 255))],
    "blue": [((95, 120, 50), (130, 255, 255))],
}

_NAME = r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$"
_STREAM = re.compile(r"^(rtsp|rtsps|http|https|rtmp|udp|tcp)://", re.IGNORECASE)
_HSV_MAX = (179, 255, 255)


def source_kind(source: str) -> SourceKind:
    """Which kind of source `source` names: `sim:<arm>`, a URL (stream), a V4L2 device (a
    `/dev/` path or an index), a folder of images (an existing folder, or any path ending in
    `/`, so that a folder missing at start is still one), else a video file."""
    if source.startswith("sim:"):
        return "sim"
    if _STREAM.match(source):
        return "stream"
    if source.isdigit() or source.startswith("/dev/"):
        return "device"
    if Path(source).is_dir() or source.endswith(("/", "\\")):
        return "folder"
    return "file"


class CameraConfig(BaseModel):
    """One `[[cameras]]` table (API.md "Cameras (v1.2)"). Unknown keys are refused by name."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    name: Annotated[str, Field(pattern=_NAME)]
    source: Annotated[str, Field(min_length=1, max_length=1024)]
    arm: Annotated[str, Field(min_length=1, max_length=64)]
    width: Annotated[int, Field(ge=16, le=7680)] = 640
    height: Annotated[int, Field(ge=16, le=4320)] = 480
    fps: Annotated[float, Field(gt=0, le=240)] = 15.0
    #: Extra (or replaced) colours: name -> one band [[h, s, v], [h, s, v]] or a list of bands.
    colors: dict[str, list[Band]] = Field(default_factory=dict)
    #: JPEG quality of served frames, 1..100 (OpenCV IMWRITE_JPEG_QUALITY).
    jpeg_quality: Annotated[int, Field(ge=1, le=100)] = 80

    @field_validator("colors", mode="before")
    @classmethod
    def _bands(cls, value: object) -> object:
        if not isinstance(value, dict):
            return value
        out: dict[str, object] = {}
        for name, bands in value.items():
            if not re.match(r"^[a-z][a-z0-9_-]{0,31}$", str(name)):
                raise ValueError(f"colour name {name!r}: lower-case letters, digits, _ or -")
            # one band [[h,s,v],[h,s,v]] or several [[[h,s,v],[h,s,v]], ...]
            if (isinstance(bands, list) and len(bands) == 2
                    and all(isinstance(b, list) and b and not isinstance(b[0], list)
                            for b in bands)):
                bands = [bands]
            out[str(name)] = bands
        return out

    @field_validator("colors")
    @classmethod
    def _in_range(cls, value: dict[str, list[Band]]) -> dict[str, list[Band]]:
        for name, bands in value.items():
            if not bands:
                raise ValueError(f"colour {name!r} has no band")
            for low, high in bands:
                for k, (lo, hi, top) in enumerate(zip(low, high, _HSV_MAX, strict=True)):
                    if not 0 <= lo <= hi <= top:
                        raise ValueError(f"colour {name!r}: {'HSV'[k]} band {lo}..{hi} is not "
                                         f"within 0..{top} with low <= high")
        return value

    @property
    def kind(self) -> SourceKind:
        return source_kind(self.source)

    def palette(self) -> dict[str, list[Band]]:
        """The default colours with this camera's added (a configured name replaces one)."""
        return {**DEFAULT_COLORS, **self.colors}


def default_cameras(profiles: list[ArmProfile]) -> list[CameraConfig]:
    """One simulated camera per simulated arm, named after the arm (the server with no config
    file)."""
    return [CameraConfig(name=p.name, source=f"sim:{p.name}", arm=p.name, fps=10.0)
            for p in profiles if p.link.kind == "sim"]


def parse_cameras(tables: object, arms: list[str], where: str) -> list[CameraConfig]:
    """`[[cameras]]` tables as read from TOML, checked: known keys only, a known arm, a sim
    source naming a hosted arm, unique names. Raises `ConfigError` saying which and what."""
    if not isinstance(tables, list) or not all(isinstance(t, dict) for t in tables):
        raise ConfigError(f"{where}: `cameras` must be [[cameras]] tables")
    out: list[CameraConfig] = []
    for k, table in enumerate(tables):
        at = f"{where}, [[cameras]] #{k + 1}"
        try:
            cam = CameraConfig.model_validate(table)
        except ValidationError as exc:
            raise invalid_config(exc, at, "not a camera setting") from None
        if cam.arm not in arms:
            raise ConfigError(f"{at}: arm = {cam.arm!r} is not a hosted arm ({', '.join(arms)})")
        if cam.kind == "sim" and cam.source[4:] not in arms:
            raise ConfigError(f"{at}: source = {cam.source!r} names no hosted arm")
        out.append(cam)
    names = [c.name for c in out]
    if len(set(names)) != len(names):
        raise ConfigError(f"{where}: camera names must be unique, got {names}")
    return out


def load_cameras(config_file: str | Path | None, profiles: list[ArmProfile]) -> list[CameraConfig]:
    """The cameras a server hosts: the config file's `[[cameras]]` (none if it has none), or
    without a config file one simulated camera per simulated arm. The file was read and its
    top-level tables checked by `app.arms.loading.load_arms` already."""
    if config_file is None:
        return default_cameras(profiles)
    path = Path(config_file)
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        raise ConfigError(f"config file {path}: {exc}") from None
    if "cameras" not in data:
        return []
    return parse_cameras(data["cameras"], [p.name for p in profiles], f"config file {path}")
