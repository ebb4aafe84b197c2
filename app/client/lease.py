"""The lease keeper of `AsyncArmClient.hold_lease` / `queue_turn`: while the block runs, the
lease id goes on the client's requests to the arm and a task renews it (every `ttl / 3` s
unless `every`); on exit the task stops and the lease is released."""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import AsyncIterator
from typing import Protocol

from app import schemas as s
from app.client.core import LeaseKeeper
from app.client.errors import ArmServerError

log = logging.getLogger(__name__)


class Leasing(Protocol):
    """What the keeper needs of a client."""

    leases: dict[str, str]

    async def renew_lease(self, arm: str, lease_id: str) -> s.Lease: ...

    async def release_lease(self, arm: str, lease_id: str) -> None: ...


@contextlib.asynccontextmanager
async def keep_lease(client: Leasing, arm: str, lease: s.Lease, every: float | None
                     ) -> AsyncIterator[LeaseKeeper]:
    keeper = LeaseKeeper(lease)
    previous = client.leases.get(arm)
    client.leases[arm] = lease.id
    period = every if every is not None else max(lease.ttl / 3.0, 0.05)

    async def beat() -> None:
        while True:
            await asyncio.sleep(period)
            try:
                keeper.lease = await client.renew_lease(arm, lease.id)
                keeper.renewals += 1
            except ArmServerError as exc:
                keeper.error = exc
                log.warning("%s: lease %s not renewed: %s", arm, lease.id, exc)
                if exc.status != 0:
                    return

    task = asyncio.create_task(beat(), name=f"lease:{arm}")
    try:
        yield keeper
    finally:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task
        if previous is None:
            client.leases.pop(arm, None)
        else:
            client.leases[arm] = previous
        with contextlib.suppress(ArmServerError):
            await client.release_lease(arm, lease.id)
