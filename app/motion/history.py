"""A motion's record and the per-arm motion history (issue 11.12).

The history keeps the last HISTORY motions or those ended within HISTORY_S, whichever is more,
never more than MAX_HISTORY records; a forgotten id leaves a tombstone (status, code, times) for
the last TOMBSTONES ids, so GET answers 410 `motion_expired` with what is known instead of a 404
as if it never existed.
"""

from __future__ import annotations

import asyncio
import time
import uuid
from collections import OrderedDict
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np

from app import schemas as s
from app.errors import MotionExpired, UnknownMotion
from app.runtime.control_thread import on_home

HISTORY = 256
HISTORY_S = 600.0
MAX_HISTORY = 4096
TOMBSTONES = 16384

Status = Literal["queued", "running", "done", "stopped", "failed"]
Kind = Literal["joints", "pose"]
PathKind = Literal["joint", "line"]


@dataclass
class Plan:
    traj: Any  # JointTrajectory or SampledTrajectory: .duration, .sample(t) -> (q, qd, qdd)
    start: np.ndarray
    target: np.ndarray
    path: PathKind


@dataclass
class MotionRecord:
    id: str
    arm: str
    kind: Kind
    path: PathKind
    request: Any
    target: np.ndarray
    target_tip: dict[str, float]  # as reported (x, y, z and, with a wrist, pitch)
    planned_duration: float
    planned_path: np.ndarray  # (k, 3) m, kept as one small array: the history holds 256
    status: Status = "queued"
    progress: float = 0.0
    reason: str | None = None
    code: str | None = None
    created: float = field(default_factory=time.time)
    started: float | None = None
    ended: float | None = None
    final_positions: list[float] | None = None
    final_tip: dict[str, float] | None = None
    cancel: str | None = None  # "stop" (decelerate), "replace" (hand over now)
    #: How to plan it again when it starts (the planner and its goal); dropped when it ends.
    planner: Any = field(default=None, repr=False)
    goal: np.ndarray | None = field(default=None, repr=False)
    done: asyncio.Event = field(default_factory=asyncio.Event)
    #: The control loop the record's executor runs on (waiting crosses there).
    home_loop: Any = field(default=None, repr=False)

    async def wait(self) -> MotionRecord:
        """Runs `_wait` on the executor's control loop (the record's event is set there)."""
        return await on_home(self.home_loop, lambda: self._wait())

    async def _wait(self) -> MotionRecord:
        await self.done.wait()
        return self

    def to_schema(self) -> s.Motion:
        return s.Motion(
            id=self.id, arm=self.arm, kind=self.kind, path=self.path, status=self.status,
            progress=round(self.progress, 4), planned_duration=self.planned_duration,
            target_positions=[float(v) for v in self.target], target_tip=s.Tip(**self.target_tip),
            reason=self.reason, code=self.code, created=self.created, started=self.started,
            ended=self.ended, final_positions=self.final_positions,
            final_tip=None if self.final_tip is None else s.Tip(**self.final_tip),
            planned_path=[s.Vec3(x=float(p[0]), y=float(p[1]), z=float(p[2]))
                          for p in self.planned_path])


class MotionHistory:
    """The records of one arm's motions by id, and the tombstones of forgotten ones."""

    def __init__(self, arm: str) -> None:
        self.arm = arm
        self._records: OrderedDict[str, MotionRecord] = OrderedDict()
        self._tombstones: OrderedDict[str, tuple[str, str | None, float, float | None]] = (
            OrderedDict())
        self._next_serial = 1  # the serial of the next motion id (for 410 on forgotten ids)
        #: how many motions, and how many seconds of ended ones, the history keeps at least
        self.history, self.history_s = HISTORY, HISTORY_S

    def new_id(self, serial: int) -> str:
        """The id of motion number `serial` (m<serial>-<8 hex>)."""
        self._next_serial = max(self._next_serial, serial + 1)
        return f"m{serial}-{uuid.uuid4().hex[:8]}"

    def get(self, motion_id: str) -> MotionRecord:
        rec = self._records.get(motion_id)
        if rec is None:
            gone = self._tombstones.get(motion_id)
            if gone is not None:
                status, code, created, ended = gone
                raise MotionExpired(
                    f"motion {motion_id} of {self.arm} has left the history (kept: the last "
                    f"{self.history} motions or those of the last {self.history_s:g} s); it was "
                    f"created "
                    f"at {_utc(created)} and ended {status}"
                    + (f" ({code})" if code else "") + (f" at {_utc(ended)}" if ended else ""))
            if self._issued(motion_id):
                raise MotionExpired(f"motion {motion_id} of {self.arm} has left the history "
                                    "long ago; nothing more is known about it")
            raise UnknownMotion(f"{self.arm} has no motion {motion_id!r}")
        return rec

    def _issued(self, motion_id: str) -> bool:
        """Whether this history handed out `motion_id` (ids are m<serial>-<8 hex>)."""
        head, _, tail = motion_id.partition("-")
        if not (head[:1] == "m" and head[1:].isdigit() and len(tail) == 8):
            return False
        return int(head[1:]) < self._next_serial

    def remember(self, rec: MotionRecord) -> None:
        """Add `rec` to the history; forget ended records beyond both the count and the age."""
        self._records[rec.id] = rec
        now = time.time()
        while len(self._records) > self.history:
            old = next(iter(self._records.values()))
            young = old.ended is None or now - old.ended < self.history_s
            if young and len(self._records) <= MAX_HISTORY:
                break
            del self._records[old.id]
            self._tombstones[old.id] = (old.status, old.code, old.created, old.ended)
            while len(self._tombstones) > TOMBSTONES:
                self._tombstones.popitem(last=False)


def _utc(t: float) -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(t))
