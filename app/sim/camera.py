"""The simulated camera: a pinhole view of a simulated world's table, rendered to a BGR image.

`SimView` is an ideal pinhole camera (no lens distortion): intrinsics ``fx, fy, cx, cy`` in
pixels for an image of ``width`` x ``height``, and a pose in the arm's base frame: the camera
centre ``position`` (m) and ``rotation``, whose columns are the camera's axes in the base
frame (OpenCV's convention: x right, y down, z along the optical axis). A base-frame point p
projects to ``K R^T (p - position)`` (OpenCV, "Camera Calibration and 3D Reconstruction":
the pinhole model). `table_homography` is that projection restricted to the table plane,
``H = K [r1 r2 r3 z + t]`` with ``[r1 r2 r3] = R^T`` and ``t = -R^T position``
(Hartley & Zisserman, a plane-to-image homography).

`render` draws the table (a neutral, faintly grained top with a 5 cm grid), the bins (a grey
floor tinted pale in their colour, a dark rim: unsaturated, so that colour detection does not
take a bin for an object), the objects (balls as shaded discs, blocks as squares with a
lit top, magnetic targets as flat discs with a ring) as seen from the camera, far ones first,
and the tip as a small dark cross. ``light`` scales the brightness; ``noise`` adds Gaussian
pixel noise of that standard deviation as a fraction of full scale. The same world, view,
size and seed give the same bytes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from functools import lru_cache

import cv2
import numpy as np

from app.config import ArmProfile
from app.sim.world import COLORS, Scene, World, height, layout_for, width

SHIFT = 4  # cv2 drawing's fractional bits: coordinates to 1/16 pixel
_ONE = 1 << SHIFT
TABLE_BGR = (168, 178, 184)
FLOOR_BGR = (70, 72, 74)
GRID_STEP_M = 0.05
#: The default view's focal length at 640 pixels wide, px.
FOCAL_PX = 1000.0


@dataclass(frozen=True)
class SimView:
    """A pinhole camera: intrinsics (px) for `width` x `height`, and its pose in the arm's
    base frame (position m; rotation: columns are the camera's x, y, z axes)."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    position: tuple[float, float, float]
    rotation: tuple[tuple[float, float, float], ...]
    #: The table plane's height (m) for `table_homography`.
    table_z: float = 0.0

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def R(self) -> np.ndarray:
        """Camera-to-base rotation (3, 3)."""
        return np.array(self.rotation, dtype=float)

    def scaled(self, width: int, height: int) -> SimView:
        """The same camera at another image size (intrinsics scaled)."""
        if (width, height) == (self.width, self.height):
            return self
        sx, sy = width / self.width, height / self.height
        return replace(self, fx=self.fx * sx, fy=self.fy * sy, cx=(self.cx + 0.5) * sx - 0.5,
                       cy=(self.cy + 0.5) * sy - 0.5, width=width, height=height)

    def to_camera(self, points: np.ndarray) -> np.ndarray:
        """Base-frame points (..., 3) in the camera's frame (..., 3)."""
        p = np.asarray(points, dtype=float) - np.asarray(self.position)
        return np.asarray(p @ self.R)

    def project(self, points: np.ndarray) -> np.ndarray:
        """Pixels (..., 2) (u right, v down) of base-frame points (..., 3) in front of it."""
        c = self.to_camera(points)
        z = c[..., 2]
        return np.stack([self.fx * c[..., 0] / z + self.cx, self.fy * c[..., 1] / z + self.cy],
                        axis=-1)

    def table_homography(self, z: float | None = None) -> np.ndarray:
        """H (3, 3): base-frame table points (x, y, 1) at height `z` (default the table's) to
        pixels (u, v, 1), up to scale (normalised so that H[2, 2] = 1)."""
        z0 = self.table_z if z is None else z
        Rw = self.R.T
        t = -Rw @ np.asarray(self.position, dtype=float)
        H = self.K @ np.column_stack([Rw[:, 0], Rw[:, 1], Rw[:, 2] * z0 + t])
        return np.asarray(H / H[2, 2])

    @classmethod
    def looking_down(cls, centre: tuple[float, float], above: float, table_z: float,
                     width: int = 640, height: int = 480, f: float = 600.0) -> SimView:
        """A camera `above` m over (x, y) = `centre` looking straight down, the base's +x up
        the image and +y to its left (the arm seen from above, its base at the bottom)."""
        rot = ((0.0, -1.0, 0.0), (-1.0, 0.0, 0.0), (0.0, 0.0, -1.0))  # columns: x, y, z axes
        return cls(f, f, (width - 1) / 2, (height - 1) / 2, width, height,
                   (centre[0], centre[1], table_z + above), rot, table_z)

    @classmethod
    def default_for(cls, profile: ArmProfile, width: int = 640, height: int = 480) -> SimView:
        """A view from above of the profile's table workspace: the default object region and
        the bins in the picture with a margin. A long focal length (1000 px at 640 wide, a 35
        degree field) from high up: a 25 mm block's top lies within ~4 mm of its footprint
        through the table homography across the picture, where a wide lens from close by would
        put it twice as far."""
        table, (x0, x1, y0, y1), bins = layout_for(profile)
        xs = [x0, x1, *(b.lo[0] for b in bins), *(b.hi[0] for b in bins)]
        ys = [y0, y1, *(b.lo[1] for b in bins), *(b.hi[1] for b in bins)]
        cx, cy = (min(xs) + max(xs)) / 2, (min(ys) + max(ys)) / 2
        f = FOCAL_PX * width / 640
        # half extents: base x runs along the image's v axis, base y along u; 15 % margin
        above = 1.15 * max((max(ys) - min(ys)) / 2 / ((width / 2) / f),
                           (max(xs) - min(xs)) / 2 / ((height / 2) / f))
        return cls.looking_down((cx, cy), round(above, 3), table.z, width, height, f)


def render(world: World | Scene, view: SimView, width: int, height: int, *,
           noise: float = 0.0, light: float = 1.0, seed: int = 0) -> np.ndarray:
    """The world as `view` sees it: (height, width, 3) uint8 BGR. Deterministic for a seed."""
    scene = world.scene() if isinstance(world, World) else world
    v = view.scaled(width, height)
    img = _table_image(v, scene.table.x0, scene.table.x1, scene.table.y0, scene.table.y1,
                       scene.table.z).copy()
    for b in scene.bins:
        _draw_bin(img, v, b.lo, b.hi, COLORS[b.color])
    cam_z = np.array([v.to_camera(np.array(o.position))[2] for o in scene.objects])
    for i in np.argsort(-cam_z, kind="stable"):  # far first: near ones cover them
        o = scene.objects[int(i)]
        _draw_object(img, v, o.kind, o.position, COLORS[o.color])
    if scene.tip is not None:
        _draw_tip(img, v, scene.tip)
    if light == 1.0 and noise <= 0.0:
        # the picture as drawn: the pass below would give the same bytes (x + 0.5 floors to x)
        # and was two thirds of a frame's 20-26 ms (a sim camera read at 15 fps: a third of a
        # core)
        return img
    out = img.astype(np.float32)
    if light != 1.0:
        out *= float(light)
    if noise > 0.0:
        rng = np.random.default_rng(seed)
        out += rng.normal(0.0, 255.0 * float(noise), out.shape).astype(np.float32)
    return np.asarray(np.clip(out + 0.5, 0, 255).astype(np.uint8))


# --- drawing ------------------------------------------------------------------------------

def _fix(uv: np.ndarray) -> np.ndarray:
    """Pixel coordinates to cv2's fixed point (SHIFT fractional bits)."""
    return np.round(np.asarray(uv) * _ONE).astype(np.int32)


@lru_cache(maxsize=8)
def _table_image(v: SimView, x0: float, x1: float, y0: float, y1: float,
                 z: float) -> np.ndarray:
    """The empty table (cached per view and table): floor, top, grain, grid."""
    img = np.empty((v.height, v.width, 3), np.uint8)
    img[:] = FLOOR_BGR
    corners = np.array([(x0, y0, z), (x1, y0, z), (x1, y1, z), (x0, y1, z)])
    cv2.fillPoly(img, [_fix(v.project(corners))], TABLE_BGR, cv2.LINE_AA, SHIFT)
    mask = np.zeros(img.shape[:2], np.uint8)
    cv2.fillPoly(mask, [_fix(v.project(corners))], 255, cv2.LINE_8, SHIFT)
    raw = np.random.default_rng(12345).normal(0.0, 3.0, img.shape[:2]).astype(np.float32)
    grain = np.asarray(cv2.GaussianBlur(raw, (0, 0), 1.5))[..., None]
    top = mask[..., None] > 0
    img = np.where(top, np.clip(img + grain, 0, 255), img).astype(np.uint8)
    grid = (150, 158, 162)
    for gx in np.arange(math.ceil(x0 / GRID_STEP_M), math.floor(x1 / GRID_STEP_M) + 1):
        a, b = v.project(np.array([(gx * GRID_STEP_M, y0, z), (gx * GRID_STEP_M, y1, z)]))
        cv2.line(img, tuple(_fix(a)), tuple(_fix(b)), grid, 1, cv2.LINE_AA, SHIFT)
    for gy in np.arange(math.ceil(y0 / GRID_STEP_M), math.floor(y1 / GRID_STEP_M) + 1):
        a, b = v.project(np.array([(x0, gy * GRID_STEP_M, z), (x1, gy * GRID_STEP_M, z)]))
        cv2.line(img, tuple(_fix(a)), tuple(_fix(b)), grid, 1, cv2.LINE_AA, SHIFT)
    img.setflags(write=False)
    return img


def _tint(color: tuple[int, int, int], amount: float, base: tuple[int, int, int]) -> tuple[
        int, int, int]:
    return (round(base[0] + amount * (color[0] - base[0])),
            round(base[1] + amount * (color[1] - base[1])),
            round(base[2] + amount * (color[2] - base[2])))


def _draw_bin(img: np.ndarray, v: SimView, lo: tuple[float, float, float],
              hi: tuple[float, float, float], color: tuple[int, int, int]) -> None:
    floor = np.array([(lo[0], lo[1], lo[2]), (hi[0], lo[1], lo[2]), (hi[0], hi[1], lo[2]),
                      (lo[0], hi[1], lo[2])])
    rim = floor.copy()
    rim[:, 2] = hi[2]
    cv2.fillPoly(img, [_fix(v.project(floor))], _tint(color, 0.22, (150, 150, 150)),
                 cv2.LINE_AA, SHIFT)
    for k in range(4):  # the walls, floor edge to rim edge
        wall = np.array([floor[k], floor[(k + 1) % 4], rim[(k + 1) % 4], rim[k]])
        cv2.fillConvexPoly(img, _fix(v.project(wall)), (95, 98, 100), cv2.LINE_AA, SHIFT)
    cv2.polylines(img, [_fix(v.project(rim))], True, (60, 62, 64), 2, cv2.LINE_AA, SHIFT)


def _radius_px(v: SimView, centre: np.ndarray, r: float) -> float:
    return float(v.fx * r / v.to_camera(centre)[2])


def _draw_object(img: np.ndarray, v: SimView, kind: str, pos: tuple[float, float, float],
                 color: tuple[int, int, int]) -> None:
    p = np.array(pos, dtype=float)
    top = p + (0.0, 0.0, height(kind) / 2)
    if kind == "block":
        e = width(kind) / 2
        sq = np.array([top + (-e, -e, 0), top + (e, -e, 0), top + (e, e, 0), top + (-e, e, 0)])
        cv2.fillPoly(img, [_fix(v.project(sq))], _tint(color, 0.85, (0, 0, 0)), cv2.LINE_AA,
                     SHIFT)
        inner = top + (sq - top) * 0.7
        cv2.fillPoly(img, [_fix(v.project(inner))], color, cv2.LINE_AA, SHIFT)
        return
    if kind == "ball":
        _shaded_disc(img, v.project(p), _radius_px(v, p, width(kind) / 2), color)
        return
    uv = v.project(top)
    r = _radius_px(v, top, width(kind) / 2)
    cv2.circle(img, tuple(_fix(uv)), round(r * _ONE), _tint(color, 0.8, (0, 0, 0)), -1,
               cv2.LINE_AA, SHIFT)
    cv2.circle(img, tuple(_fix(uv)), round(r * 0.75 * _ONE), color, -1, cv2.LINE_AA, SHIFT)
    cv2.circle(img, tuple(_fix(uv)), round(r * 0.25 * _ONE), _tint(color, 0.8, (0, 0, 0)), -1,
               cv2.LINE_AA, SHIFT)


def _shaded_disc(img: np.ndarray, uv: np.ndarray, r: float, color: tuple[int, int, int]) -> None:
    """A ball lit from above and a little to the top left: brightest off centre, darker to the
    rim (never below 55 % of its colour, so that its colour stays its colour)."""
    u0, v0 = float(uv[0]), float(uv[1])
    a, b = max(0, math.floor(u0 - r - 1)), min(img.shape[1], math.ceil(u0 + r + 2))
    c, d = max(0, math.floor(v0 - r - 1)), min(img.shape[0], math.ceil(v0 + r + 2))
    if a >= b or c >= d or r <= 0:
        return
    uu, vv = np.meshgrid(np.arange(a, b, dtype=np.float32), np.arange(c, d, dtype=np.float32))
    dist = np.hypot(uu - u0, vv - v0)
    cover = np.clip(r + 0.5 - dist, 0.0, 1.0)[..., None]  # anti-aliased edge
    hl = np.hypot(uu - (u0 - 0.3 * r), vv - (v0 - 0.3 * r)) / max(r, 1e-6)
    shade = np.clip(1.15 - 0.45 * hl, 0.55, 1.15)[..., None]
    ball = np.clip(np.array(color, np.float32) * shade, 0, 255)
    patch = img[c:d, a:b].astype(np.float32)
    img[c:d, a:b] = (patch * (1 - cover) + ball * cover + 0.5).astype(np.uint8)


def _draw_tip(img: np.ndarray, v: SimView, tip: tuple[float, float, float]) -> None:
    p = np.array(tip, dtype=float)
    if v.to_camera(p)[2] <= 0.01:
        return
    u, w = v.project(p)
    s = 6.0
    for a, b in (((u - s, w), (u + s, w)), ((u, w - s), (u, w + s))):
        cv2.line(img, tuple(_fix(np.array(a))), tuple(_fix(np.array(b))), (40, 40, 40), 2,
                 cv2.LINE_AA, SHIFT)
