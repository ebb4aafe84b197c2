"""app.store: settings survive a reopen; a locked database, a full disk or a directory that
cannot be created is an error in health() and never a lost write (kept, answered by reads,
retried until it lands); the event loop keeps running while the writer waits on a lock. The
data folder is private (0700, files 0600); an older audit table is migrated, and a start record
a dead process left open is marked interrupted."""

from __future__ import annotations

import asyncio
import os
import sqlite3
import stat
from collections.abc import Iterator
from pathlib import Path

import pytest

from app.store import DB_NAME, INTERRUPTED, MIGRATIONS, Store


@pytest.fixture
def store(tmp_path: Path) -> Iterator[Store]:
    st = Store(tmp_path, retry_s=0.05, busy_timeout_s=0.05)
    st.open()
    yield st
    st.close()


async def test_round_trip_and_reopen(tmp_path: Path, store: Store) -> None:
    assert await store.get_setting("arm:a", "safety") is None
    assert await store.put_setting("arm:a", "safety", {"floor_z": 0.01, "zones": []}) is True
    assert await store.put_setting("arm:a", "safety", {"floor_z": 0.02, "zones": []}) is True
    assert await store.put_setting("arm:b", "safety", [1, 2]) is True
    store.close()
    again = Store(tmp_path)
    again.open()
    try:
        assert again.get_setting_sync("arm:a", "safety") == {"floor_z": 0.02, "zones": []}
        assert await again.get_setting("arm:b", "safety") == [1, 2]
        assert again.health().ok
    finally:
        again.close()
    rows = sqlite3.connect(tmp_path / DB_NAME).execute(
        "SELECT scope, key FROM settings ORDER BY scope").fetchall()
    assert rows == [("arm:a", "safety"), ("arm:b", "safety")]
    assert (sqlite3.connect(tmp_path / DB_NAME).execute("PRAGMA user_version").fetchone()[0]
            == len(MIGRATIONS))


async def test_locked_database_keeps_the_write_and_retries(tmp_path: Path, store: Store) -> None:
    other = sqlite3.connect(tmp_path / DB_NAME, isolation_level=None)
    other.execute("BEGIN EXCLUSIVE")
    ticks = 0

    async def ticker() -> None:
        nonlocal ticks
        while True:
            ticks += 1
            await asyncio.sleep(0)

    t = asyncio.create_task(ticker())
    try:
        saved = await store.put_setting("arm:a", "safety", {"v": 1})
    finally:
        t.cancel()
    assert saved is False
    assert ticks > 1, "the event loop stalled while the writer waited on the lock"
    h = store.health()
    assert not h.ok and h.pending == 1 and "locked" in (h.error or "")
    assert await store.get_setting("arm:a", "safety") == {"v": 1}  # not lost: answered
    other.execute("ROLLBACK")
    other.close()
    for _ in range(400):  # the writer retries on its own every retry_s
        if store.health().ok:
            break
        await asyncio.sleep(0.01)
    assert store.health().ok and store.health().pending == 0
    row = sqlite3.connect(tmp_path / DB_NAME).execute("SELECT value FROM settings").fetchone()
    assert row == ('{"v":1}',)


async def test_full_disk_is_an_error_in_health(tmp_path: Path) -> None:
    probe = Store(tmp_path / "probe")
    probe.open()
    probe.close()
    pages = sqlite3.connect(tmp_path / "probe" / DB_NAME).execute(
        "PRAGMA page_count").fetchone()[0]
    st = Store(tmp_path, max_pages=pages, retry_s=0.05)
    st.open()
    try:
        assert st.health().ok
        saved = await st.put_setting("arm:a", "big", "x" * 200_000)
        assert saved is False
        h = st.health()
        assert not h.ok and "full" in (h.error or "") and h.pending == 1
        assert await st.get_setting("arm:a", "big") == "x" * 200_000
    finally:
        st.close()


async def test_unusable_directory_is_an_error_not_a_crash(tmp_path: Path) -> None:
    blocker = tmp_path / "not-a-dir"
    blocker.write_text("a file where the data directory should be")
    st = Store(blocker / "data")
    st.open()
    try:
        h = st.health()
        assert not h.ok and "cannot open" in (h.error or "")
        assert await st.put_setting("s", "k", 1) is False
        assert await st.get_setting("s", "k") == 1
    finally:
        st.close()


async def test_run_uses_the_writer_connection(store: Store) -> None:
    await store.put_setting("s", "k", {"a": 1})
    rows = await store.run(lambda db: db.execute("SELECT scope, key, value FROM settings")
                           .fetchall())
    assert rows == [("s", "k", '{"a":1}')]
    with pytest.raises(sqlite3.OperationalError):
        await store.run(lambda db: db.execute("SELECT * FROM no_such_table").fetchall())
    assert store.health().ok  # a caller's bad statement is the caller's error


def _mode(path: Path) -> int:
    return stat.S_IMODE(path.stat().st_mode)


async def test_the_data_folder_is_0700_and_its_files_0600(tmp_path: Path) -> None:
    """Issue 22.12: the log names people and what they did. A new folder and database, and an
    old folder and database left open to others, are made private; -wal and -shm too."""
    old_umask = os.umask(0o022)  # a usual umask: files 0644, folders 0755 unless made private
    try:
        for folder in (tmp_path / "new" / "data", tmp_path / "old"):
            if folder.name == "old":
                folder.mkdir(mode=0o755)
                os.chmod(folder, 0o755)
                sqlite3.connect(folder / DB_NAME).close()  # 0644, as an earlier version made it
                assert _mode(folder / DB_NAME) == 0o644
            st = Store(folder, flush_s=0.01)
            st.open()
            try:
                assert await st.put_setting("s", "k", 1) is True
                st.audit((1.0, "alice", "operator", None, "POST", "/x", "", 200, None))
                for _ in range(500):
                    if st.health().pending == 0:
                        break
                    await asyncio.sleep(0.01)
                assert st.health().pending == 0
                names = sorted(p.name for p in folder.iterdir())
                assert names == sorted([DB_NAME, f"{DB_NAME}-wal", f"{DB_NAME}-shm"])
                assert {n: _mode(folder / n) for n in names} == dict.fromkeys(names, 0o600)
                assert _mode(folder) == 0o700
            finally:
                st.close()
    finally:
        os.umask(old_umask)


async def test_a_shared_sticky_folder_is_left_as_it_is(tmp_path: Path) -> None:
    shared = tmp_path / "shared"
    shared.mkdir()
    os.chmod(shared, 0o1777)
    st = Store(shared)
    st.open()
    try:
        assert st.health().ok
        assert _mode(shared) == 0o1777 and _mode(shared / DB_NAME) == 0o600
    finally:
        st.close()


async def test_an_audit_log_of_the_first_schema_is_kept_and_an_open_start_is_interrupted(
        tmp_path: Path) -> None:
    db = sqlite3.connect(tmp_path / DB_NAME, isolation_level=None)
    for i, sql in enumerate(MIGRATIONS[:3], start=1):  # the issue-14 schema
        db.execute(sql)
        db.execute(f"PRAGMA user_version={i}")
    db.execute("INSERT INTO audit (time, name, role, arm, method, route, summary, status, code)"
               " VALUES (5.0, 'alice', 'operator', 'angler', 'POST', '/s', '', 409, 'leased')")
    db.close()
    st = Store(tmp_path, flush_s=0.01)
    st.open()
    try:
        got = await st.query_audit()
        assert got == [{"time": 5.0, "name": "alice", "role": "operator", "arm": "angler",
                        "method": "POST", "route": "/s", "summary": "", "status": 409,
                        "code": "leased", "kind": "request", "count": 1, "ended": None,
                        "address": None}]
        st.audit((6.0, "bob", "operator", "angler", "POST", "/m", "", None, None))  # a start
        for _ in range(500):
            if st.health().pending == 0:
                break
            await asyncio.sleep(0.01)
        assert st.health().pending == 0
    finally:
        st._jobs.put(None)  # as a kill: no shutdown flush, the start is left open
        assert st._thread is not None
        st._thread.join(5.0)
    again = Store(tmp_path)
    again.open()
    try:
        got = await again.query_audit()
        assert [(r["time"], r["status"], r["code"]) for r in got] == [
            (6.0, None, INTERRUPTED), (5.0, 409, "leased")]
    finally:
        again.close()
    assert (sqlite3.connect(tmp_path / DB_NAME).execute("PRAGMA user_version").fetchone()[0]
            == len(MIGRATIONS))


async def test_audit_changes_made_while_the_database_is_locked_land_once_it_is_not(
        tmp_path: Path, store: Store) -> None:
    """A start record completed, another taken back, a written one completed and a written one
    taken back, all while writes fail: once the lock goes, the table says each last word."""
    written = store.audit((1.0, "alice", "operator", None, "POST", "/a", "", None, None))
    gone = store.audit((2.0, "alice", "operator", None, "POST", "/b", "", None, None))
    for _ in range(500):
        if store.health().pending == 0:
            break
        await asyncio.sleep(0.01)
    assert written.seq is not None and gone.seq is not None
    other = sqlite3.connect(tmp_path / DB_NAME, isolation_level=None)
    other.execute("BEGIN EXCLUSIVE")
    try:
        start = store.audit((3.0, "bob", "operator", None, "POST", "/c", "", None, None))
        never = store.audit((4.0, "bob", "operator", None, "POST", "/d", "", None, None))
        for _ in range(500):
            if not store.health().ok:
                break
            await asyncio.sleep(0.01)
        assert not store.health().ok  # the lock held a write back
        store.audit_update(start, status=200, ended=3.5)
        store.audit_cancel(never)
        store.audit_update(written, status=409, code="leased", ended=1.5)
        store.audit_cancel(gone)
        assert [(r["route"], r["status"]) for r in await store.query_audit()] == [
            ("/c", 200), ("/a", 409)]
    finally:
        other.execute("ROLLBACK")
        other.close()
    for _ in range(500):
        if store.health().ok and store.health().pending == 0:
            break
        await asyncio.sleep(0.01)
    assert store.health().pending == 0
    rows = sqlite3.connect(tmp_path / DB_NAME).execute(
        "SELECT route, status, code, ended FROM audit ORDER BY seq").fetchall()
    assert rows == [("/a", 409, "leased", 1.5), ("/c", 200, None, 3.5)]
