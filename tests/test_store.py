"""app.store: settings survive a reopen; a locked database, a full disk or a directory that
cannot be created is an error in health() and never a lost write (kept, answered by reads,
retried until it lands); the event loop keeps running while the writer waits on a lock."""

from __future__ import annotations

import asyncio
import sqlite3
from collections.abc import Iterator
from pathlib import Path

import pytest

from app.store import DB_NAME, MIGRATIONS, Store


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
