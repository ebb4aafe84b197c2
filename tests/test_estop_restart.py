"""A latched estop survives a restart of the server that latched it, and an outage of the
arm's link: only a release releases it (app/service.py `keep_latch_in`; the store's record
`arm:<name>` / `estop`). The app in process over the default simulated arms, stopped and
started again on the same data folder, as `armserver serve` is by a crash, a kill or an
operator; a lab's killed worker, and a press while it restarts, are
tests/test_lab_workers.py's.
"""

from __future__ import annotations

import asyncio
import json
import logging
import sqlite3
import threading
from pathlib import Path

import numpy as np
import pytest
from _safety_support import goal_raw, motor_of, set_pid_body
from _wait import wait_for
from conftest import make_settings, running_client

from app.config import FaultConfig
from app.service import ArmService
from app.store import DB_NAME, Store

API = "/api/v1/arms"


def _stored(data: Path, arm: str) -> dict[str, object] | None:
    """The store's record of `arm`'s latch, read from the database file as another process
    would (None: none written)."""
    with sqlite3.connect(f"file:{data / DB_NAME}?mode=ro", uri=True) as db:
        row = db.execute("SELECT value FROM settings WHERE scope = ? AND key = 'estop'",
                         (f"arm:{arm}",)).fetchone()
    return None if row is None else json.loads(row[0])


async def _on_disk(data: Path, arm: str, latched: bool) -> None:
    await wait_for(lambda: (_stored(data, arm) or {}).get("latched") is latched,
                   what=f"{arm}'s latch {latched} in the database file")


async def test_a_latch_holds_across_a_restart_until_released(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    settings = make_settings(data_dir=str(tmp_path))
    async with running_client(settings) as (_app, c):
        assert (await c.post(f"{API}/rbe3001/estop")).json() == {"estop": True}
        await _on_disk(tmp_path, "rbe3001", True)
        assert _stored(tmp_path, "angler") is None  # the other arm: nothing latched
    caplog.set_level(logging.WARNING, logger="app.service")
    async with running_client(settings) as (app, c):
        rb, an = app.state.services["rbe3001"], app.state.services["angler"]
        # latched from the start, before any request: the arm came up and samples flow
        assert rb.estop and not an.estop
        assert (await c.get(f"{API}/rbe3001/state")).json()["estop"] is True
        assert rb.hub.latest is not None and rb.hub.latest["estop"] is True
        assert any("latched since" in r.getMessage() and "DELETE /api/v1/arms/rbe3001/estop"
                   in r.getMessage() for r in caplog.records), caplog.text
        # nothing moves it: a planned move, a pass-through SET_PID
        q = np.asarray(rb.driver.positions, dtype=float)
        r = await c.post(f"{API}/rbe3001/move/joints", json={"positions": (q + 0.1).tolist()})
        assert r.status_code == 409 and r.json()["code"] == "estop_latched", r.text
        r = await c.post(f"{API}/rbe3001/rbe3001/set-pid", json=set_pid_body(rb, q + 0.1))
        assert r.status_code == 409 and r.json()["code"] == "estop_latched", r.text
        assert np.allclose(rb.driver.positions, q, atol=0.02)
        # the other arm moves as ever
        r = await c.put(f"{API}/angler/dynamixel/{motor_of(an, 2)}/registers/goal_position",
                        json={"raw": goal_raw(an, 2, np.asarray(an.driver.positions) + [0, 0,
                                                                                         0.1, 0])})
        assert r.status_code == 200, r.text
        # released: that is kept too
        assert (await c.delete(f"{API}/rbe3001/estop")).json() == {"estop": False}
        await _on_disk(tmp_path, "rbe3001", False)
        r = await c.post(f"{API}/rbe3001/move/joints", json={"positions": (q + 0.05).tolist()})
        assert r.status_code == 202, r.text
    async with running_client(settings) as (app, c):
        assert not app.state.services["rbe3001"].estop
        assert (await c.get(f"{API}/rbe3001/state")).json()["estop"] is False


async def test_a_press_is_answered_once_its_latch_is_on_disk(tmp_path: Path) -> None:
    """An answered press survives a crash: the 200 comes once the latch's record is in the
    database file, not only queued for the store's writer thread. The writer is held here by
    a job of the test's in front of the record (a disk that is slow for a moment)."""
    settings = make_settings(data_dir=str(tmp_path))
    async with running_client(settings) as (app, c):
        svc, store = app.state.services["rbe3001"], app.state.store
        gate = threading.Event()
        store._call(lambda: gate.wait(30.0))  # the writer thread waits for the gate
        press = asyncio.create_task(c.post(f"{API}/rbe3001/estop"))
        try:
            # latched, the hold commanded: all the answer waited for before this change
            await wait_for(lambda: svc._hold is not None and svc._hold.done(),
                           what="the latch's hold commanded")
            await asyncio.sleep(0.2)  # (not a wait for something: the early answer's chance)
            assert not press.done(), "answered before the latch was on disk"
            assert _stored(tmp_path, "rbe3001") is None
        finally:
            gate.set()
        async with asyncio.timeout(10.0):
            r = await press
        assert r.status_code == 200 and r.json() == {"estop": True}
        record = _stored(tmp_path, "rbe3001")  # at the answer, not after a wait
        assert record is not None and record["latched"] is True, record


async def _settled(svc: ArmService, store: Store) -> None:
    """Every latch record `svc` has asked for is written: its hold has ended, its control
    loop has run what was queued for it before now, and the store has written what was
    queued before a write of the test's (one writer thread, in order)."""
    await wait_for(lambda: svc._hold is not None and svc._hold.done(),
                   what="the latch's hold ended")
    await svc.release_estop()  # (a round trip through its loop)
    assert await store.put_setting("test", "settled", True)


async def test_the_fast_paths_latch_is_kept_once_its_sample_is_out(tmp_path: Path) -> None:
    """The estop fast path presses on a request's head and sends the sample that shows the
    latch before the latch's record goes to the store's writer (whose thread woken with the
    latch kept the GIL from that sample). The record still lands: when the fast path says its
    sample is out, or at the hold's end if it never does; and a release that comes between
    the press and either has the last word."""
    settings = make_settings(data_dir=str(tmp_path))
    async with running_client(settings) as (app, c):
        rb, an, store = (app.state.services["rbe3001"], app.state.services["angler"],
                         app.state.store)
        await c.get("/api/v1/health")  # builds the middleware stack
        layer = app.middleware_stack
        while type(layer).__name__ != "StateFastPath":
            layer = layer.app
        # the fast path alone, the request's head: latched and kept, no route's press after it
        await layer._press_estop({"type": "http", "method": "POST", "headers": [],
                                  "path": f"{API}/angler/estop"})
        assert an.estop
        await _on_disk(tmp_path, "angler", True)
        # the press without its word that the sample is out: kept at the hold's end
        rb.press_estop()
        assert rb.estop
        await _on_disk(tmp_path, "rbe3001", True)
        assert (await c.delete(f"{API}/rbe3001/estop")).json() == {"estop": False}
        await _on_disk(tmp_path, "rbe3001", False)
        # released before the word comes and before the hold ends (the release is queued on
        # the arm's loop right behind the press; the hold waits for the board, which answers
        # 30 ms late, inside the link's timeout): the record says released, then and after
        rb.driver.link.set_faults(FaultConfig(latency_s=0.03))
        rb.press_estop()
        assert (await rb.release_estop()).estop is False
        rb.pressed_sample_sent()
        await _settled(rb, store)
        assert not rb.estop
        assert (_stored(tmp_path, "rbe3001") or {}).get("latched") is False
    async with running_client(settings) as (app, c):  # as a restart finds them
        assert app.state.services["angler"].estop
        assert not app.state.services["rbe3001"].estop


async def test_a_press_on_a_latch_from_before_the_start_is_a_press_on_a_latched_estop(
        tmp_path: Path) -> None:
    """A press after such a start changes nothing (and writes nothing); a release then a
    press latches and records again."""
    settings = make_settings(data_dir=str(tmp_path))
    async with running_client(settings) as (_app, c):
        await c.post(f"{API}/angler/estop")
        await _on_disk(tmp_path, "angler", True)
    async with running_client(settings) as (app, c):
        at = _stored(tmp_path, "angler")
        assert app.state.services["angler"].estop
        assert (await c.post(f"{API}/angler/estop")).json() == {"estop": True}
        # a setting written after the press is on disk: so would the press's be (the store
        # writes in order, one thread)
        r = await c.put(f"{API}/angler/safety", json={"speed_override": 0.9})
        assert r.status_code == 200 and r.json()["persisted"] is True, r.text
        assert _stored(tmp_path, "angler") == at
        await c.delete(f"{API}/angler/estop")
        await _on_disk(tmp_path, "angler", False)
        await c.post(f"{API}/angler/estop")
        await _on_disk(tmp_path, "angler", True)
        assert _stored(tmp_path, "angler") != at  # its own time


@pytest.mark.parametrize("value", ['"latched"', '{"latched": "yes"}', "[true]", "not json"])
async def test_a_record_that_is_not_a_latch_latches_nothing(
        tmp_path: Path, value: str, caplog: pytest.LogCaptureFixture) -> None:
    """Only `{"latched": true}` latches; anything else the store holds there is not a latch
    (unreadable JSON is said in the log)."""
    settings = make_settings(data_dir=str(tmp_path))
    async with running_client(settings):
        pass  # the database made
    with sqlite3.connect(tmp_path / DB_NAME) as db:
        db.execute("INSERT INTO settings (scope, key, value, updated) "
                   "VALUES ('arm:rbe3001', 'estop', ?, 0)", (value,))
    async with running_client(settings) as (app, c):
        assert not app.state.services["rbe3001"].estop
        assert (await c.get(f"{API}/rbe3001/state")).json()["estop"] is False
    if value == "not json":
        assert "stored estop latch could not be read" in caplog.text


@pytest.mark.parametrize("arm", ["rbe3001", "angler"])
async def test_a_press_while_the_link_is_down_latches_the_arm_it_comes_back_to(
        arm: str, caplog: pytest.LogCaptureFixture) -> None:
    """The cable out: the press latches (200, the hold it could not command is said in the
    log), and the arm comes back latched; a move is refused until the release. A lab's front
    keeps a press for a restarting worker to the same end."""
    async with running_client() as (app, c):
        svc = app.state.services[arm]
        link = svc.driver.link
        # out for 2 s: the press comes while it is out, a loaded machine's delays included
        link.set_faults(FaultConfig(reconnect_after_s=2.0))
        svc.home_loop.call_soon_threadsafe(link.disconnect)  # (the link's loop)

        async def down() -> bool:
            return (await c.get("/api/v1/health")).json()["arms"][arm]["state"] != "up"

        await wait_for(down, every=0.005, what=f"{arm}'s link down")
        r = await c.post(f"{API}/{arm}/estop")
        assert r.status_code == 200 and r.json() == {"estop": True}, r.text
        assert "could not command a hold" in caplog.text
        assert await svc.driver.wait_connected(10.0)
        await wait_for(lambda: svc.hub.latest is not None and not svc.driver.stale,
                       what=f"{arm}'s samples again")
        assert (await c.get(f"{API}/{arm}/state")).json()["estop"] is True
        q = np.asarray(svc.driver.positions, dtype=float)
        r = await c.post(f"{API}/{arm}/move/joints", json={"positions": q.tolist()})
        assert r.status_code == 409 and r.json()["code"] == "estop_latched", r.text
        assert (await c.delete(f"{API}/{arm}/estop")).json() == {"estop": False}
