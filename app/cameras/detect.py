"""Colour detection, as the lab's `detectColor()`: HSV thresholds, morphological clean-up,
connected components, a minimum area; the largest object first.

OpenCV calls: `cv2.cvtColor(BGR2HSV)`, `cv2.inRange` per band (red has two: its hue wraps at
0/180), `cv2.morphologyEx` open (specks) then close (holes), and
`cv2.connectedComponentsWithStats` (area, bounding box, centroid of each component); see
OpenCV's "Changing Colorspaces", "Morphological Transformations" and
`connectedComponentsWithStats` documentation. Pure: an image in, blobs out.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass

import cv2
import numpy as np

from app.cameras.config import Band

__all__ = ["MAX_PER_COLOR", "Blob", "detect", "mask_of"]

#: Most objects reported per colour (the largest): an answer stays small on a noisy scene.
MAX_PER_COLOR = 50
_KERNEL = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (5, 5))


@dataclass(frozen=True)
class Blob:
    color: str
    #: Centroid, px (u right, v down, origin at the top-left pixel's centre).
    u: float
    v: float
    #: Pixels.
    area: int
    #: [u0, v0, u1, v1]: the first and one past the last column and row, px.
    bbox: tuple[int, int, int, int]


def mask_of(hsv: np.ndarray, bands: Iterable[Band]) -> np.ndarray:
    """The cleaned mask (uint8 0/255) of the pixels inside any of `bands`."""
    mask: np.ndarray | None = None
    for low, high in bands:
        m = cv2.inRange(hsv, np.array(low, np.uint8), np.array(high, np.uint8))
        mask = m if mask is None else cv2.bitwise_or(mask, m)
    assert mask is not None, "a colour has one band at least (checked by its config)"
    mask = cv2.morphologyEx(mask, cv2.MORPH_OPEN, _KERNEL)
    return cv2.morphologyEx(mask, cv2.MORPH_CLOSE, _KERNEL)


def detect(image: np.ndarray, palette: Mapping[str, Iterable[Band]], colors: Iterable[str],
           min_area: int) -> list[Blob]:
    """Objects of each of `colors` (names in `palette`) in a BGR image, at least `min_area`
    pixels each, largest first (at most MAX_PER_COLOR per colour)."""
    hsv = cv2.cvtColor(image, cv2.COLOR_BGR2HSV)
    found: list[Blob] = []
    for color in colors:
        mask = mask_of(hsv, palette[color])
        n, _, stats, centroids = cv2.connectedComponentsWithStats(mask, connectivity=8)
        blobs = []
        for i in range(1, n):  # 0 is the background
            area = int(stats[i, cv2.CC_STAT_AREA])
            if area < min_area:
                continue
            x, y = int(stats[i, cv2.CC_STAT_LEFT]), int(stats[i, cv2.CC_STAT_TOP])
            w, h = int(stats[i, cv2.CC_STAT_WIDTH]), int(stats[i, cv2.CC_STAT_HEIGHT])
            blobs.append(Blob(color, float(centroids[i, 0]), float(centroids[i, 1]), area,
                              (x, y, x + w, y + h)))
        blobs.sort(key=lambda b: -b.area)
        found.extend(blobs[:MAX_PER_COLOR])
    found.sort(key=lambda b: -b.area)
    return found
