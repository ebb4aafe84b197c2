"""The server's teleoperation sessions: started, listed and stopped here (the routes call
this), each run on its follower's control loop (app/teleop/session.py).

A session runs under the lease it was started with: a watcher on this (the HTTP) loop asks
the lease manager every LEASE_CHECK_S whether that lease would still be let through on the
follower, and stops the session when another client's lease (or the classroom's hand-off)
holds the arm now."""

from __future__ import annotations

import asyncio
import itertools
import logging
import uuid
from collections import OrderedDict
from dataclasses import dataclass

from app import schemas as s
from app.classroom.lease import LeaseManager
from app.errors import Busy, EstopLatched, InvalidRequest, Leased, NotFound
from app.runtime.control_thread import on_home
from app.runtime.tasks import cancel_and_wait
from app.safety.falling import falling_refusal
from app.service import ArmService
from app.teleop.config import TeleopPair, with_pair
from app.teleop.leader import Leader
from app.teleop.mapping import Mapping, joint_map, tip_map
from app.teleop.session import TeleopSession

log = logging.getLogger(__name__)

#: Ended sessions kept for GET (with their figures and why they ended).
KEEP_ENDED = 16
#: How often the watcher asks whether each session's lease still holds its follower, s.
LEASE_CHECK_S = 0.25


@dataclass(frozen=True)
class LeaseRef:
    """The lease a session was started under: its id (None: none was held) and whether the
    classroom's hand-off gate applies (everyone but an instructor)."""

    lease_id: str | None
    gated: bool


def frees_leader(req: s.TeleopStart, leader: Leader) -> bool:
    """Whether the session switches the leader's torque off (to be moved by hand): as asked,
    else for a real leader (not simulated)."""
    if req.free_leader is not None:
        return req.free_leader
    return leader.link_status().kind != "sim"


class TeleopSessions:
    """Every session of one server, by id; running and the last KEEP_ENDED ended ones."""

    def __init__(self, leases: LeaseManager, pairs: list[TeleopPair] | None = None) -> None:
        #: The config's per-pair defaults (`[[teleop]]`, app/teleop/config.py).
        self._pairs = list(pairs or [])
        self._sessions: OrderedDict[str, TeleopSession] = OrderedDict()
        self._ids = itertools.count(1)
        self._leases = leases
        self._held: dict[str, LeaseRef] = {}
        self._watcher: asyncio.Task[None] | None = None
        #: One start at a time: two requests for one follower must not both pass the check.
        self._starting = asyncio.Lock()

    def list(self) -> list[s.TeleopSession]:
        return [t.describe() for t in list(self._sessions.values())]

    def running_with(self, arm: str) -> TeleopSession | None:
        """The running session `arm` leads or follows, if any."""
        return next((t for t in self._sessions.values() if t.status == "running"
                     and arm in (t.leader.name, t.follower.name)), None)

    def get(self, sid: str) -> TeleopSession:
        t = self._sessions.get(sid)
        if t is None:
            raise NotFound(f"no teleoperation session {sid!r} (GET /api/v1/teleop lists them)")
        return t

    async def start(self, req: s.TeleopStart, leader: Leader, follower: ArmService,
                    lease: LeaseRef) -> TeleopSession:
        """Check and start a session (the caller checked the follower's `lease`). 422 for a
        leader that is the follower or a mapping that does not fit the arms; 409 `busy` for
        a follower another session drives; 409 `estop_latched` for either arm latched; 409
        `not_supported` for a real leader whose device cannot switch its torque off (a
        real leader's torque is off for the session, on again when it ends); 409 `in_use`
        for a leader so freed whose joints fall without torque, unless `load_supported`; the
        follower's own refusals (shutdown) as they are."""
        async with self._starting:
            return await self._start(with_pair(req, self._pairs), leader, follower, lease)

    async def _start(self, req: s.TeleopStart, leader: Leader, follower: ArmService,
                     lease: LeaseRef) -> TeleopSession:
        if leader is follower:
            raise InvalidRequest(f"the leader and the follower are both {leader.name}: an arm "
                                 "cannot follow itself")
        for t in self._sessions.values():
            if t.status == "running" and t.follower is follower:
                raise Busy(f"{follower.name} already follows {t.leader.name} (teleoperation "
                           f"session {t.id}): stop it first (DELETE /api/v1/teleop/{t.id})")
        follower.require_motion_allowed()
        follower.require_torque()
        if leader.estop:  # the session would end at its first tick
            raise EstopLatched(f"{leader.name}'s emergency stop is latched: a leader under "
                               f"estop drives nothing (DELETE /api/v1/arms/{leader.name}/estop)")
        mapping = self._mapping(req, leader, follower)
        # a real leader is moved by hand: its torque off for the session (409 not_supported
        # where its device cannot); a simulated one is moved by its own commands, or by a
        # hand in its world when asked (free_leader)
        free = frees_leader(req, leader)
        falls = leader.profile.falling_joints if free else []
        if falls and not req.load_supported:
            raise falling_refusal(leader.name, falls, "the session",
                                  '; or {"free_leader": false} for a leader moved by its own '
                                  "commands")
        if free:
            await leader.set_torque(False)
        sid = f"t{next(self._ids)}-{uuid.uuid4().hex[:8]}"
        session = TeleopSession(sid, leader, follower, req.rate_hz, req.mapping, mapping,
                                req.deadman_s, free_leader=free)
        try:
            await on_home(follower.home_loop, session.start)
        except BaseException:
            if free:
                await leader.set_torque(True)
            raise
        self._sessions[sid] = session
        self._held[sid] = lease
        self._forget_ended()
        if self._watcher is None or self._watcher.done():
            self._watcher = asyncio.create_task(self._watch(), name="teleop:leases")
        return session

    async def _watch(self) -> None:
        """Stop each session whose follower another lease holds now; ends with the last."""
        while True:
            running = [t for t in self._sessions.values() if t.status == "running"]
            if not running:
                return
            for t in running:
                ref = self._held.get(t.id, LeaseRef(None, True))
                try:
                    await self._leases.check(t.follower.name, ref.lease_id, ref.gated)
                except Leased:
                    await self.stop(t.id, "the follower's lease is another client's now")
                except Exception:  # a bug here must not leave sessions unwatched silently
                    log.exception("teleop %s: lease check failed", t.id)
            await asyncio.sleep(LEASE_CHECK_S)

    @staticmethod
    def _mapping(req: s.TeleopStart, leader: Leader, follower: ArmService) -> Mapping:
        if req.mapping == "joints":
            return joint_map(leader.model, follower.model, req.scale, req.offset,
                             req.clamp_margin)
        return tip_map(leader.model, follower.model, req.tip_scale, req.tip_offset,
                       req.clamp_margin)

    async def stop(self, sid: str, reason: str) -> TeleopSession:
        t = self.get(sid)
        await on_home(t.follower.home_loop, lambda: t.stop(reason))
        return t

    async def close(self) -> None:
        """Stop every running session (server shutdown), each follower holding."""
        await cancel_and_wait(self._watcher)
        for t in list(self._sessions.values()):
            await self.stop(t.id, "server shutting down")

    def _forget_ended(self) -> None:
        ended = [k for k, t in self._sessions.items() if t.status != "running"]
        for k in ended[:max(0, len(ended) - KEEP_ENDED)]:
            del self._sessions[k]
            self._held.pop(k, None)
