"""A plain control lease outlives the process that holds it (app/classroom/lease.py): the
server, or in a lab the arm's worker, starts again on the same data folder and the lease is
there, its holder's renewal finds it and nobody else takes the arm meanwhile. Through the
real app and its store, started twice."""

from __future__ import annotations

import asyncio
import json
import sqlite3
import tempfile
import time

from conftest import make_settings, running_client

from app.classroom.lease import KEY, SCOPE
from app.store import Store

API = "/api/v1"
ARM = f"{API}/arms/rbe3001"
MOVE = ("POST", f"{ARM}/move/joints", {"positions": [0.1, 0.5, 0.3]})


async def test_a_lease_held_across_a_restart_stays_its_holders() -> None:
    settings = make_settings(data_dir=tempfile.mkdtemp(prefix="lease-"))
    async with running_client(settings) as (_app, c):
        r = await c.post(f"{ARM}/lease")
        assert r.status_code == 201, r.text
        lease = r.json()["id"]
    async with running_client(settings) as (_app, c):
        r = await c.request(*MOVE[:2], json=MOVE[2])
        assert r.status_code == 409 and r.json()["code"] == "leased", r.text
        r = await c.post(f"{ARM}/lease")
        assert r.status_code == 409 and r.json()["code"] == "leased", r.text
        r = await c.put(f"{ARM}/lease/{lease}")
        assert r.status_code == 200 and r.json()["id"] == lease, r.text
        assert r.json()["expires"] > time.time() + 0.5 * settings.lease_ttl_s
        r = await c.request(*MOVE[:2], json=MOVE[2], headers={"X-Arm-Lease": lease})
        assert r.status_code == 202, r.text
        r = await c.post(f"{ARM}/stop", headers={"X-Arm-Lease": lease})
        assert r.status_code == 200, r.text
        r = await c.delete(f"{ARM}/lease/{lease}")
        assert r.status_code == 204, r.text
    async with running_client(settings) as (_app, c):  # released: gone for good
        r = await c.put(f"{ARM}/lease/{lease}")
        assert r.status_code == 404 and r.json()["code"] == "unknown_lease", r.text
        r = await c.post(f"{ARM}/lease")
        assert r.status_code == 201, r.text


async def test_a_lease_that_lapsed_long_before_the_start_or_is_unreadable_is_not_restored(
        ) -> None:
    settings = make_settings(data_dir=tempfile.mkdtemp(prefix="lease-"))
    ttl = settings.lease_ttl_s
    store = Store(settings.data_dir)
    store.open()
    try:
        rows = {"rbe3001": {"id": "old", "ttl": ttl, "deadline": time.time() - 2 * ttl},
                "angler": [5]}
        for arm, row in rows.items():
            store.put_setting_nowait(SCOPE.format(arm), KEY, row).result()
    finally:
        store.close()
    async with running_client(settings) as (_app, c):
        for arm in rows:
            r = await c.post(f"{API}/arms/{arm}/lease")
            assert r.status_code == 201, (arm, r.text)
    store = Store(settings.data_dir)
    store.open()
    try:  # the new leases replaced them (a lease is not ended by a shutdown)
        for arm in rows:
            row = store.get_setting_sync(SCOPE.format(arm), KEY)
            assert isinstance(row["id"], str) and row["id"] not in ("old", "5"), (arm, row)
    finally:
        store.close()


async def test_a_lease_within_a_ttl_of_its_deadline_comes_back_with_a_ttl_to_renew() -> None:
    """The process was down while the holder's renewals met nothing: a lease whose deadline
    passed less than a ttl ago comes back, with one ttl from the start."""
    settings = make_settings(data_dir=tempfile.mkdtemp(prefix="lease-"))
    ttl = settings.lease_ttl_s
    store = Store(settings.data_dir)
    store.open()
    stored = time.time() - 0.5 * ttl
    try:
        store.put_setting_nowait(SCOPE.format("rbe3001"), KEY, {
            "id": "abc", "ttl": ttl, "deadline": stored}).result()
    finally:
        store.close()
    async with running_client(settings) as (app, c):
        held = app.state.leases.held("rbe3001")
        assert held is not None and held.id == "abc"
        assert held.expires > max(time.time(), stored + ttl)  # a ttl from the start
        r = await c.put(f"{ARM}/lease/abc")
        assert r.status_code == 200, r.text


async def test_a_lease_is_answered_once_its_record_is_on_disk() -> None:
    """A worker killed just after it answered a lease had lost it (its write still queued: a
    clean clone's loaded run of tests/test_lab_workers.py). With the store's writer held up
    0.3 s, the take, the renewal and the release each answer only once the database file
    says so, read from a connection of the test's own."""
    settings = make_settings(data_dir=tempfile.mkdtemp(prefix="lease-"))
    async with running_client(settings) as (app, c):
        store = app.state.store

        def on_disk() -> object:
            with sqlite3.connect(store.path) as db:
                row = db.execute("SELECT value FROM settings WHERE scope = ? AND key = ?",
                                 (SCOPE.format("rbe3001"), KEY)).fetchone()
            return None if row is None else json.loads(row[0])

        async def held_up(request):
            """The answer to `request` made while the writer is busy 0.3 s with another job,
            and what the file says as it comes."""
            blocker = asyncio.create_task(store.run(lambda _db: time.sleep(0.3)))
            await asyncio.sleep(0)
            r = await request
            row = on_disk()
            await blocker
            return r, row

        r, row = await held_up(c.post(f"{ARM}/lease"))
        assert r.status_code == 201, r.text
        lease = r.json()["id"]
        assert isinstance(row, dict) and row["id"] == lease, row
        deadline = row["deadline"]
        r, row = await held_up(c.put(f"{ARM}/lease/{lease}"))
        assert r.status_code == 200, r.text
        assert isinstance(row, dict) and row["deadline"] > deadline, row
        r, row = await held_up(c.delete(f"{ARM}/lease/{lease}"))
        assert r.status_code == 204, r.text
        assert row is None
