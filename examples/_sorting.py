"""The lab's sorting program, shared by sort_colors.py (a claw) and angler_fish.py (a magnet):
the design document's `nextColor()` / `detectColor()` flow through the server's API.

Where things are comes from the camera, never from the simulator: `detectColor()` asks
GET /cameras/{cam}/detections for one colour and takes the largest object in the relevant field
of view (on the table, outside every bin). The camera is calibrated first if it is not: the tip
is put on four or more known table points and its mark found in the camera's frames (the
difference of two frames with the tip in two places), then POST /cameras/{cam}/calibration.
What the lab knows beforehand, as a lab would: its bins (read from the world route's layout, or
given), the table's height and the objects' sizes.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np
from _common import fail, fmt, log

from app.client import ArmClient, ArmServerError

#: Height to approach and leave from, above the object or the bin's rim, m.
APPROACH_DZ = 0.05
#: How far outside a bin's footprint a detection still counts as in the bin, m.
BIN_MARGIN = 0.012
#: A claw that closes or opens, s (the RBE3001 claw servo: ~0.5 s end to end).
CLAW_S = 0.7
#: Tries per object before the program leaves it (an object it cannot reach or hold).
TRIES = 2


@dataclass
class Bin:
    name: str
    color: str
    lo: tuple[float, float, float]
    hi: tuple[float, float, float]

    def holds(self, x: float, y: float, margin: float = BIN_MARGIN) -> bool:
        return (self.lo[0] - margin <= x <= self.hi[0] + margin
                and self.lo[1] - margin <= y <= self.hi[1] + margin)

    @property
    def centre(self) -> tuple[float, float]:
        return ((self.lo[0] + self.hi[0]) / 2, (self.lo[1] + self.hi[1]) / 2)


@dataclass
class Lab:
    """One sorting cell: the arm, its camera, its bins and how its end effector works."""

    c: ArmClient
    arm: str
    camera: str
    bins: list[Bin]
    table_z: float
    #: "claw": pick at the object's centre and close; "magnet": touch the object's top.
    effector: str
    #: The objects' height, m (a claw grips at half of it; a magnet touches the top).
    object_height: float
    min_area: int = 60
    speed: float = 1.0
    #: Height to approach and leave from, above the object or the bin's rim, m.
    approach: float = APPROACH_DZ
    given_up: list[tuple[float, float]] = field(default_factory=list)
    tries: dict[tuple[int, int], int] = field(default_factory=dict)
    dropped: dict[str, int] = field(default_factory=dict)

    # --- the design document's two functions -------------------------------------------------

    def detect_color(self, color: str) -> tuple[float, float] | None:
        """detectColor(): is any large enough object of `color` in the relevant field of view?
        Where the largest is on the table (x, y), or None."""
        found = self.c.detections(self.camera, color, min_area=self.min_area)
        for d in found.detections:  # largest first
            if d.position is None:
                fail(f"camera {self.camera} is not calibrated")
                return None
            x, y = d.position.x, d.position.y
            if any(b.holds(x, y) for b in self.bins):
                continue  # already sorted
            if any(np.hypot(x - gx, y - gy) < 0.015 for gx, gy in self.given_up):
                continue
            return (x, y)
        return None

    def run(self, colors: Sequence[str]) -> int:
        """The program: nextColor() picks the colour to look for; detectColor() finds its
        largest object; pick it and place it in that colour's bin; until no colour is left.
        The number of objects placed."""
        remaining = [c for c in colors]
        placed = 0

        def next_color() -> str | None:
            """nextColor(): the colour to look for next, None when the program ends."""
            return remaining[0] if remaining else None

        while (color := next_color()) is not None:
            spot = self.detect_color(color)
            if spot is None:
                log(f"{color}: none left")
                remaining.remove(color)
                continue
            bin_ = next((b for b in self.bins if b.color == color), None)
            if bin_ is None:
                fail(f"no bin for {color}")
                return placed
            key = (round(spot[0] * 100), round(spot[1] * 100))
            self.tries[key] = self.tries.get(key, 0) + 1
            if self.tries[key] > TRIES:
                log(f"{color}: giving up on the object at {fmt_xy(spot)}")
                self.given_up.append(spot)
                continue
            log(f"{color}: largest at {fmt_xy(spot)} -> bin {bin_.name}")
            try:
                self.pick(spot)
                self.place(bin_)
            except ArmServerError as exc:
                log(f"{color}: {exc.code}: {exc.detail}")
                self.given_up.append(spot)
                continue
            placed += 1
        return placed

    # --- moves --------------------------------------------------------------------------------

    def move(self, p: tuple[float, float, float], path: str = "joint") -> None:
        m = self.c.move_pose(self.arm, *p, path=path, speed=self.speed,  # type: ignore[arg-type]
                             wait=True)
        if m.status != "done":
            raise ArmServerError("motion_failed", f"{m.status}: {m.reason}", 409)

    def pick(self, spot: tuple[float, float]) -> None:
        x, y = spot
        if self.effector == "claw":
            z = self.table_z + self.object_height / 2
            self.c.gripper(self.arm, 0.0)
            self.move((x, y, z + self.approach))
            time.sleep(CLAW_S)  # the claw opens while the arm travels; this covers the rest
            self.move((x, y, z), "line")
            self.c.gripper(self.arm, 1.0)
            time.sleep(CLAW_S)
            self.move((x, y, z + self.approach), "line")
        else:  # straight down and up: only the winch turns (a joint path, at its speed)
            z = self.table_z + self.object_height + 0.001  # the magnet on the target's top
            self.move((x, y, z + self.approach))
            self.move((x, y, z))
            self.move((x, y, z + self.approach))

    def place(self, b: Bin) -> None:
        """Over the bin, at one of four spots a quarter of its size from its centre in turn
        (so that what it holds does not pile up in one place), release."""
        k = self.dropped.get(b.name, 0)
        self.dropped[b.name] = k + 1
        sx, sy = ((-1, -1), (1, 1), (-1, 1), (1, -1))[k % 4]
        x = b.centre[0] + sx * (b.hi[0] - b.lo[0]) / 4
        y = b.centre[1] + sy * (b.hi[1] - b.lo[1]) / 4
        if self.effector == "claw":
            self.move((x, y, b.hi[2] + self.approach / 2))
            self.c.gripper(self.arm, 0.0)
            time.sleep(CLAW_S)
        else:  # lowered into the bin, the rim strips the target off the magnet
            self.move((x, y, b.hi[2] + self.approach))
            self.move((x, y, b.hi[2] - 0.01))
            self.move((x, y, b.hi[2] + self.approach))

    # --- calibration ----------------------------------------------------------------------

    def calibrate(self, points: Sequence[tuple[float, float]], z: float) -> None:
        """Put the tip on each table point (at height z), find its mark in the camera's frame,
        and fit the camera's calibration from those pixels and positions."""
        frames = []
        path = "line" if self.effector == "claw" else "joint"  # a winch goes straight down
        for x, y in points:
            self.move((x, y, z + self.approach))
            self.move((x, y, z), path)
            frames.append(self.fresh_frame())
            self.move((x, y, z + self.approach), path)
        pairs = []
        for i, (x, y) in enumerate(points):
            other = frames[(i + 1) % len(frames)]
            u, v = tip_mark(frames[i], other)
            log(f"  tip at {fmt_xy((x, y))} seen at pixel ({u:.1f}, {v:.1f})")
            pairs.append(((u, v), (x, y, z)))
        cal = self.c.calibrate_camera(self.camera, pairs, arm=self.arm)
        log(f"camera {self.camera} calibrated: {fmt(cal)}" if hasattr(cal, "x") else
            f"camera {self.camera} calibrated from {len(pairs)} points")

    def fresh_frame(self) -> np.ndarray:
        """A frame the camera took after now (its sequence number past the current one)."""
        seq = self.c.detections(self.camera, min_area=10**6).frame_seq
        deadline = time.monotonic() + 10.0
        while self.c.detections(self.camera, min_area=10**6).frame_seq <= seq + 1:
            if time.monotonic() > deadline:
                fail(f"camera {self.camera} gives no new frames")
            time.sleep(0.05)
        jpeg = self.c.camera_frame(self.camera)
        image = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR)
        if image is None:
            fail("the camera's frame is not a JPEG")
        return np.asarray(image)


def tip_mark(here: np.ndarray, elsewhere: np.ndarray, threshold: int = 25) -> tuple[float, float]:
    """The tip's pixel: the centroid of what is darker in `here` than in `elsewhere` (the same
    scene with the tip moved away)."""
    a = cv2.cvtColor(here, cv2.COLOR_BGR2GRAY).astype(np.int16)
    b = cv2.cvtColor(elsewhere, cv2.COLOR_BGR2GRAY).astype(np.int16)
    mask = (b - a) > threshold
    vs, us = np.nonzero(mask)
    if len(us) < 5:
        fail("the tip's mark is not in the camera's view")
    w = (b - a)[mask].astype(float)
    return float(np.average(us, weights=w)), float(np.average(vs, weights=w))


def fmt_xy(p: tuple[float, float]) -> str:
    return f"({p[0] * 1000:+6.1f}, {p[1] * 1000:+6.1f}) mm"


def lab_from_world(c: ArmClient, arm: str, camera: str, effector: str, object_height: float,
                   speed: float, approach: float = APPROACH_DZ) -> Lab:
    """The lab's layout (bins, table height) as the world route describes it: the cell's
    furniture, which a lab knows; the objects are left to the camera."""
    w = c.world(arm)
    bins = [Bin(b.name, b.color, (b.min.x, b.min.y, b.min.z), (b.max.x, b.max.y, b.max.z))
            for b in w.bins]
    z = w.table.z if w.table is not None else 0.0
    return Lab(c, arm, camera, bins, z, effector, object_height, speed=speed,
               approach=approach)


def check_sorted(c: ArmClient, arm: str, bins: Sequence[Bin],
                 report: Callable[[str], None] = log) -> bool:
    """Every object in the bin of its colour (the world route: the simulator's truth, read only
    to check the result)."""
    ok = True
    for o in c.world(arm).objects:
        b = next((b for b in bins if b.color == o.color), None)
        inside = b is not None and b.holds(o.position.x, o.position.y, 0.0)
        ok = ok and inside and not o.held
        report(f"  {o.id} {o.color:<6} at ({o.position.x * 1000:+6.1f}, "
               f"{o.position.y * 1000:+6.1f}) mm: {'in its bin' if inside else 'NOT in its bin'}")
    return ok
