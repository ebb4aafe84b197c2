"""The audit log (API.md "Audit log"): every changing request recorded with names, never
tokens; instructor-only queries, CSV; a locked or full database keeps the records; the log and
the queues survive a restart."""

from __future__ import annotations

import csv
import io
import sqlite3
import time
from pathlib import Path
from typing import Any

from app.store import AUDIT_COLUMNS, Store
from tests.conftest import make_settings, running_client
from tests.test_classroom import ALICE, BOB, TEACH, VIEW, H, class_settings, offered, until


async def audit(c: Any, **params: Any) -> list[dict[str, Any]]:
    r = await c.get("/api/v1/audit", params=params, headers=H(TEACH))
    assert r.status_code == 200, r.text
    return r.json()  # type: ignore[no-any-return]


async def test_every_change_is_recorded_with_names_not_tokens() -> None:
    async with running_client(class_settings(lease_ttl_s=30.0)) as (_, c):
        t0 = time.time()
        r = await c.post("/api/v1/arms/rbe3001/lease", headers=H(ALICE))
        lease = r.json()["id"]
        move = {"positions": [0.1, 0.5, 0.3], "speed": 1.0, "wait": True}
        r = await c.post("/api/v1/arms/rbe3001/move/joints", json=move,
                         headers={**H(ALICE), "X-Arm-Lease": lease})
        assert r.status_code == 200
        r = await c.post("/api/v1/arms/rbe3001/move/joints", json=move, headers=H(BOB))
        assert r.status_code == 409
        await c.post("/api/v1/arms/angler/stop", headers=H(BOB))
        await c.post("/api/v1/arms/angler/estop", headers=H(VIEW))
        await c.delete("/api/v1/arms/angler/estop", headers=H(TEACH))
        await c.put(f"/api/v1/arms/rbe3001/lease/{lease}", headers=H(ALICE))
        await c.delete(f"/api/v1/arms/rbe3001/lease/{lease}", headers=H(ALICE))
        await c.post("/api/v1/arms/angler/queue", headers=H(ALICE))
        await c.post("/api/v1/arms/angler/stop", headers=H("not-a-token"))
        await c.get("/api/v1/arms/angler/state", headers=H(ALICE))  # a read: not recorded
        rows = await audit(c, since=t0)
        got = [(r["name"], r["method"], r["route"], r["status"], r["code"]) for r in rows]
        assert got == [
            ("(unauthenticated)", "POST", "/api/v1/arms/angler/stop", 401, "unauthorized"),
            ("alice", "POST", "/api/v1/arms/angler/queue", 201, None),
            ("alice", "DELETE", "/api/v1/arms/rbe3001/lease/{lease}", 204, None),
            ("alice", "PUT", "/api/v1/arms/rbe3001/lease/{lease}", 200, None),
            ("teach", "DELETE", "/api/v1/arms/angler/estop", 200, None),
            (rows[5]["name"], "POST", "/api/v1/arms/angler/estop", 200, None),
            ("bob", "POST", "/api/v1/arms/angler/stop", 200, None),
            ("bob", "POST", "/api/v1/arms/rbe3001/move/joints", 409, "leased"),
            ("alice", "POST", "/api/v1/arms/rbe3001/move/joints", 200, None),
            ("alice", "POST", "/api/v1/arms/rbe3001/lease", 201, None),
        ]
        assert rows[5]["role"] == "viewer" and rows[0]["role"] == "none"
        assert rows[-2]["arm"] == "rbe3001" and '"positions":[0.1,0.5,0.3]' in rows[-2]["summary"]
        text = str(rows)
        assert lease not in text and ALICE not in text and BOB not in text
        # filters
        assert {r["name"] for r in await audit(c, who="bob", since=t0)} == {"bob"}
        assert {r["arm"] for r in await audit(c, arm="angler", since=t0)} == {"angler"}
        assert len(await audit(c, since=t0, limit=3)) == 3
        assert await audit(c, until=t0 - 1) == []
        # CSV
        r = await c.get("/api/v1/audit", params={"since": t0},
                        headers={**H(TEACH), "Accept": "text/csv"})
        assert r.status_code == 200 and r.headers["content-type"].startswith("text/csv")
        table = list(csv.reader(io.StringIO(r.text)))
        assert tuple(table[0]) == AUDIT_COLUMNS and len(table) == 11
        assert table[1][1] == "(unauthenticated)" and table[-1][5].endswith("/lease")
        # instructor only
        assert (await c.get("/api/v1/audit", headers=H(ALICE))).status_code == 403
        r = await c.get("/api/v1/audit", params={"limit": 0}, headers=H(TEACH))
        assert r.status_code == 422


async def test_restart_keeps_the_queue_and_the_log(tmp_path: Path) -> None:
    settings = class_settings(data_dir=str(tmp_path), claim_s=30.0, slot_s=60.0,
                              lease_ttl_s=30.0)
    async with running_client(settings) as (_, c):
        a = (await c.post("/api/v1/arms/angler/queue", headers=H(ALICE))).json()
        b = (await c.post("/api/v1/arms/angler/queue", headers=H(BOB))).json()
        await offered(c, "angler", a["id"], ALICE)
        before = await audit(c)
    async with running_client(settings) as (_, c):
        q = (await c.get("/api/v1/arms/angler/queue", headers=H(VIEW))).json()
        assert [(e["id"], e["name"]) for e in q["entries"]] == [(a["id"], "alice"),
                                                                (b["id"], "bob")]
        await offered(c, "angler", a["id"], ALICE)  # alice's offer died with the process
        after = await audit(c)
        assert after[-len(before):] == before


async def test_locked_database_keeps_audit_records_and_health_says_so(tmp_path: Path) -> None:
    st = Store(tmp_path, retry_s=0.05, busy_timeout_s=0.05)
    st.open()
    try:
        other = sqlite3.connect(st.path, isolation_level=None)
        other.execute("BEGIN EXCLUSIVE")
        rows = [(time.time() + i, "alice", "operator", "rbe3001", "POST", "/x", "", 200, None)
                for i in range(50)]
        for r in rows:
            st.audit(r)

        async def failing() -> bool:
            return not st.health().ok
        await until(failing, timeout=10.0, what="the store to report the lock")
        h = st.health()
        assert h.pending >= 1 and "audit" in (h.error or "")
        got = await st.query_audit(limit=100)  # unsaved records answer reads too
        assert len(got) == 50 and got[0]["time"] == rows[-1][0]
        other.execute("ROLLBACK")
        other.close()

        async def landed() -> bool:
            return st.health().ok and st.health().pending == 0
        await until(landed, timeout=10.0, what="the retried records to land")
        assert st.audit_written == 50
    finally:
        st.close()
    st2 = Store(tmp_path)
    st2.open()
    try:
        assert len(await st2.query_audit(limit=1000)) == 50
    finally:
        st2.close()


async def test_full_disk_keeps_audit_records(tmp_path: Path) -> None:
    st = Store(tmp_path, retry_s=0.05)
    st.open()
    st.close()
    pages = sqlite3.connect(tmp_path / "armserver.sqlite3").execute(
        "PRAGMA page_count").fetchone()[0]
    st = Store(tmp_path, max_pages=pages + 2, retry_s=0.05)
    st.open()
    try:
        big = "x" * 4000
        for i in range(40):
            st.audit((float(i), "bob", "operator", "angler", "POST", "/y", big, 200, None))
        async def full() -> bool:
            return not st.health().ok

        await until(full, timeout=10.0, what="the store to say the disk is full")
        h = st.health()
        assert not h.ok and "full" in (h.error or "") and h.pending > 0
        assert len(await st.query_audit(limit=100)) == 40  # none lost
    finally:
        st.close()


async def test_open_server_records_anyone() -> None:
    async with running_client(make_settings()) as (_, c):
        await c.post("/api/v1/arms/angler/stop")
        rows = (await c.get("/api/v1/audit")).json()
        assert rows[0]["name"] == "anyone" and rows[0]["role"] == "instructor"
