"""Cameras, detections and the camera-to-table calibration (API.md "Cameras (v1.2)")."""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import Field

from app.schemas.arms import Vec3
from app.schemas.common import Finite, Model

SourceKind = Literal["device", "stream", "file", "folder", "sim"]


class CameraSummary(Model):
    name: str
    arm: str = Field(description="the arm whose base frame detections are given in")
    kind: SourceKind = Field(description="the source's kind: V4L2 `device`, network `stream`, "
                             "video `file`, image `folder`, or `sim` (a simulated arm's table)")
    width: int
    height: int
    fps: float
    up: bool = Field(description="frames are coming")
    calibrated: bool


class CameraDetail(CameraSummary):
    source: str
    last_error: str | None = Field(description="why the camera is down (null while up)")
    frame_seq: int = Field(description="frames taken since the server started")
    connects: int = Field(description="times the source was opened")
    colors: list[str] = Field(description="the colour names detections know")
    streaming_clients: int = Field(description="MJPEG clients watching now")


class CameraStatus(Model):
    """A camera in /health."""

    up: bool
    last_error: str | None = None


class Pixel(Model):
    u: Finite = Field(description="column, px (0 at the left pixel's centre)")
    v: Finite = Field(description="row, px (0 at the top pixel's centre)")


class Detection(Model):
    color: str
    pixel: Pixel = Field(description="the object's centroid")
    area: int = Field(description="px")
    bbox: tuple[int, int, int, int] = Field(description="[u0, v0, u1, v1]: first and one past "
                                            "the last column and row, px")
    position: Vec3 | None = Field(description="the centroid on the table in the arm's "
                                        "base frame, m; null while the camera is not "
                                        "calibrated")


class Detections(Model):
    camera: str
    frame_seq: int
    time: float = Field(description="when the frame was taken, s since the epoch")
    took_ms: float = Field(description="how long the detection took, ms")
    detections: list[Detection] = Field(description="largest first")


class Correspondence(Model):
    pixel: Pixel
    position: Vec3 = Field(description="the tip's position at that pixel, on the table, "
                                 "in the arm's base frame, m")


class CalibrationRequest(Model):
    points: Annotated[list[Correspondence], Field(min_length=1, max_length=200)] = Field(
        description="4 or more, spread over the table, no three on a line when only four")


class Calibration(Model):
    camera: str
    calibrated: bool
    homography: list[list[float]] | None = Field(
        None, description="3x3, row-major: table (x, y, 1) in m to image (u, v, 1) in px, up to "
        "scale (H[2][2] = 1)")
    z: float | None = Field(None, description="the table's height in the arm's base frame, m")
    rms_px: float | None = Field(None, description="reprojection error of the points: root "
                                 "mean square, px")
    max_px: float | None = Field(None, description="... and the largest, px")
    points: int | None = None
    time: float | None = Field(None, description="when it was fitted, s since the epoch")
