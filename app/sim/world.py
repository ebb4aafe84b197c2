"""The simulated world of one simulated arm: the table, coloured objects on it, bins, and what
the end effector does to them (grasp, carry, release).

Frames and units: the arm's base frame (x, y, z in metres, z up), as its kinematics model
reports the tip. The table is the plane ``z = table.z``; bins are axis-aligned boxes standing
on it (``min``/``max`` corners); an object's ``position`` is its centre.

Physics, kept to what a sorting lab needs:

- **Claw** (a profile with ``[gripper] kind = "claw"``: the rbe3001's, the OpenManipulator-X's).
  When the claw closes (its opening crosses ``CLOSED`` going up: 0.0 open .. 1.0 closed, the
  value the simulated hardware itself reports) around an object whose centre is within
  ``GRASP_TOLERANCE`` of the tip, the object is held and its centre follows the tip. When the
  claw opens again (crosses ``CLOSED`` going down) the held object is released where it is
  and falls straight down: onto a bin's floor when its centre is above the bin's footprint,
  else onto the table.
- **Magnet** (``kind = "magnet"``: the angler's passive magnet on its winch, which has no
  on/off state). A magnetic ``target`` whose top face is within ``MAGNET_TOLERANCE`` of the
  tip sticks to the magnet and hangs from it. A held target lowered into a bin (the tip inside
  the bin's footprint and below its rim) is stripped off by the rim and stays in the bin; a
  target lying in a bin is not picked again. That stripping is this simulator's model of the
  lab's release by hand; the angler's profile models no release of its own.

The world follows the simulated device's own joint state, not the server's commands: the
device's tap (app/sim/world_tap.py) records the joint readings the simulated hardware holds
(encoder ticks, servo Present Position) at most every ``TAP_PERIOD_S`` of simulated time; the
world converts them through the profile's transmission and the arm's kinematics model
(app/arms ``model_for``) and replays them, in order, whenever it is read (a GET of the world
route, a frame of the simulated camera). The control thread only appends a snapshot to a
deque; the grasp logic runs on the reader's thread under the world's lock.
"""

from __future__ import annotations

import math
import threading
from collections import deque
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field, replace
from typing import Literal

import numpy as np

from app.arms import model_for
from app.config import ArmProfile

Kind = Literal["ball", "block", "target"]

#: Named colours (BGR, 0..255), the camera's default detection colours (API.md "Cameras").
COLORS: dict[str, tuple[int, int, int]] = {
    "red": (40, 40, 210),
    "green": (50, 170, 40),
    "blue": (200, 90, 20),
    "yellow": (30, 210, 230),
}
#: Object sizes (m): a ball's diameter, a block's edge, a target's diameter and thickness.
BALL_D = 0.025
BLOCK_EDGE = 0.025
TARGET_D = 0.03
TARGET_T = 0.005
#: The claw holds an object whose centre is this close to the tip when it closes (m).
GRASP_TOLERANCE = 0.02
#: The magnet picks a target whose top face centre is this close to the tip (m).
MAGNET_TOLERANCE = 0.008
#: Claw opening (0 open .. 1 closed) above which the claw counts as closed.
CLOSED = 0.5
#: Snapshots the tap keeps between two reads (at TAP_PERIOD_S: two minutes); older ones go.
HISTORY = 6000
#: At most one snapshot per this much simulated time (s): the world's own rate.
TAP_PERIOD_S = 0.02
MAX_OBJECTS = 64
MAX_BINS = 16


class SceneError(ValueError):
    """A scene that cannot be laid out; the message says which item and why."""


def height(kind: str) -> float:
    """An object's height (m): its centre sits half that above what it rests on."""
    return TARGET_T if kind == "target" else (BALL_D if kind == "ball" else BLOCK_EDGE)


def width(kind: str) -> float:
    """An object's footprint across (m): a disc's diameter, a block's edge."""
    return {"ball": BALL_D, "block": BLOCK_EDGE}.get(kind, TARGET_D)


@dataclass(frozen=True)
class Table:
    """The table's top: a rectangle ``x0..x1`` by ``y0..y1`` at height ``z`` (m)."""

    x0: float
    x1: float
    y0: float
    y1: float
    z: float

    def contains(self, x: float, y: float) -> bool:
        return self.x0 <= x <= self.x1 and self.y0 <= y <= self.y1


@dataclass(frozen=True)
class Bin:
    """A box on the table; ``lo`` and ``hi`` are its min and max corners (m)."""

    name: str
    color: str
    lo: tuple[float, float, float]
    hi: tuple[float, float, float]

    def over(self, x: float, y: float) -> bool:
        """(x, y) is within the bin's footprint."""
        return self.lo[0] <= x <= self.hi[0] and self.lo[1] <= y <= self.hi[1]

    @property
    def centre(self) -> tuple[float, float]:
        return ((self.lo[0] + self.hi[0]) / 2, (self.lo[1] + self.hi[1]) / 2)


@dataclass(frozen=True)
class WorldObject:
    id: str
    kind: Kind
    color: str
    position: tuple[float, float, float]
    held: bool = False


@dataclass(frozen=True)
class Scene:
    """What the world holds at one moment: objects, bins, the table, the tip (None before the
    device's first reading) and the claw's opening (None for a magnet)."""

    objects: tuple[WorldObject, ...]
    bins: tuple[Bin, ...]
    table: Table
    tip: tuple[float, float, float] | None = None
    gripper: float | None = None


@dataclass
class _Tracker:
    """The end effector's state as the replayed readings left it."""

    tip: tuple[float, float, float] | None = None
    gripper: float | None = None
    held: str | None = None  # the id of the held object


#: Per arm type (app/sim may name them): the table, and where the default scene's objects and
#: bins go (object region x0, x1, y0, y1; bins as (name, colour, x0, x1, y0, y1)).
_LAYOUTS: dict[str, tuple[Table, tuple[float, float, float, float],
                          tuple[tuple[str, str, float, float, float, float], ...]]] = {
    "rbe3001": (Table(-0.05, 0.38, -0.32, 0.32, 0.0), (0.11, 0.23, -0.12, 0.12), (
        ("red", "red", 0.04, 0.11, 0.17, 0.25),
        ("green", "green", 0.04, 0.11, -0.25, -0.17),
        ("blue", "blue", 0.26, 0.31, -0.04, 0.04))),
    "openmanipulator_x": (Table(-0.05, 0.38, -0.32, 0.32, 0.0), (0.14, 0.24, -0.10, 0.10), (
        ("red", "red", 0.06, 0.13, 0.15, 0.23),
        ("green", "green", 0.06, 0.13, -0.23, -0.15),
        ("blue", "blue", 0.27, 0.32, -0.04, 0.04))),
    "angler": (Table(-0.2, 0.2, -0.1, 0.2, -0.05), (-0.065, 0.065, 0.045, 0.105), (
        ("red", "red", 0.105, 0.155, -0.045, 0.005),
        ("green", "green", -0.155, -0.105, -0.045, 0.005),
        ("blue", "blue", -0.025, 0.025, 0.13, 0.165))),
}
_BIN_HEIGHT = 0.03


def layout_for(profile: ArmProfile) -> tuple[Table, tuple[float, float, float, float],
                                              tuple[Bin, ...]]:
    """The table, the default object region and the default bins of a profile's arm type (an
    arm type without a layout of its own gets the rbe3001's)."""
    table, region, bins = _LAYOUTS.get(profile.model, _LAYOUTS["rbe3001"])
    z = table.z
    return table, region, tuple(Bin(n, c, (x0, y0, z), (x1, y1, z + _BIN_HEIGHT))
                                for n, c, x0, x1, y0, y1 in bins)


class World:
    """One simulated arm's surroundings. Thread-safe: every public method takes the lock."""

    def __init__(self, profile: ArmProfile) -> None:
        self.profile = profile
        self.model = model_for(profile)
        self.effector: str = profile.gripper.kind  # "claw", "magnet" or "none"
        self.kinds: tuple[Kind, ...] = (("target",) if self.effector == "magnet"
                                        else ("ball", "block"))
        self.table, self.region, default_bins = layout_for(profile)
        self._lock = threading.Lock()
        self._pending: deque[tuple[tuple[float, ...], float | None]] = deque(maxlen=HISTORY)
        self._objects: dict[str, WorldObject] = {}
        self._bins: tuple[Bin, ...] = default_bins
        self._fx = _Tracker()
        self.version = 0  # bumped at every change of the scene (a renderer may cache on it)
        self.set_scene(random_objects(self, seed=0), default_bins)

    # --- the device's side (called by the tap, on the control thread: cheap) -------------

    def observe(self, joint_ticks: tuple[float, ...], gripper: float | None) -> None:
        """Record one reading of the simulated hardware: joint positions in device ticks and
        the claw's opening (0..1) or None. Only appends (deque.append is atomic)."""
        self._pending.append((joint_ticks, gripper))

    # --- readers -------------------------------------------------------------------------

    def scene(self) -> Scene:
        """The scene now, after replaying every reading the device has recorded."""
        with self._lock:
            self._replay()
            return Scene(tuple(self._objects.values()), self._bins, self.table,
                         self._fx.tip, self._fx.gripper)

    def set_scene(self, objects: Iterable[WorldObject], bins: Iterable[Bin]) -> Scene:
        """Replace the scene (all or nothing): every object settles on what is below it, and
        nothing is held. Raises SceneError with the reason; the scene is then unchanged."""
        objs, bns = list(objects), tuple(bins)
        self._check(objs, bns)
        with self._lock:
            self._replay()
            self._bins = bns
            self._objects = {o.id: replace(o, held=False, position=self._rest(
                o.kind, o.position[0], o.position[1])) for o in objs}
            self._fx.held = None
            self.version += 1
            return Scene(tuple(self._objects.values()), self._bins, self.table,
                         self._fx.tip, self._fx.gripper)

    # --- checks --------------------------------------------------------------------------

    def _check(self, objs: Sequence[WorldObject], bins: Sequence[Bin]) -> None:
        if len(objs) > MAX_OBJECTS or len(bins) > MAX_BINS:
            raise SceneError(f"at most {MAX_OBJECTS} objects and {MAX_BINS} bins")
        t = self.table
        names: set[str] = set()
        for b in bins:
            where = f"bin {b.name!r}"
            if b.name in names:
                raise SceneError(f"{where}: two bins of that name")
            names.add(b.name)
            _known_color(where, b.color)
            _finite(where, (*b.lo, *b.hi))
            if not all(lo < hi for lo, hi in zip(b.lo, b.hi, strict=True)):
                raise SceneError(f"{where}: min must be below max on every axis")
            if not (t.contains(b.lo[0], b.lo[1]) and t.contains(b.hi[0], b.hi[1])):
                raise SceneError(f"{where}: off the table (x {t.x0}..{t.x1}, y {t.y0}..{t.y1})")
        ids: set[str] = set()
        for o in objs:
            where = f"object {o.id!r}"
            if not o.id or o.id in ids:
                raise SceneError(f"{where}: ids must be non-empty and unique")
            ids.add(o.id)
            _known_color(where, o.color)
            if o.kind not in self.kinds:
                raise SceneError(f"{where}: kind {o.kind!r} is not for a {self.effector} "
                                 f"end effector (use {', '.join(self.kinds)})")
            _finite(where, o.position)
            x, y, _ = o.position
            if not t.contains(x, y):
                raise SceneError(f"{where}: off the table at x={x:.4f}, y={y:.4f} (the table "
                                 f"is x {t.x0}..{t.x1}, y {t.y0}..{t.y1} m)")

    # --- physics (under the lock) ----------------------------------------------------------

    def _rest(self, kind: str, x: float, y: float) -> tuple[float, float, float]:
        """Where an object dropped at (x, y) comes to rest: a bin's floor or the table."""
        b = self._bin_under(x, y)
        return (float(x), float(y), (b.lo[2] if b is not None else self.table.z) + height(kind) / 2)

    def _replay(self) -> None:
        """Every recorded reading, in order: the tips in one vectorised pass, then the grasp
        logic a reading at a time (two minutes of motion: a few tens of ms)."""
        batch = []
        while self._pending:
            batch.append(self._pending.popleft())
        if not batch:
            return
        ticks = np.array([t for t, _ in batch], dtype=float)
        tips = np.asarray(self.model.fk(self.model.transmission.from_ticks(ticks)), dtype=float)
        for (_, gripper), p in zip(batch, tips.tolist(), strict=True):
            self._step((p[0], p[1], p[2]), gripper)

    def _step(self, tip: tuple[float, float, float], gripper: float | None) -> None:
        fx = self._fx
        was = fx.gripper
        fx.tip, fx.gripper = tip, gripper
        if self.effector == "claw" and gripper is not None:
            # the first reading only says where the claw is (a half-open gripper at power-up
            # is not a claw closing on what happens to lie there)
            closing = gripper >= CLOSED and was is not None and was < CLOSED
            opening = gripper < CLOSED and was is not None and was >= CLOSED
            if fx.held is not None and opening:
                self._release()
            elif fx.held is None and closing:
                fx.held = self._nearest(tip, GRASP_TOLERANCE, top=False)
        elif self.effector == "magnet":
            if fx.held is not None:
                b = self._bin_under(tip[0], tip[1])
                if b is not None and tip[2] <= b.hi[2]:
                    self._release()
            else:
                fx.held = self._nearest(tip, MAGNET_TOLERANCE, top=True)
        if fx.held is not None:
            o = self._objects[fx.held]
            dz = -height(o.kind) / 2 if self.effector == "magnet" else 0.0
            self._objects[o.id] = replace(o, held=True, position=(tip[0], tip[1], tip[2] + dz))
            self.version += 1

    def _nearest(self, tip: tuple[float, float, float], tol: float, top: bool) -> str | None:
        best, best_d = None, tol
        for o in self._objects.values():
            if top and self._bin_under(o.position[0], o.position[1]) is not None:
                continue  # a target in a bin stays there (module docstring)
            z = o.position[2] + (height(o.kind) / 2 if top else 0.0)
            d = math.dist(tip, (o.position[0], o.position[1], z))
            if d <= best_d:
                best, best_d = o.id, d
        return best

    def _release(self) -> None:
        held = self._fx.held
        self._fx.held = None
        if held is None:
            return
        o = self._objects[held]
        self._objects[held] = replace(o, held=False,
                                      position=self._rest(o.kind, o.position[0], o.position[1]))
        self.version += 1

    def _bin_under(self, x: float, y: float) -> Bin | None:
        for b in self._bins:
            if b.over(x, y):
                return b
        return None


def _known_color(where: str, color: str) -> None:
    if color not in COLORS:
        raise SceneError(f"{where}: unknown colour {color!r} (known: {', '.join(COLORS)})")


def _finite(where: str, values: Iterable[float]) -> None:
    if not all(math.isfinite(v) for v in values):
        raise SceneError(f"{where}: every coordinate must be a finite number")


@dataclass
class _Picker:
    rng: np.random.Generator
    placed: list[tuple[float, float]] = field(default_factory=list)


def random_objects(world: World, seed: int, n: int = 6,
                   colors: Sequence[str] = ("red", "green", "blue"),
                   spacing: float = 0.04) -> list[WorldObject]:
    """`n` objects of the world's first kind, colours in turn, at random places of the
    default object region at least `spacing` apart (deterministic for a seed)."""
    x0, x1, y0, y1 = world.region
    pick = _Picker(np.random.default_rng(seed))
    out: list[WorldObject] = []
    for i in range(n):
        for _ in range(2000):
            x, y = (float(v) for v in pick.rng.uniform((x0, y0), (x1, y1)))
            if all(math.dist((x, y), p) >= spacing for p in pick.placed):
                break
        pick.placed.append((x, y))
        kind = world.kinds[i % len(world.kinds)] if world.effector == "magnet" else (
            world.kinds[int(pick.rng.integers(len(world.kinds)))])
        out.append(WorldObject(f"o{i + 1}", kind, colors[i % len(colors)],
                               (round(x, 4), round(y, 4), 0.0)))
    return out
