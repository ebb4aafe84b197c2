"""Camera to arm calibration: the homography H from the table plane (the arm's base frame x, y,
m, at the table's height z) to the image (u, v, px), fitted from four or more correspondences,
and its inverse for a pixel's position on the table.

The fit is the normalised direct linear transform (Hartley and Zisserman, "Multiple View
Geometry", algorithm 4.2; what `cv2.findHomography` does with method 0), done here in numpy so
that a degenerate set is refused with its reason rather than fitted: too few points, a point
given twice, points on one line (in the image or on the table), three of four points on a line,
or a table that is not level (z spread). Pure functions; no I/O.
"""

from __future__ import annotations

import itertools
import time
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from app.errors import InvalidRequest

__all__ = ["MIN_POINTS", "Calibration", "fit", "project", "to_table"]

MIN_POINTS = 4
#: Two points closer than this are the same point: m on the table, px in the image.
SAME_M = 1e-3
SAME_PX = 1.0
#: Points whose smaller spread is under this fraction of the larger lie on one line.
LINE_RATIO = 0.02
#: Largest height difference between the points, m: they must all be on the table.
Z_SPREAD_M = 0.01


@dataclass(frozen=True)
class Calibration:
    #: Table (x, y, 1) -> image (u, v, 1) up to scale, row-major 3x3, H[2][2] = 1.
    homography: list[list[float]]
    #: The table's height in the arm's base frame (the points' mean z), m.
    z: float
    #: Reprojection error of the points: root mean square and largest, px.
    rms_px: float
    max_px: float
    points: int
    time: float

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> Calibration:
        return cls(homography=[[float(x) for x in row] for row in data["homography"]],
                   z=float(data["z"]), rms_px=float(data["rms_px"]),
                   max_px=float(data["max_px"]), points=int(data["points"]),
                   time=float(data["time"]))


def _normaliser(p: np.ndarray) -> np.ndarray:
    """The similarity taking `p` (n, 2) to centroid 0, mean distance sqrt(2) (Hartley)."""
    c = p.mean(axis=0)
    d = float(np.mean(np.linalg.norm(p - c, axis=1)))
    s = np.sqrt(2.0) / d
    return np.array([[s, 0.0, -s * c[0]], [0.0, s, -s * c[1]], [0.0, 0.0, 1.0]])


def _h(t: np.ndarray, p: np.ndarray) -> np.ndarray:
    q = np.c_[p, np.ones(len(p))] @ t.T
    out: np.ndarray = q[:, :2] / q[:, 2:3]
    return out


def project(h: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Table points (n, 2), m -> pixels (n, 2)."""
    return _h(np.asarray(h, float), np.asarray(xy, float).reshape(-1, 2))


def to_table(cal: Calibration, uv: np.ndarray) -> np.ndarray:
    """Pixels (n, 2) -> table points (n, 2), m."""
    inverse = np.linalg.inv(np.asarray(cal.homography, float))
    return _h(inverse, np.asarray(uv, float).reshape(-1, 2))


def _on_a_line(p: np.ndarray) -> bool:
    s = np.linalg.svd(p - p.mean(axis=0), compute_uv=False)
    return bool(s[0] == 0.0 or s[-1] / s[0] < LINE_RATIO)


def _check(uv: np.ndarray, xyz: np.ndarray) -> None:
    n = len(uv)
    if n < MIN_POINTS:
        raise InvalidRequest(f"a homography needs {MIN_POINTS} or more points, got {n}")
    if not (np.isfinite(uv).all() and np.isfinite(xyz).all()):
        raise InvalidRequest("the points must be finite numbers")
    for i, j in itertools.combinations(range(n), 2):
        if np.linalg.norm(xyz[i, :2] - xyz[j, :2]) < SAME_M:
            raise InvalidRequest(f"points {i + 1} and {j + 1} repeat the same table position "
                                 f"(closer than {SAME_M * 1000:g} mm)")
        if np.linalg.norm(uv[i] - uv[j]) < SAME_PX:
            raise InvalidRequest(f"points {i + 1} and {j + 1} repeat the same pixel")
    spread = float(np.ptp(xyz[:, 2]))
    if spread > Z_SPREAD_M:
        raise InvalidRequest(f"the points' heights differ by {spread * 1000:.0f} mm: they must "
                             f"all be on the table (within {Z_SPREAD_M * 1000:g} mm)")
    if _on_a_line(xyz[:, :2]):
        raise InvalidRequest("the table positions lie on one line (collinear): spread them "
                             "over the table")
    if _on_a_line(uv):
        raise InvalidRequest("the pixels lie on one line (collinear): spread them over the "
                             "image")
    if n == MIN_POINTS:
        for trio in itertools.combinations(range(n), 3):
            idx = list(trio)
            if _on_a_line(xyz[idx, :2]) or _on_a_line(uv[idx]):
                names = ", ".join(str(k + 1) for k in idx)
                raise InvalidRequest(f"points {names} lie on one line: with four points no "
                                     "three may be collinear")


def fit(uv: np.ndarray, xyz: np.ndarray) -> Calibration:
    """H from pixels `uv` (n, 2) and tip positions `xyz` (n, 3, m) on the table; raises
    `InvalidRequest` (422 `invalid_request`) with the reason for a degenerate set."""
    uv = np.asarray(uv, float).reshape(-1, 2)
    xyz = np.asarray(xyz, float).reshape(-1, 3)
    if len(uv) != len(xyz):
        raise InvalidRequest("as many pixels as positions are needed")
    _check(uv, xyz)
    ta, tb = _normaliser(xyz[:, :2]), _normaliser(uv)
    a, b = _h(ta, xyz[:, :2]), _h(tb, uv)
    rows = []
    for (x, y), (u, v) in zip(a, b, strict=True):
        rows.append([-x, -y, -1.0, 0.0, 0.0, 0.0, u * x, u * y, u])
        rows.append([0.0, 0.0, 0.0, -x, -y, -1.0, v * x, v * y, v])
    _, s, vt = np.linalg.svd(np.array(rows))
    if s[7] / s[0] < 1e-9:
        raise InvalidRequest("the points do not determine a homography (degenerate layout)")
    hn = vt[-1].reshape(3, 3)
    h = np.linalg.inv(tb) @ hn @ ta
    if abs(h[2, 2]) < 1e-12:
        raise InvalidRequest("the points do not determine a homography (the table's origin "
                             "maps to infinity)")
    h = h / h[2, 2]
    err = np.linalg.norm(project(h, xyz[:, :2]) - uv, axis=1)
    return Calibration(homography=h.tolist(), z=float(xyz[:, 2].mean()),
                       rms_px=float(np.sqrt(np.mean(err ** 2))), max_px=float(err.max()),
                       points=len(uv), time=time.time())
