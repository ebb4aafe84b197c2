"""The classroom queue of each arm, and the hand-off between holders (API.md "Queue and
hand-off").

The control lease (app/classroom/lease.py) stays the mechanism; the queue drives it:

- when an arm's lease is free and nobody is handing off, the head of its queue is *offered* a
  lease (held for `claim_s` for its first renewal; only its owner sees the id);
- the first renewal claims it (`holding`): the slot then ends `slot_s` later, renewed or not;
- when a lease ends (released, lapsed, slot over, revoked, or an offer not claimed) the server
  hands off: it stops the arm, brings it to its profile's home pose at reduced speed, checks
  that it got there with no fault, and only then offers the next lease. A failed hand-off
  leaves the arm with nobody (`blocked`, with the reason, in GET /queue and a `handoff` event);
  an instructor's DELETE /lease tries the hand-off again.

While people wait, or a hand-off runs, a plain POST /lease answers 409 `leased`: the queue is
the way in.

A plain lease (taken while nobody waited) has no slot while nobody waits. Once someone waits, it
ends at most one slot after the moment the queue went from nobody waiting to someone waiting,
renewed or not (`LeaseManager.contest`); then the arm is handed off to the head of the queue as
between two queue slots. If nobody waits any more before then (they left, or an instructor
cleared the queue), the slot is lifted; a later join starts a new one. Why this rule: nobody
waits longer for a plain holder than for a queue holder whose slot has just begun (one slot);
the time the holder had while nobody waited cost nobody, so it is not charged; and a holder is
never cut off the moment someone joins, with no notice (counting the slot from when the lease
was taken would end a lease held longer than a slot at once).

The waiting entries of every arm are kept in the store and come back after a restart (an entry
offered or holding at the time comes back at the head, waiting: its lease died with the
process).
"""

from __future__ import annotations

import asyncio
import logging
import secrets
import time
from collections import OrderedDict
from collections.abc import Collection, Mapping
from dataclasses import dataclass, field
from typing import Any, Literal

from app import schemas as s
from app.classroom.handoff import handoff, home_pose, positions
from app.classroom.lease import LeaseManager
from app.errors import AlreadyQueued, Forbidden, InvalidOrder, UnknownEntry
from app.runtime.tasks import cancel_and_wait
from app.service import ArmService
from app.store import Store, StoreError
from app.web.security import Identity, Role

log = logging.getLogger(__name__)

EntryStatus = Literal["waiting", "offered", "holding", "done", "expired"]
#: Ended entries kept per arm for GET /queue/{id}.
HISTORY = 512
#: Ended entries kept across a restart per arm (so a client polling its entry learns the end).
PERSISTED_HISTORY = 100
SCOPE = "queue:{}"
KEY = "entries"


@dataclass
class Entry:
    id: str
    arm: str
    name: str
    created: float
    status: EntryStatus = "waiting"
    lease_id: str | None = None
    offered_until: float | None = None
    started: float | None = None
    slot_end: float | None = None
    ended: float | None = None
    reason: str | None = None

    @property
    def active(self) -> bool:
        return self.status in ("waiting", "offered", "holding")


@dataclass
class ArmQueue:
    arm: str
    entries: list[Entry] = field(default_factory=list)  # active ones, in order
    history: OrderedDict[str, Entry] = field(default_factory=OrderedDict)
    handing_off: bool = False
    blocked: str | None = None
    last_handoff: dict[str, Any] | None = None
    handoffs: int = 0
    task: asyncio.Task[None] | None = None
    again: bool = False  # another cycle was asked for while one ran
    needs_handoff: bool = False

    def current(self) -> Entry | None:
        for e in self.entries:
            if e.status in ("offered", "holding"):
                return e
        return None

    def waiting(self) -> list[Entry]:
        return [e for e in self.entries if e.status == "waiting"]


class Classroom:
    """The queues of every arm of one server."""

    def __init__(self, services: Mapping[str, ArmService], leases: LeaseManager,
                 store: Store | None, claim_s: float, slot_s: float) -> None:
        self._services = services
        self._leases = leases
        self._store = store
        self.claim_s = claim_s
        self.slot_s = slot_s
        self._queues: dict[str, ArmQueue] = {}
        leases.observers.append(self._on_lease)
        leases.gate = self._gate

    def queue(self, arm: str) -> ArmQueue:
        q = self._queues.get(arm)
        if q is None:
            q = self._queues[arm] = ArmQueue(arm)
        return q

    # ------------------------------------------------------------ life

    def load(self, names: Collection[str] | None = None) -> None:
        """The stored waiting entries of every arm (blocking: start-up, before serving).
        With `names` (the names the server's current tokens have; empty on an open server,
        which has no queue), an entry of any other name is dropped and logged: left by a
        server with other tokens, it would keep the arm offered to nobody, and every move
        answered 409 `leased` until its claim window ran out."""
        if self._store is None:
            return
        for arm in self._services:
            try:
                stored = self._store.get_setting_sync(SCOPE.format(arm), KEY) or []
            except StoreError as exc:
                log.error("%s: stored queue not read: %s", arm, exc)  # noqa: TRY400
                continue
            q = self.queue(arm)
            for item in stored:
                e = Entry(id=str(item["id"]), arm=arm, name=str(item["name"]),
                          created=float(item["created"]))
                if item.get("status") in ("done", "expired"):
                    e.status = item["status"]
                    e.reason, e.ended = item.get("reason"), item.get("ended")
                    e.started = item.get("started")
                    q.history[e.id] = e
                else:
                    q.entries.append(e)
            stale = [e for e in q.entries if names is not None and e.name not in names]
            for e in stale:
                self._end(q, e, "expired", "dropped at start-up: no current token has the "
                          f"name {e.name!r}" if names else "dropped at start-up: an open "
                          "server (no tokens) has no queue")
                log.warning("%s: stored queue entry %s of %r dropped: %s", arm, e.id, e.name,
                            e.reason)
            if stale:
                self._changed(q)
            if q.entries:
                log.info("%s: %d queued from the store", arm, len(q.entries))

    def queued_arms(self) -> list[str]:
        """The arms someone queues for (after `load`)."""
        return [arm for arm, q in self._queues.items() if q.entries]

    def start(self) -> None:
        """Offer the heads of the stored queues; where people wait, hand off first (the arm
        may be anywhere after a restart)."""
        for arm in self._services:
            self._kick(arm, handoff=bool(self.queue(arm).entries))

    async def close(self) -> None:
        for q in self._queues.values():
            await cancel_and_wait(q.task)
            q.task = None

    # ------------------------------------------------------------ requests

    def join(self, arm: str, who: Identity) -> s.QueueEntry:
        q = self.queue(arm)
        mine = [e for e in q.entries if e.name == who.name]
        if mine:
            raise AlreadyQueued(f"{who.name} is already in {arm}'s queue (entry {mine[0].id}, "
                                f"{mine[0].status})")
        e = Entry(id=secrets.token_hex(6), arm=arm, name=who.name, created=time.time())
        q.entries.append(e)
        self._changed(q)
        self._kick(arm, handoff=False)
        return self._entry(q, e, who)

    def get(self, arm: str, entry_id: str, who: Identity) -> s.QueueEntry:
        q = self.queue(arm)
        return self._entry(q, self._find(q, entry_id), who)

    async def leave(self, arm: str, entry_id: str, who: Identity) -> s.QueueEntry:
        q = self.queue(arm)
        e = self._find(q, entry_id)
        if e.name != who.name and who.role < Role.INSTRUCTOR:
            raise Forbidden(f"entry {entry_id} is {e.name}'s: only they or an instructor may "
                            "remove it")
        if not e.active:
            return self._entry(q, e, who)
        if e.status in ("offered", "holding") and e.lease_id is not None:
            # ends the lease: the observer records the entry and hands off
            e.reason = "left the queue" if e.name == who.name else f"removed by {who.name}"
            await self._leases.revoke(arm)
        else:
            self._end(q, e, "done", "left the queue" if e.name == who.name
                      else f"removed by {who.name}")
            self._changed(q)
        return self._entry(q, e, who)

    def reorder(self, arm: str, order: list[str], who: Identity) -> s.QueueStatus:
        q = self.queue(arm)
        waiting = q.waiting()
        if sorted(order) != sorted(e.id for e in waiting):
            raise InvalidOrder("order must name every waiting entry exactly once: "
                               f"{[e.id for e in waiting]}")
        by_id = {e.id: e for e in waiting}
        others = [e for e in q.entries if e.status != "waiting"]
        q.entries = others + [by_id[i] for i in order]
        self._changed(q)
        return self.status(arm, who)

    def clear(self, arm: str, who: Identity) -> s.QueueStatus:
        """Remove every waiting entry (the holder keeps their slot)."""
        q = self.queue(arm)
        for e in q.waiting():
            self._end(q, e, "expired", f"queue cleared by {who.name}")
        self._changed(q)
        return self.status(arm, who)

    async def revoke(self, arm: str, who: Identity) -> bool:
        """End the current lease (an instructor's call); with none and a failed hand-off, try
        the hand-off again. True if a lease was revoked."""
        q = self.queue(arm)
        cur = q.current()
        if cur is not None:
            cur.reason = f"revoked by {who.name}"
        lease_id = await self._leases.revoke(arm)
        if lease_id is None and q.blocked is not None:
            q.blocked = None
            self._kick(arm, handoff=True)
        return lease_id is not None

    def status(self, arm: str, who: Identity) -> s.QueueStatus:
        q = self.queue(arm)
        cur = q.current()
        lease = self._leases.held(arm)
        holder = None
        if cur is not None and cur.status == "holding":
            holder = cur.name
        elif lease is not None and cur is None:
            holder = "(a lease outside the queue)"
        return s.QueueStatus(
            arm=arm, holder=holder, slot_left=self._leases.slot_left(arm) if holder else None,
            entries=[self._entry(q, e, who) for e in q.entries],
            handing_off=q.handing_off, blocked=q.blocked, last_handoff=q.last_handoff,
            claim_s=self.claim_s, slot_s=self.slot_s)

    # ------------------------------------------------------------ the lease's side

    def _gate(self, arm: str) -> str | None:
        q = self.queue(arm)
        if q.handing_off:
            return f"{arm} is being handed off to the next in its queue"
        if q.blocked is not None:
            return (f"{arm}'s last hand-off failed ({q.blocked}); an instructor's DELETE "
                    f"/api/v1/arms/{arm}/lease tries it again")
        if q.waiting():
            return f"{len(q.waiting())} people are queued for {arm}: join its queue"
        return None

    def _on_lease(self, what: str, arm: str, lease_id: str) -> None:
        q = self.queue(arm)
        cur = q.current()
        mine = cur is not None and cur.lease_id == lease_id
        svc = self._services.get(arm)
        if what == "claimed":
            if mine and cur is not None:
                cur.status = "holding"
                cur.started = time.time()
                left = self._leases.slot_left(arm)
                cur.slot_end = None if left is None else time.time() + left
                if svc is not None:
                    svc.event("lease_granted", entry=cur.id, who=cur.name,
                              slot_end=cur.slot_end)
                self._changed(q)
            return
        # the lease ended: released, lapsed, slot_over, revoked
        if mine and cur is not None:
            status: EntryStatus = "done" if cur.status == "holding" else "expired"
            reason = cur.reason or {"released": "released", "lapsed": "not renewed in time",
                                    "slot_over": "slot over", "revoked": "revoked"}.get(what, what)
            if status == "expired" and what == "lapsed":
                reason = "offer not claimed in time"
            self._end(q, cur, status, reason)
            if svc is not None:
                svc.event("lease_ended", entry=cur.id, who=cur.name, reason=reason)
            self._changed(q)
            self._kick(arm, handoff=True)
        elif q.waiting():
            self._kick(arm, handoff=True)  # a lease outside the queue ended: hand off too

    # ------------------------------------------------------------ hand-off and offers

    def _kick(self, arm: str, handoff: bool) -> None:
        q = self.queue(arm)
        q.needs_handoff = q.needs_handoff or handoff
        if q.task is not None and not q.task.done():
            q.again = True
            return
        q.task = asyncio.get_running_loop().create_task(self._cycle(q), name=f"queue:{arm}")

    async def _cycle(self, q: ArmQueue) -> None:
        svc = self._services.get(q.arm)
        if svc is None:
            return
        while True:
            q.again = False
            try:
                if q.needs_handoff and q.blocked is None:
                    q.needs_handoff = False
                    await self._handoff(q, svc)
                if q.blocked is None and not q.needs_handoff:
                    await self._offer(q, svc)
            except Exception:  # keep the queue alive; the reason is logged
                log.exception("%s: queue cycle failed", q.arm)
            if not q.again:
                return

    async def _handoff(self, q: ArmQueue, svc: ArmService) -> None:
        q.handing_off = True
        try:
            why = await handoff(svc)
        finally:
            q.handing_off = False
        q.handoffs += 1
        q.last_handoff = {"ok": why is None, "reason": why, "time": time.time()}
        svc.event("handoff", ok=why is None, reason=why,
                  positions=positions(svc))
        if why is not None:
            q.blocked = why
            log.warning("%s: hand-off failed, the arm is left with nobody: %s", q.arm, why)
        self._changed(q, persist=False)

    async def _offer(self, q: ArmQueue, svc: ArmService) -> None:
        if q.current() is not None or self._leases.held(q.arm) is not None:
            return
        waiting = q.waiting()
        if not waiting:
            return
        head = waiting[0]
        lease = await self._leases.acquire(q.arm, claim_s=self.claim_s, slot_s=self.slot_s,
                                           gated=False)
        head.status = "offered"
        head.lease_id = lease.id
        head.offered_until = time.time() + self.claim_s
        svc.event("lease_offered", entry=head.id, who=head.name,
                  claim_until=head.offered_until)
        self._changed(q)

    # ------------------------------------------------------------ helpers

    def _find(self, q: ArmQueue, entry_id: str) -> Entry:
        for e in q.entries:
            if e.id == entry_id:
                return e
        e2 = q.history.get(entry_id)
        if e2 is None:
            raise UnknownEntry(f"{q.arm}'s queue has no entry {entry_id!r}")
        return e2

    def _end(self, q: ArmQueue, e: Entry, status: EntryStatus, reason: str) -> None:
        e.status = status
        e.reason = reason
        e.ended = time.time()
        e.lease_id = None
        if e in q.entries:
            q.entries.remove(e)
        q.history[e.id] = e
        while len(q.history) > HISTORY:
            q.history.popitem(last=False)

    def _entry(self, q: ArmQueue, e: Entry, who: Identity) -> s.QueueEntry:
        position = None
        if e.status == "waiting":
            position = 1 + q.waiting().index(e)
        elif e.status in ("offered", "holding"):
            position = 0
        return s.QueueEntry(id=e.id, arm=e.arm, name=e.name, position=position, status=e.status,
                            created=e.created,
                            lease_id=e.lease_id if e.status == "offered" and e.name == who.name
                            else None,
                            offered_until=e.offered_until if e.status == "offered" else None,
                            started=e.started, slot_end=e.slot_end, ended=e.ended,
                            reason=e.reason)

    def _slot_for_plain_lease(self, q: ArmQueue) -> None:
        """A lease outside the queue gets a slot once someone waits, and loses it when nobody
        does (the rule is in the module's docstring)."""
        if q.current() is not None:
            return  # the arm's lease is the queue's own: its slot is its claim's
        if q.waiting():
            self._leases.contest(q.arm, self.slot_s)
        else:
            self._leases.uncontest(q.arm)

    def _changed(self, q: ArmQueue, persist: bool = True) -> None:
        self._slot_for_plain_lease(q)
        svc = self._services.get(q.arm)
        if svc is not None:
            svc.event("queue", entries=[{"id": e.id, "who": e.name, "status": e.status}
                                        for e in q.entries],
                      handing_off=q.handing_off, blocked=q.blocked)
        if persist and self._store is not None:
            # every active entry, the current one first: after a restart it waits at the head
            rows = [{"id": e.id, "name": e.name, "created": e.created} for e in q.entries]
            rows += [{"id": e.id, "name": e.name, "created": e.created, "status": e.status,
                      "reason": e.reason, "started": e.started, "ended": e.ended}
                     for e in list(q.history.values())[-PERSISTED_HISTORY:]]
            self._store.put_setting_nowait(SCOPE.format(q.arm), KEY, rows)


__all__ = ["Classroom", "handoff", "home_pose"]
