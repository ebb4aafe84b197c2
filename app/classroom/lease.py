"""Control leases: one client at a time may move an arm (API.md, "Control lease").

A lease is a bearer capability: whoever presents its id in `X-Arm-Lease` holds it. While one
is held on an arm, requests that move it or send protocol commands without that id get 409
`leased`; the emergency stop stays open to every authenticated client. A lease not renewed
within its ttl lapses: the arm is brought to a controlled stop (`ArmService.stop`), a
`lease_expired` event goes to telemetry subscribers, and the lease is gone.

A lease taken while nobody queued for the arm (a plain lease) has no slot until someone waits:
then the classroom queue gives it one (`contest`), ending `slot_s` after that moment, renewed or
not, and lifts it (`uncontest`) if nobody waits any more before it ends (app/classroom/queue.py has
the rule and why).

A lapsed lease is expired by whichever comes first: the watcher task (which wakes at the
earliest expiry) or the next request that looks at it, so a request can never slip a motion in
between the expiry and its stop.

A plain lease is kept in the store (`SCOPE`: its id, ttl and deadline, as each take, renewal
and end changes them) and comes back when the server, or in a lab the arm's worker process,
starts again (`load`): its holder's next renewal finds it, and nobody else takes the arm
meanwhile. It comes back with one ttl to be renewed in (the process was down for a while, and
renewals met nothing), unless it had lapsed more than a ttl before the start. A lease of the
classroom queue is not kept: the queue's entries are, and the queue offers the arm again
(app/classroom/queue.py); nor a plain lease on an arm people queue for. A take, a renewal and
a release are answered once their record is on disk (as an estop press is; a disk that holds
it over `LATCH_SAVE_WAIT_S` does not hold the answer back): a worker killed just after
answering a lease had lost it, its write still queued (a clean clone's loaded run).
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import hmac
import logging
import secrets
import time
from collections.abc import Callable, Collection, Mapping
from dataclasses import dataclass

from app import schemas as s
from app.errors import ArmError, Leased, UnknownLease
from app.runtime.tasks import cancel_and_wait
from app.service import ArmService
from app.store import Store, StoreError, saved_within

log = logging.getLogger(__name__)

#: The store's scope of an arm's plain lease (key `KEY`).
SCOPE = "lease:{}"
KEY = "lease"


@dataclass
class _Lease:
    id: str
    arm: str
    ttl: float
    deadline: float  # loop-independent monotonic time, s
    #: A lease from the classroom queue ends here, renewed or not (monotonic, s).
    slot_end: float | None = None
    #: Offered by the queue and not yet claimed (claimed on its first renewal).
    offered: bool = False
    #: The slot's length: it starts when the lease is taken, or claimed if it was offered.
    slot_s: float | None = None
    #: A plain lease (taken outside the queue) whose `slot_end` was set because people wait.
    contested: bool = False

    def expired(self, now: float) -> bool:
        return now >= self.deadline

    def expires(self) -> float:
        """The deadline in wall-clock time (`time.time()`), s."""
        return time.time() + (self.deadline - time.monotonic())

    def to_schema(self) -> s.Lease:
        return s.Lease(id=self.id, arm=self.arm, expires=self.expires(), ttl=self.ttl)


class LeaseManager:
    """The leases of every arm of one server, and the watcher that expires them."""

    def __init__(self, services: Mapping[str, ArmService], ttl: float,
                 store: Store | None = None) -> None:
        self._services = services
        self.ttl = ttl
        self._store = store
        #: Arms with a row in the store (`_save`, `load`): only they need a None written.
        self._stored: set[str] = set()
        self._leases: dict[str, _Lease] = {}
        self._changed = asyncio.Event()
        self._task: asyncio.Task[None] | None = None
        #: Called with (what, arm, lease id) on "claimed", "released", "lapsed", "slot_over",
        #: "revoked" (the classroom queue, app/classroom/queue.py, drives hand-offs from these).
        self.observers: list[Callable[[str, str, str], None]] = []
        #: Says why a plain POST /lease must wait (e.g. people are queued), else None.
        self.gate: Callable[[str], str | None] | None = None

    def _notify(self, what: str, arm: str, lease_id: str) -> None:
        for fn in self.observers:
            try:
                fn(what, arm, lease_id)
            except Exception:  # an observer's bug must not break the lease
                log.exception("%s: lease observer failed on %s", arm, what)

    def start(self) -> None:
        if self._task is None:
            self._task = asyncio.create_task(self._watch(), name="lease-watcher")

    async def close(self) -> None:
        await cancel_and_wait(self._task)
        self._task = None

    # ------------------------------------------------------------ requests

    def held(self, arm: str) -> s.Lease | None:
        lease = self._leases.get(arm)
        return None if lease is None else lease.to_schema()

    async def acquire(self, arm: str, *, claim_s: float | None = None,
                      slot_s: float | None = None, gated: bool = True) -> s.Lease:
        """Take the arm's lease. With `claim_s`: an offer (the queue's), held that long for its
        first renewal; with `slot_s`: it ends that long from now even if renewed."""
        await self._expire_if_due(arm)
        if arm in self._leases:
            raise Leased(f"{arm} is leased by another client; wait for it to be released or "
                         "to lapse, or latch the emergency stop")
        why = self.gate(arm) if gated and self.gate is not None else None
        if why is not None:
            raise Leased(why)
        now = time.monotonic()
        slot_end = None if slot_s is None or claim_s is not None else now + slot_s
        deadline = now + (self.ttl if claim_s is None else claim_s)
        lease = _Lease(secrets.token_urlsafe(16), arm, self.ttl,
                       deadline if slot_end is None else min(deadline, slot_end), slot_end,
                       offered=claim_s is not None, slot_s=slot_s)
        self._leases[arm] = lease
        self._changed.set()
        saved = self._save(arm)
        log.info("%s: lease taken (ttl %.1f s)", arm, self.ttl)
        out = lease.to_schema()
        await saved_within(saved)
        return out

    async def renew(self, arm: str, lease_id: str) -> s.Lease:
        lease = await self._find(arm, lease_id)
        now = time.monotonic()
        if lease.offered and lease.slot_s is not None:
            lease.slot_end = now + lease.slot_s
        lease.deadline = now + lease.ttl
        if lease.slot_end is not None:
            lease.deadline = min(lease.deadline, lease.slot_end)
        self._changed.set()
        saved = self._save(arm)
        if lease.offered:
            lease.offered = False
            self._notify("claimed", arm, lease.id)
        out = lease.to_schema()
        await saved_within(saved)
        return out

    async def release(self, arm: str, lease_id: str) -> None:
        lease = await self._find(arm, lease_id)
        del self._leases[lease.arm]
        self._changed.set()
        saved = self._save(arm)
        log.info("%s: lease released", arm)
        self._notify("released", arm, lease.id)
        await saved_within(saved)

    async def revoke(self, arm: str) -> str | None:
        """End the arm's lease whoever holds it (an instructor's call): stop the arm, send
        `lease_expired`; the id of the revoked lease, None if there was none."""
        await self._expire_if_due(arm)
        lease = self._leases.get(arm)
        if lease is None:
            return None
        await self._expire(lease, "revoked")
        return lease.id

    def slot_left(self, arm: str) -> float | None:
        """Seconds left in the held lease's slot, None without a slot."""
        lease = self._leases.get(arm)
        if lease is None or lease.slot_end is None:
            return None
        return max(0.0, lease.slot_end - time.monotonic())

    def contest(self, arm: str, slot_s: float) -> bool:
        """People wait for `arm`: its plain lease (taken outside the queue, with no slot) ends
        `slot_s` from now, renewed or not. A lease that has a slot already (the queue's, or a
        plain one contested before) keeps it. True if a slot was set now."""
        lease = self._leases.get(arm)
        if lease is None or lease.offered or lease.slot_s is not None or lease.contested:
            return False
        lease.slot_end = time.monotonic() + slot_s
        lease.deadline = min(lease.deadline, lease.slot_end)
        lease.contested = True
        self._changed.set()
        log.info("%s: people wait: the lease outside the queue ends in %.1f s", arm, slot_s)
        return True

    def uncontest(self, arm: str) -> bool:
        """Nobody waits for `arm` any more: a plain lease's slot from `contest` is lifted (its
        next renewal gives it the full ttl again). True if a slot was lifted."""
        lease = self._leases.get(arm)
        if lease is None or not lease.contested:
            return False
        lease.slot_end = None
        lease.contested = False
        self._changed.set()
        log.info("%s: nobody waits: the lease outside the queue has no slot again", arm)
        return True

    def offered(self, arm: str) -> bool:
        lease = self._leases.get(arm)
        return lease is not None and lease.offered

    async def check(self, arm: str, lease_id: str | None, gated: bool = True) -> None:
        """Let a request that moves `arm` through, or 409 `leased` if another holds it (or,
        with `gated`, while the classroom queue says the arm is nobody's: hand-off)."""
        await self._expire_if_due(arm)
        lease = self._leases.get(arm)
        if lease is None:
            why = self.gate(arm) if gated and self.gate is not None else None
            if why is not None:  # a hand-off runs, or failed, or people wait for their offer
                raise Leased(why)
            return
        if lease_id is None or not hmac.compare_digest(lease_id.encode(), lease.id.encode()):
            raise Leased(f"{arm} is leased: send the lease id in the X-Arm-Lease header "
                         "(only the emergency stop is open without it)")

    # ------------------------------------------------------------ across restarts

    def _save(self, arm: str) -> concurrent.futures.Future[bool] | None:
        """Keep `arm`'s plain lease in the store (None once it is gone, or the queue's): the
        write's future (`saved_within`), or None where nothing is written."""
        if self._store is None:
            return None
        lease = self._leases.get(arm)
        row = None
        if lease is not None and not lease.offered and lease.slot_s is None:
            row = {"id": lease.id, "ttl": lease.ttl, "deadline": lease.expires()}
            self._stored.add(arm)
        elif arm in self._stored:
            self._stored.discard(arm)
        else:
            return None  # nothing kept for it: the queue's lease renewed, nothing to write
        return self._store.put_setting_nowait(SCOPE.format(arm), KEY, row)

    def load(self, skip: Collection[str] = ()) -> None:
        """The plain leases kept in the store (blocking: start-up, before serving), each
        with one ttl from now, but for an arm in `skip` (people queue for it: the queue
        offers it) and a lease that lapsed more than its ttl before now."""
        if self._store is None:
            return
        now = time.time()
        for arm in self._services:
            try:
                row = self._store.get_setting_sync(SCOPE.format(arm), KEY)
            except StoreError as exc:
                log.error("%s: stored lease not read: %s", arm, exc)  # noqa: TRY400
                continue
            if row is None or arm in self._leases:
                continue
            self._stored.add(arm)
            try:
                lease_id, ttl, deadline = str(row["id"]), float(row["ttl"]), float(row["deadline"])
            except (KeyError, TypeError, ValueError):
                log.warning("%s: stored lease %r not understood: dropped", arm, row)
                self._save(arm)
                continue
            if arm in skip or deadline < now - ttl:
                why = "people queue for the arm" if arm in skip else "it had lapsed"
                log.info("%s: stored lease not restored (%s)", arm, why)
                self._save(arm)
                continue
            self._leases[arm] = _Lease(lease_id, arm, ttl, time.monotonic() + ttl)
            self._save(arm)
            log.info("%s: lease restored from the store (renew within %.1f s)", arm, ttl)
        self._changed.set()

    # ------------------------------------------------------------ expiry

    async def _find(self, arm: str, lease_id: str) -> _Lease:
        await self._expire_if_due(arm)
        lease = self._leases.get(arm)
        if lease is None or not hmac.compare_digest(lease_id.encode(), lease.id.encode()):
            raise UnknownLease(f"no lease {lease_id!r} on {arm} (released, lapsed or never "
                               "taken)")
        return lease

    async def _expire_if_due(self, arm: str) -> None:
        lease = self._leases.get(arm)
        if lease is not None and lease.expired(time.monotonic()):
            await self._expire(lease)

    async def _expire(self, lease: _Lease, why: str | None = None) -> None:
        if self._leases.get(lease.arm) is not lease:
            return  # released or expired meanwhile
        if why is None:
            at_end = lease.slot_end is not None and time.monotonic() >= lease.slot_end
            why = "slot_over" if at_end else "lapsed"
        del self._leases[lease.arm]
        self._save(lease.arm)
        svc = self._services.get(lease.arm)
        if why == "slot_over":
            what = f"the lease on {lease.arm} reached the end of its slot"
        elif why == "revoked":
            what = f"the lease on {lease.arm} was revoked"
        else:
            what = f"the lease on {lease.arm} lapsed (not renewed within {lease.ttl:g} s)"
        log.warning("%s: stopping the arm", what)
        stopped: list[str] = []
        if svc is not None:
            try:
                stopped = (await svc.stop(f"stopped: {what}")).stopped
            except ArmError as exc:  # stop failed on the device: still report the lapse
                log.warning("%s: stop after lease lapse failed: %s", lease.arm, exc.detail)
            svc.event("lease_expired", lease=lease.id, stopped=stopped, reason=why)
        self._notify(why, lease.arm, lease.id)

    async def _watch(self) -> None:
        while True:
            self._changed.clear()
            now = time.monotonic()
            for lease in list(self._leases.values()):
                if lease.expired(now):
                    try:
                        await self._expire(lease)
                    except Exception:  # keep watching the other arms' leases
                        log.exception("%s: expiring the lease failed", lease.arm)
            deadlines = [lease.deadline for lease in self._leases.values()]
            timeout = None if not deadlines else max(0.0, min(deadlines) - time.monotonic())
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(timeout):  # not wait_for: on 3.11 it can lose a cancel
                    await self._changed.wait()
