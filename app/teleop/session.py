"""One teleoperation session: every 1/rate s, the leader's newest sample, mapped to a follower
target (app/teleop/mapping.py), stepped towards at the follower's speed limit and sent
through the follower's facade (`ArmService.command_setpoint`: the guard, the envelope, the
latch, the one commanded state). It runs as a task on the follower's control loop, the loop
that owns the follower's commands, and reads the leader through its telemetry subscription
(`ArmService.subscribe`; the hub's log is locked, no crossing needed).

A real leader (not simulated) is moved by hand: its torque is off for the session
(`ArmService.set_torque`) and on again, holding where it is, when the session ends; so is a
simulated one started with `free_leader`, moved by the hand in its world (app/sim/hand.py).

A tick sends nothing, and counts a hold, when the leader's newest sample is older than the
deadman time or stale, when its pose has no follower target, or when the follower refuses the
setpoint (a keep-out zone, a joint limit, a planned motion running on it, a lost link): the
follower holds its last command, and the session goes on. The emergency stop on either arm
ends the session (the follower's estop holds it; after the leader's, the follower is told to
hold where it is), as do a stop request on the follower (POST /arms/{arm}/stop) and `stop`
(DELETE): the follower holds where it is.
"""

from __future__ import annotations

import asyncio
import logging
import time
from typing import Any, Literal

import numpy as np
import orjson

from app import schemas as s
from app.errors import ArmError
from app.runtime.tasks import cancel_and_wait
from app.service import ArmService
from app.teleop.latency import TeleopStats
from app.teleop.leader import Leader
from app.teleop.mapping import Mapping, NoTarget, step_towards

log = logging.getLogger(__name__)

#: The longest time one tick's step may cover, s: the executor's MAX_STEP_S (a late tick does
#: not make the follower jump to catch up).
MAX_STEP_S = 0.03
#: The fraction of the follower's speed limit a step may use: the guard measures the time
#: since the last command from when it was written, a little after this loop's clock.
STEP_SHARE = 0.9
#: Samples the leader's subscription keeps (only the newest is read each tick): more than a
#: tick's worth at the slowest rate and the fastest poll (500 Hz / 30 Hz), so no sample is
#: counted as dropped in the leader's telemetry figures.
BACKLOG = 256


class TeleopSession:
    """A leader driving a follower at `rate_hz`; built on any thread, run on the follower's
    control loop (`start`, `stop` are called there)."""

    def __init__(self, sid: str, leader: Leader, follower: ArmService, rate_hz: float,
                 mapping_name: Literal["joints", "tip"], mapping: Mapping,
                 deadman_s: float, free_leader: bool = False) -> None:
        self.id = sid
        self.leader = leader
        self.follower = follower
        self.rate_hz = rate_hz
        self.mapping_name = mapping_name
        self.mapping = mapping
        self.deadman_s = deadman_s
        #: The leader's torque was switched off for the session (a real arm moved by hand):
        #: on again, holding where it is, when the session ends.
        self.free_leader = free_leader
        self._freed = free_leader  # as started (free_leader is cleared when given back)
        self.stats = TeleopStats()
        self.status: Literal["running", "ended"] = "running"
        self.reason: str | None = None
        self.last_refusal: str | None = None
        #: Why the last tick held the follower (`deadman`, `no_target`, `refused:<code>`),
        #: None while it follows.
        self.held: str | None = None
        self.started = time.time()
        self.ended: float | None = None
        self._task: asyncio.Task[None] | None = None
        k = follower.profile.tracking_margin * follower.safety_settings.speed_override
        #: The follower's speed per joint a step may take, rad/s or m/s.
        self._speed = np.asarray(follower.model.vmax, dtype=float) * k * STEP_SHARE

    # --------------------------------------------------------- on the follower's loop

    async def start(self) -> None:
        self._task = asyncio.create_task(self._run(), name=f"teleop:{self.id}")

    async def stop(self, reason: str) -> None:
        """End the session and hold the follower where it is (unless a planned motion has the
        follower, or its estop holds it already)."""
        if self.status != "running":
            return
        self._end(reason)
        await cancel_and_wait(self._task)
        await self._hold()

    async def _hold(self) -> None:
        """At the end: the follower holds where it is, and a leader freed for the session has
        its torque again, holding where the hand left it."""
        if self.free_leader:
            self.free_leader = False
            try:
                await self.leader.set_torque(True)
            except ArmError as exc:
                log.warning("teleop %s: could not switch %s's torque on again: %s", self.id,
                            self.leader.name, exc.detail)
        if self.follower.estop or self.follower.moving:
            return
        try:
            await self.follower.emergency_hold()
        except ArmError as exc:
            log.warning("teleop %s: could not hold %s: %s", self.id, self.follower.name,
                        exc.detail)

    def _end(self, reason: str) -> None:
        if self.status == "running":
            self.status, self.reason, self.ended = "ended", reason, time.time()
            log.info("teleop %s (%s -> %s) ended: %s", self.id, self.leader.name,
                     self.follower.name, reason)
            self.follower.event("teleop_ended", id=self.id, reason=reason)

    async def _run(self) -> None:
        sub = self.leader.subscribe(BACKLOG)
        try:
            await self._loop(sub)
        except asyncio.CancelledError:
            raise
        except Exception:  # a bug ends this session, never the control loop
            log.exception("teleop %s crashed", self.id)
            self._end("internal error (logged)")
            await self._hold()
        finally:
            sub.close()

    async def _loop(self, sub: Any) -> None:
        loop = asyncio.get_running_loop()
        period = 1.0 / self.rate_hz
        due = loop.time()
        stops = self.follower.stops
        latest: dict[str, Any] | None = (None if sub.initial is None
                                          else orjson.loads(sub.initial))
        last: np.ndarray | None = None
        last_at = loop.time() - period
        while self.status == "running":
            which = [a.name for a in (self.leader, self.follower) if a.estop]
            if which:
                self._end(f"emergency stop on {' and '.join(which)}")
                await self._hold()
                return
            if self.follower.stops != stops:  # POST /arms/{follower}/stop
                self._end(f"{self.follower.name} stopped (POST /stop)")
                await self._hold()
                return
            samples, _events, _dropped = sub.take()
            if samples:
                latest = orjson.loads(samples[-1])  # the newest only
            now = loop.time()
            target = self._target(latest)
            if target is None or latest is None:
                self.held = self._why_held(latest)
                self.stats.hold(now)
            else:
                if last is None:
                    here = self.follower.positions
                    last = None if here is None else np.asarray(here, dtype=float)
                if last is None:
                    self.held = "no_target"
                    self.stats.hold(now)
                else:
                    cap = self._speed * min(max(now - last_at, 0.0), MAX_STEP_S)
                    q = step_towards(last, target, cap)
                    try:
                        await self.follower.command_setpoint(q)
                    except ArmError as exc:
                        self.last_refusal = exc.code
                        self.held = f"refused:{exc.code}"
                        self.stats.hold(loop.time())
                    else:
                        self.held = None
                        last, last_at = q, loop.time()
                        self.stats.command(last_at, time.time() - float(latest["time"]))
            due += period
            wait = due - loop.time()
            if wait < -period:  # held up: skip the missed ticks, never a burst
                due, wait = loop.time(), 0.0
            await asyncio.sleep(max(0.0, wait))

    def _target(self, latest: dict[str, Any] | None) -> np.ndarray | None:
        """The follower's target from the leader's newest sample, or None (hold): no sample,
        a stale one, or one older than the deadman time; a pose with no follower target."""
        if latest is None or latest.get("stale") or latest.get("positions") is None:
            return None
        if time.time() - float(latest["time"]) > self.deadman_s:
            return None
        here = self.follower.positions
        if here is None:
            return None
        try:
            return self.mapping.target(np.asarray(latest["positions"], dtype=float), here)
        except NoTarget:
            return None

    def _why_held(self, latest: dict[str, Any] | None) -> str:
        """Why `_target` gave nothing: `deadman` (no leader sample, a stale one or one older
        than the deadman time) or `no_target` (the pose maps to no follower target)."""
        if latest is None or latest.get("stale") or latest.get("positions") is None:
            return "deadman"
        if time.time() - float(latest["time"]) > self.deadman_s:
            return "deadman"
        return "no_target"

    # --------------------------------------------------------- reading (any thread)

    def describe(self) -> s.TeleopSession:
        lat = self.stats.latency_ms()
        return s.TeleopSession(
            id=self.id, leader=self.leader.name, follower=self.follower.name,
            rate_hz=self.rate_hz, mapping=self.mapping_name,
            deadman_s=self.deadman_s,
            free_leader=self.free_leader or self._freed,
            achieved_hz=round(self.stats.achieved_hz(), 3) if self.status == "running" else 0.0,
            latency_ms=None if lat is None else s.TeleopLatency(p50=round(lat[0], 3),
                                                                p99=round(lat[1], 3)),
            commands=self.stats.commands, holds=self.stats.holds,
            status=self.status,
            reason=self.reason, last_refusal=self.last_refusal,
            held=self.held if self.status == "running" else None, started=self.started,
            ended=self.ended)
