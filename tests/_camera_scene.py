"""Synthetic camera scenes for the camera tests and bench: coloured discs on a grained table
texture, seen through a known tilted pinhole camera (so the true table-to-image homography is
known), with optional lighting change and pixel noise; an MJPEG server to stand for a network
camera. Generated, not committed."""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import cv2
import numpy as np

#: The table region drawn, base frame, m.
X0, X1, Y0, Y1 = 0.04, 0.32, -0.16, 0.16
#: Canvas resolution of the top-down drawing, px/m.
SCALE = 2000.0
DISC_R = 0.015
BGR = {"red": (40, 40, 210), "green": (50, 170, 40), "blue": (200, 90, 20),
       "yellow": (30, 210, 230)}
#: Four markers "clicked" for a calibration (tip positions on the table, z = 0).
MARKERS = [(0.07, -0.13), (0.07, 0.13), (0.29, 0.13), (0.29, -0.12)]


def camera_homography(width: int = 640, height: int = 480, tilt_deg: float = 12.0
                      ) -> np.ndarray:
    """A pinhole camera 0.5 m above the table's middle, tilted `tilt_deg` about its x axis:
    H = K [r1 r2 t] (table x, y at z = 0 to pixels), normalised."""
    f = 560.0
    k = np.array([[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1]])
    down = np.array([[0.0, -1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])  # columns: axes
    a = np.radians(tilt_deg)
    tilt = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    rot = down @ tilt
    centre = np.array([(X0 + X1) / 2 - 0.5 * np.sin(a), (Y0 + Y1) / 2, 0.5 * np.cos(a)])
    rw = rot.T
    t = -rw @ centre
    h = k @ np.column_stack([rw[:, 0], rw[:, 1], t])
    return h / h[2, 2]


def project(h: np.ndarray, xy: np.ndarray) -> np.ndarray:
    q = np.c_[np.asarray(xy, float).reshape(-1, 2), np.ones(len(np.atleast_2d(xy)))] @ h.T
    out: np.ndarray = q[:, :2] / q[:, 2:3]
    return out


@dataclass(frozen=True)
class Disc:
    color: str
    x: float
    y: float


def scene(seed: int, n: int = 6) -> list[Disc]:
    """`n` discs in three colours, apart from each other and the table's edge."""
    rng = np.random.default_rng(seed)
    out: list[Disc] = []
    colors = ["red", "green", "blue"]
    while len(out) < n:
        x, y = rng.uniform(X0 + 0.03, X1 - 0.03), rng.uniform(Y0 + 0.03, Y1 - 0.03)
        if all(np.hypot(x - d.x, y - d.y) > 3 * DISC_R for d in out):
            out.append(Disc(colors[len(out) % 3], float(x), float(y)))
    return out


def render(discs: list[Disc], h: np.ndarray, *, width: int = 640, height: int = 480,
           light: float = 1.0, noise: float = 0.0, seed: int = 0) -> np.ndarray:
    """The discs on the table as the camera `h` sees them, BGR."""
    rng = np.random.default_rng(seed)
    cw, ch = int((Y1 - Y0) * SCALE), int((X1 - X0) * SCALE)
    canvas = np.full((ch, cw, 3), 150, np.uint8)
    grain = rng.normal(0, 6, (ch, cw, 1))
    canvas = np.clip(canvas + grain, 0, 255).astype(np.uint8)
    for k in range(0, cw, 100):  # a 5 cm grid
        canvas[:, k:k + 2] = 120
    for k in range(0, ch, 100):
        canvas[k:k + 2, :] = 120
    for d in discs:  # column: y, row: x
        c = ((d.y - Y0) * SCALE, (d.x - X0) * SCALE)
        cv2.circle(canvas, (round(c[0] * 16), round(c[1] * 16)), round(DISC_R * SCALE * 16),
                   BGR[d.color], -1, cv2.LINE_AA, shift=4)
    # canvas (col, row, 1) -> table (x, y, 1); pixel centres at integer coordinates
    a = np.array([[0, 1 / SCALE, X0], [1 / SCALE, 0, Y0], [0, 0, 1]])
    img = cv2.warpPerspective(canvas, h @ a, (width, height), flags=cv2.INTER_LINEAR,
                              borderValue=(60, 60, 60))
    out = img.astype(np.float32) * light
    if noise:
        out += rng.normal(0, noise, out.shape)
    return np.clip(out + 0.5, 0, 255).astype(np.uint8)


def write_folder(folder: Path, images: list[np.ndarray]) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    for k, img in enumerate(images):
        cv2.imwrite(str(folder / f"{k:03d}.png"), img)
    return folder


def clicked(h: np.ndarray) -> list[tuple[tuple[float, float], tuple[float, float, float]]]:
    """The four markers as clicked: whole pixels, and the tip's position there."""
    uv = np.round(project(h, np.array(MARKERS)))
    return [((float(u), float(v)), (x, y, 0.0)) for (u, v), (x, y) in zip(uv, MARKERS,
                                                                          strict=True)]


class MjpegServer:
    """An HTTP MJPEG camera on a loopback port (a network camera), stoppable and restartable
    on the same port."""

    def __init__(self, image: np.ndarray, fps: float = 20.0, port: int = 0) -> None:
        self.jpeg = cv2.imencode(".jpg", image)[1].tobytes()
        self.fps = fps
        self.port = port
        self._stop = threading.Event()
        self._srv: ThreadingHTTPServer | None = None

    def start(self) -> MjpegServer:
        owner = self

        class Handler(BaseHTTPRequestHandler):
            def do_GET(self) -> None:
                self.send_response(200)
                self.send_header("Content-Type", "multipart/x-mixed-replace; boundary=frame")
                self.end_headers()
                try:
                    while not owner._stop.is_set():
                        self.wfile.write(b"--frame\r\nContent-Type: image/jpeg\r\n"
                                         b"Content-Length: %d\r\n\r\n" % len(owner.jpeg)
                                         + owner.jpeg + b"\r\n")
                        time.sleep(1.0 / owner.fps)
                except OSError:
                    pass

            def log_message(self, *args: object) -> None:
                pass

        self._stop.clear()
        ThreadingHTTPServer.allow_reuse_address = True
        self._srv = ThreadingHTTPServer(("127.0.0.1", self.port), Handler)
        self._srv.daemon_threads = True
        self.port = self._srv.server_address[1]
        threading.Thread(target=self._srv.serve_forever, daemon=True).start()
        return self

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}/camera.mjpg"

    def stop(self) -> None:
        self._stop.set()
        if self._srv is not None:
            self._srv.shutdown()
            self._srv.server_close()
            self._srv = None
