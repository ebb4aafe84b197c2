"""Issue 22.8: the audit log is bounded on disk (ARMSERVER_AUDIT_MAX_ROWS: the oldest rows go)
and in memory while the disk refuses it (the oldest unsaved records go, counted: in health()
while the disk is full, as a `dropped` record once it takes writes again)."""

from __future__ import annotations

import sqlite3
from pathlib import Path

from app.store import DB_NAME, Store
from tests.conftest import make_settings, running_client
from tests.test_classroom import until


def count(data_dir: Path) -> int:
    db = sqlite3.connect(data_dir / DB_NAME)
    try:
        return int(db.execute("SELECT count(*) FROM audit").fetchone()[0])
    finally:
        db.close()


async def test_the_oldest_rows_go_beyond_the_retention_bound(tmp_path: Path) -> None:
    st = Store(tmp_path, audit_max_rows=50, flush_s=0.01)
    st.open()
    try:
        for i in range(200):
            st.audit((float(i), "alice", "operator", "rbe3001", "POST", "/x", "", 200, None))
            if i % 60 == 0:  # in several transactions

                async def landed() -> bool:
                    return st.health().pending == 0
                await until(landed, timeout=10.0, what="the writes")

        async def all_landed() -> bool:
            return st.health().pending == 0
        await until(all_landed, timeout=10.0, what="the writes")
        assert count(tmp_path) == 50
        assert [r["time"] for r in await st.query_audit(limit=1000)] == [
            float(i) for i in range(199, 149, -1)]
        assert st.audit_trimmed == 150
    finally:
        st.close()
    again = Store(tmp_path, audit_max_rows=20, flush_s=0.01)  # a lower bound, set later
    again.open()
    try:
        again.audit((500.0, "bob", "operator", None, "POST", "/y", "", 200, None))

        async def landed_again() -> bool:
            return again.health().pending == 0
        await until(landed_again, timeout=10.0, what="the write")
        times = [r["time"] for r in await again.query_audit(limit=1000)]
        assert times == [500.0, *(float(i) for i in range(199, 180, -1))]
    finally:
        again.close()


async def test_the_setting_bounds_the_servers_log(tmp_path: Path) -> None:
    settings = make_settings(data_dir=str(tmp_path), audit_max_rows=100)
    assert make_settings().audit_max_rows == 100_000
    async with running_client(settings) as (app, c):
        for _ in range(130):
            assert (await c.post("/api/v1/arms/angler/stop")).status_code == 200

        async def landed() -> bool:
            return bool(app.state.store.health().pending == 0)
        await until(landed, timeout=10.0, what="the writes")
        assert count(tmp_path) == 100


async def test_memory_is_bounded_while_the_disk_is_full_and_the_loss_is_said(
        tmp_path: Path) -> None:
    probe = Store(tmp_path / "probe")
    probe.open()
    probe.close()
    pages = sqlite3.connect(tmp_path / "probe" / DB_NAME).execute(
        "PRAGMA page_count").fetchone()[0]
    st = Store(tmp_path, max_pages=pages, retry_s=0.1, flush_s=0.01, max_pending=20)
    st.open()
    try:
        big = "x" * 4000
        for i in range(100):
            st.audit((float(i), "bob", "operator", "angler", "POST", "/y", big, 200, None))

        async def bounded() -> bool:  # a write failed; quiet between two
            h = st.health()
            return st.audit_dropped == 81 and h.pending == 20 and "full" in (h.error or "")
        await until(bounded, timeout=10.0, what="the bound to drop the oldest")
        h = st.health()
        assert not h.ok and "full" in (h.error or "")
        assert "81 audit record(s) dropped" in (h.error or "")
        got = await st.query_audit(limit=1000)
        assert [r["time"] for r in got if r["kind"] == "request"] == [
            float(i) for i in range(99, 80, -1)]  # the newest 19 kept
        # the disk takes writes again: the kept records land, and so does the count of the lost
        await st.run(lambda db: db.execute("PRAGMA max_page_count=1000000"))

        async def landed() -> bool:
            return st.health().ok and st.health().pending == 0
        await until(landed, timeout=10.0, what="the kept records to land")
    finally:
        st.close()
    db = sqlite3.connect(tmp_path / DB_NAME)
    rows = db.execute("SELECT kind, count, summary FROM audit ORDER BY seq").fetchall()
    assert len(rows) == 20
    assert rows[0][:2] == ("dropped", 81) and "81 audit record(s) lost" in rows[0][2]
    assert all(r[:2] == ("request", 1) for r in rows[1:])
