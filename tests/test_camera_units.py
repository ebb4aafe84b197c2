"""The camera room's pure parts (issue 25): source kinds, colour bands (red across H = 0),
the client's MJPEG part reader fed whole, byte by byte and many parts at once, and the
homography fit's own figures."""

from __future__ import annotations

from collections.abc import AsyncIterator

import cv2
import numpy as np
import pytest
from _camera_scene import camera_homography, project

from app.cameras.calibration import fit, to_table
from app.cameras.config import DEFAULT_COLORS, source_kind
from app.cameras.detect import detect
from app.cameras.mjpeg import part
from app.client.mjpeg import mjpeg_parts
from app.errors import InvalidRequest


@pytest.mark.parametrize(("source", "kind"), [
    ("/dev/video0", "device"), ("2", "device"), ("rtsp://cam.local/stream", "stream"),
    ("http://10.0.0.5:8080/video.mjpg", "stream"), ("sim:rbe3001", "sim"),
    ("lab.mp4", "file"), ("shots/", "folder")])
def test_source_kinds(source: str, kind: str) -> None:
    assert source_kind(source) == kind


def test_red_is_found_on_both_sides_of_hue_zero() -> None:
    img = np.full((120, 200, 3), 150, np.uint8)
    hsv = np.zeros((1, 2, 3), np.uint8)
    hsv[0, 0] = (2, 220, 200)     # red just above H = 0
    hsv[0, 1] = (176, 220, 200)   # red just below H = 180
    bgr = cv2.cvtColor(hsv, cv2.COLOR_HSV2BGR)[0]
    cv2.circle(img, (50, 60), 15, tuple(int(c) for c in bgr[0]), -1)
    cv2.circle(img, (150, 60), 20, tuple(int(c) for c in bgr[1]), -1)
    blobs = detect(img, DEFAULT_COLORS, ["red"], 50)
    assert [round(b.u) for b in blobs] == [150, 50]  # the larger first
    assert detect(img, DEFAULT_COLORS, ["green", "blue", "yellow"], 50) == []


async def _chunks(data: bytes, size: int) -> AsyncIterator[bytes]:
    for k in range(0, len(data), size):
        yield data[k:k + size]


@pytest.mark.parametrize("size", [1, 7, 4096, 1 << 20])
async def test_mjpeg_parts_whole_byte_by_byte_and_many_at_once(size: int) -> None:
    jpegs = [bytes([0xFF, 0xD8]) + bytes(range(k % 256)) * 3 + b"\r\n\r\n" + bytes([0xFF, 0xD9])
             for k in range(1, 6)]
    body = b"".join(part(k, j) for k, j in enumerate(jpegs))
    assert [j async for j in mjpeg_parts(_chunks(body, size))] == jpegs


async def test_mjpeg_part_without_length_is_refused() -> None:
    with pytest.raises(ValueError, match="Content-Length"):
        _ = [j async for j in mjpeg_parts(_chunks(b"--frame\r\nX: 1\r\n\r\nabc", 100))]


def test_fit_is_exact_without_noise_and_its_inverse_maps_back() -> None:
    h = camera_homography()
    xy = np.array([[0.06, -0.14], [0.06, 0.14], [0.30, 0.14], [0.30, -0.14], [0.18, 0.0]])
    uv = project(h, xy)
    cal = fit(uv, np.c_[xy, np.full(5, 0.02)])
    assert cal.rms_px < 1e-6 and cal.max_px < 1e-6 and cal.points == 5
    assert cal.z == pytest.approx(0.02)
    assert np.allclose(np.array(cal.homography), h, atol=1e-6 * np.abs(h).max())
    assert np.allclose(to_table(cal, uv), xy, atol=1e-9)


def test_fit_refuses_non_finite_points_and_unequal_counts() -> None:
    uv = np.array([[0, 0], [100, 0], [0, 100], [100, 100.0]])
    xyz = np.array([[0.1, 0, 0], [0.2, 0, 0], [0.1, 0.1, 0], [0.2, 0.1, 0]])
    with pytest.raises(InvalidRequest, match="as many pixels as positions"):
        fit(uv[:3], xyz)
    bad = xyz.copy()
    bad[0, 0] = np.nan
    with pytest.raises(InvalidRequest, match="finite"):
        fit(uv, bad)
