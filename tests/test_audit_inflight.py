"""Issue 22.9: a request that may change the arm is recorded when it starts (status null) and
completed when it ends; the start is in the database file within a bounded time, so a kill -9
of a real `armserver serve` during a `wait: true` move keeps the attempt (and the next start
marks it `interrupted`)."""

from __future__ import annotations

import asyncio
import os
import signal
import sqlite3
import threading
import time
from pathlib import Path
from typing import Any

import httpx

from app.store import DB_NAME, INTERRUPTED, Store
from tests._http import HTTP
from tests._serve import clean_env, start
from tests.conftest import make_settings, running_client

MOVE = {"positions": [1.2, 1.4, -0.6], "speed": 0.2, "wait": True}
ROUTE = "/api/v1/arms/rbe3001/move/joints"


def moves_on_disk(data_dir: Path) -> list[dict[str, Any]]:
    """The move's rows as another process reads the database file."""
    if not (data_dir / DB_NAME).exists():
        return []
    db = sqlite3.connect(f"file:{data_dir / DB_NAME}?mode=ro", uri=True, timeout=5.0)
    db.row_factory = sqlite3.Row
    try:
        return [dict(r) for r in db.execute("SELECT * FROM audit WHERE route = ?", (ROUTE,))]
    except sqlite3.OperationalError:  # the table is not there yet
        return []
    finally:
        db.close()


async def test_the_start_is_on_disk_while_the_move_runs_and_completed_after(
        tmp_path: Path) -> None:
    async with running_client(make_settings(data_dir=str(tmp_path))) as (app, c):
        task = asyncio.create_task(c.post(ROUTE, json=MOVE))
        started: list[dict[str, Any]] = []
        deadline = time.monotonic() + 5.0
        while not started and not task.done() and time.monotonic() < deadline:
            started = [r for r in moves_on_disk(tmp_path) if r["status"] is None]
            await asyncio.sleep(0.02)
        assert started, "no start record in the database file while the move ran"
        assert not task.done()
        (row,) = started
        assert row["code"] is None and row["ended"] is None and row["arm"] == "rbe3001"
        assert '"positions":[1.2,1.4,-0.6]' in row["summary"] and row["kind"] == "request"
        # the API says it runs, too
        live = (await c.get("/api/v1/audit")).json()
        assert any(r["route"] == ROUTE and r["status"] is None for r in live)
        r = await task
        assert r.status_code == 200 and r.json()["status"] == "done", r.text

        done: list[dict[str, Any]] = []
        deadline = time.monotonic() + 5.0
        while not done and time.monotonic() < deadline:
            done = [r for r in moves_on_disk(tmp_path) if r["status"] is not None]
            await asyncio.sleep(0.02)
        assert [(d["seq"], d["status"], d["code"]) for d in done] == [(row["seq"], 200, None)]
        assert done[0]["time"] == row["time"] < done[0]["ended"]


def test_kill_9_during_a_waiting_move_keeps_the_attempt(tmp_path: Path) -> None:
    srv = start(tmp_path / "server.log", "--log-level", "warning",
                env=clean_env(ARMSERVER_DATA_DIR=str(tmp_path)))
    proc, url = srv.proc, srv.url
    try:
        box: dict[str, Any] = {}

        def move() -> None:
            try:
                box["r"] = HTTP.post(f"{url}{ROUTE}", json=MOVE, timeout=60)
            except httpx.HTTPError as exc:
                box["error"] = exc

        thread = threading.Thread(target=move, daemon=True)
        thread.start()
        deadline = time.monotonic() + 10
        while True:  # the arm moves
            assert time.monotonic() < deadline, "the move did not start"
            m = HTTP.get(f"{url}/api/v1/arms/rbe3001/state", timeout=2).json()["motion"]
            if m is not None and m["status"] == "running" and m["progress"] > 0.05:
                break
            time.sleep(0.05)
        deadline = time.monotonic() + 2.5  # the kill came 2.5 s in
        while not moves_on_disk(tmp_path) and time.monotonic() < deadline:
            time.sleep(0.02)
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(timeout=10)
        thread.join(10)
        assert "r" not in box, box  # it never answered: killed mid-move
    finally:
        srv.stop()
    (row,) = moves_on_disk(tmp_path)
    assert row["status"] is None and row["code"] is None and row["method"] == "POST"
    assert row["arm"] == "rbe3001" and '"speed":0.2' in row["summary"]
    st = Store(tmp_path)  # the next start
    st.open()
    try:
        got = asyncio.run(st.query_audit(limit=10))
    finally:
        st.close()
    assert [(r["route"], r["status"], r["code"]) for r in got] == [(ROUTE, None, INTERRUPTED)]
