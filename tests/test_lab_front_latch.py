"""A lab's front writes an estop press it keeps for a down worker to the lab's store as the
arm's latch (app/lab/front.py `_keep`): the arm's next start, however late, and after the
front's own restart, is latched. The front here in process, its workers never started (down
throughout); the arm's start is a server's over the same data folder, as a worker's is.
The whole lab, a worker killed and a press while it restarts: tests/test_lab_workers.py."""

from __future__ import annotations

import contextlib
import json
import sqlite3
from collections.abc import Iterator
from pathlib import Path

import httpx
import uvicorn
from conftest import make_settings, running_client, uvicorn_thread

from app.arms.loading import load_profile
from app.lab.serve import build_front
from app.store import DB_NAME
from app.web.factory import create_app

ESTOP = "/api/v1/arms/{}/estop"


def _stored(data: Path, arm: str) -> dict[str, object] | None:
    """The latch record of `arm` in the database file, as another process reads it."""
    with sqlite3.connect(f"file:{data / DB_NAME}?mode=ro", uri=True) as db:
        row = db.execute("SELECT value FROM settings WHERE scope = ? AND key = 'estop'",
                         (f"arm:{arm}",)).fetchone()
    return None if row is None else json.loads(row[0])


def front_client(front: object, base_url: str = "http://armserver.test") -> httpx.AsyncClient:
    """A client of the front app in this process (its lifespan not run: no supervisor)."""
    return httpx.AsyncClient(transport=httpx.ASGITransport(app=front),  # type: ignore[arg-type]
                             base_url=base_url)


async def _press(front: object, arm: str, **headers: str) -> httpx.Response:
    async with front_client(front) as c:
        return await c.post(ESTOP.format(arm), headers=headers)


async def test_a_press_on_an_open_lab_with_its_worker_down_latches_the_arm_in_the_store(
        tmp_path: Path) -> None:
    data = tmp_path / "data"
    settings = make_settings(data_dir=str(data))
    front = build_front(settings, 2, tmp_path)
    assert {a for w in front.workers for a in w.arms} == {"rbe3001", "angler"}
    front.store.open()
    try:
        r = await _press(front, "rbe3001")
        assert r.status_code == 503 and r.json()["code"] == "link_down", r.text
        assert "this estop press is kept" in r.json()["detail"], r.text
        record = _stored(data, "rbe3001")  # at the answer: no wait
        assert record is not None and record["latched"] is True, record
        # what the worker would refuse latches nothing: a page from another origin, a Host
        # the lab does not answer to (an open lab's rules, app/web/hostguard.py)
        r = await _press(front, "angler", origin="http://elsewhere.example")
        assert r.status_code == 503 and _stored(data, "angler") is None, r.text
        r = await _press(front, "angler", host="rebound.example")
        assert r.status_code == 503 and _stored(data, "angler") is None, r.text
    finally:
        front.store.close()
    # the arm's next start on that store (a worker's, or a single server's): latched, only it
    async with running_client(make_settings(data_dir=str(data))) as (app, c):
        assert app.state.services["rbe3001"].estop
        assert not app.state.services["angler"].estop
        assert (await c.get("/api/v1/arms/rbe3001/state")).json()["estop"] is True


async def test_a_press_without_a_token_the_lab_knows_latches_nothing(tmp_path: Path) -> None:
    data = tmp_path / "data"
    front = build_front(make_settings(data_dir=str(data), viewer_tokens="viewer-secret"), 2,
                        tmp_path)
    front.store.open()
    try:
        r = await _press(front, "angler", authorization="Bearer not-a-token")
        assert r.status_code == 503 and "kept" not in r.json()["detail"], r.text
        assert _stored(data, "angler") is None
        r = await _press(front, "angler", authorization="Bearer viewer-secret")  # may press
        assert r.status_code == 503 and "this estop press is kept" in r.json()["detail"]
        record = _stored(data, "angler")
        assert record is not None and record["latched"] is True, record
    finally:
        front.store.close()



@contextlib.contextmanager
def _worker_on(uds: Path, data: Path) -> Iterator[None]:
    """The real worker app (a server over the rbe3001 alone, as worker 0 of the default
    arms' plan) on the worker's Unix socket, in a thread, lifespan and all."""
    app = create_app(make_settings(data_dir=str(data)), profiles=[load_profile("rbe3001")])
    server = uvicorn.Server(uvicorn.Config(app, uds=str(uds), lifespan="on",
                                           log_level="warning"))
    with uvicorn_thread(server, "worker-0"):
        yield


async def test_the_lists_name_an_arm_and_a_camera_whose_worker_never_answered(
        tmp_path: Path) -> None:
    """`GET /api/v1/arms` lists every arm of the lab's plan: one whose worker is down and has
    not answered since the front started (no summary of its own yet) from its profile, link
    down; a client that presses every arm it lists misses none. `GET /api/v1/cameras` the
    same: such a camera from its config, not up, calibrated if the store has one. (With no
    worker ready at all: the next test.)"""
    front = build_front(make_settings(data_dir=str(tmp_path / "data")), 2, tmp_path)
    up, down = front.workers
    assert (up.arms, down.arms) == (("rbe3001",), ("angler",))
    front.store.open()
    with _worker_on(up.uds, tmp_path / "data"):
        up.ready = True  # (the supervisor, not started here, sets it once it answers)
        try:
            async with front_client(front) as c:
                r = await c.get("/api/v1/arms")
                cams = await c.get("/api/v1/cameras")
                # a calibration in the store (as the worker's hub keeps it): said calibrated
                front.store.put_setting_nowait("camera:angler", "calibration", {"k": 1})
                cams_after = await c.get("/api/v1/cameras")
        finally:
            await up.client.aclose()
            front.store.close()
    assert r.status_code == 200, r.text
    listed = {a["name"]: a for a in r.json()}
    assert list(listed) == ["rbe3001", "angler"]
    assert listed["rbe3001"]["link"]["connected"] is True
    angler = listed["angler"]
    assert angler["link"]["state"] == "down" and angler["link"]["connected"] is False
    assert angler["model"] == "angler"
    # as the angler's own server describes it; its camera too (but up)
    async with running_client(make_settings(data_dir=str(tmp_path / "one"))) as (_, c):
        own = {a["name"]: a for a in (await c.get("/api/v1/arms")).json()}["angler"]
        own_cams = {k["name"]: k for k in (await c.get("/api/v1/cameras")).json()}
    assert angler["capabilities"] == own["capabilities"], (angler, own)
    assert angler["description"] == own["description"]
    assert cams.status_code == 200, cams.text
    listed_cams = {k["name"]: k for k in cams.json()}
    assert list(listed_cams) == list(own_cams) == ["rbe3001", "angler"], listed_cams
    assert listed_cams["angler"] == {**own_cams["angler"], "up": False}, listed_cams
    assert listed_cams["rbe3001"]["up"] is True
    assert {k["name"]: k["calibrated"] for k in cams_after.json()}["angler"] is True


async def test_with_no_worker_ready_the_front_checks_the_caller_and_lists_every_arm_down(
        tmp_path: Path) -> None:
    """No worker ready (the lab starting, or every worker restarting): `GET /api/v1/arms` and
    `/cameras` are answered by the front, which checks the caller as a worker would first (a
    viewer's token; on an open lab the Host rule), with the worker's own refusals: every arm
    of the plan listed from its profile, link down; every camera from its config, not up.
    They were 503 (`link_down`, "no worker process is ready"): a dashboard or a script that
    lists the arms to press them all had nothing to press."""
    data = tmp_path / "data"
    front = build_front(make_settings(data_dir=str(data), viewer_tokens="viewer-secret"), 2,
                        tmp_path)
    assert not any(w.ready for w in front.workers)
    front.store.open()
    try:
        async with front_client(front) as c:
            auth = {"authorization": "Bearer viewer-secret"}
            arms = await c.get("/api/v1/arms", headers=auth)
            cams = await c.get("/api/v1/cameras", headers=auth)
            none = await c.get("/api/v1/arms")
            wrong = await c.get("/api/v1/cameras", headers={"authorization": "Bearer nope"})
            moved = await c.get("/api/v1/arms/angler/state", headers=auth)  # still 503
    finally:
        front.store.close()
    # a server with the same tokens refuses the same way, and describes the same arms
    async with running_client(make_settings(data_dir=str(tmp_path / "one"),
                                            viewer_tokens="viewer-secret")) as (_, c):
        own_none = await c.get("/api/v1/arms")
        own_wrong = await c.get("/api/v1/cameras", headers={"authorization": "Bearer nope"})
        own = {a["name"]: a for a in (await c.get("/api/v1/arms", headers=auth)).json()}
        own_cams = {k["name"]: k for k in (await c.get("/api/v1/cameras", headers=auth)).json()}
    assert (none.status_code, none.json()) == (own_none.status_code, own_none.json()) \
        and none.status_code == 401, none.text
    assert none.headers["www-authenticate"] == "Bearer"
    assert (wrong.status_code, wrong.json()) == (own_wrong.status_code, own_wrong.json()) \
        and wrong.status_code == 401, wrong.text
    assert arms.status_code == 200, arms.text
    listed = {a["name"]: a for a in arms.json()}
    assert list(listed) == list(own) == ["rbe3001", "angler"]
    for name, arm in listed.items():
        assert arm["link"]["state"] == "down" and arm["link"]["connected"] is False, arm
        assert {k: v for k, v in arm.items() if k != "link"} == \
            {k: v for k, v in own[name].items() if k != "link"}, (arm, own[name])
    assert cams.status_code == 200, cams.text
    assert {k["name"]: k for k in cams.json()} == \
        {name: {**k, "up": False} for name, k in own_cams.items()}
    assert moved.status_code == 503 and moved.json()["code"] == "link_down", moved.text


async def test_with_no_worker_ready_an_open_labs_lists_keep_its_host_rule(
        tmp_path: Path) -> None:
    """An open lab (no tokens) answers the lists with no worker ready only to a Host it
    answers to: another name is 400 `bad_host`, as a worker's own middleware says it."""
    front = build_front(make_settings(data_dir=str(tmp_path / "data")), 2, tmp_path)
    front.store.open()
    try:
        async with front_client(front, "http://127.0.0.1:8000") as c:
            ok = await c.get("/api/v1/arms")
            rebound = await c.get("/api/v1/arms", headers={"host": "rebound.example"})
            health = await c.get("/api/v1/health")
            rebound_health = await c.get("/api/v1/health", headers={"host": "rebound.example"})
    finally:
        front.store.close()
    async with running_client(make_settings(data_dir=str(tmp_path / "one"))) as (_, c):
        own = await c.get("/api/v1/arms", headers={"host": "rebound.example"})
    assert ok.status_code == 200 and [a["name"] for a in ok.json()] == ["rbe3001", "angler"]
    assert (rebound.status_code, rebound.json()) == (own.status_code, own.json()), own.text
    assert rebound.status_code == 400 and rebound.json()["code"] == "bad_host"
    # health, which needs no token, keeps the Host rule too (it names the arms' addresses)
    assert health.status_code == 200 and health.json()["status"] == "degraded", health.text
    assert (rebound_health.status_code, rebound_health.json()) == (own.status_code, own.json())


async def test_a_ready_worker_that_does_not_answer_leaves_the_check_to_the_front(
        tmp_path: Path) -> None:
    """A worker the supervisor still counts ready but that does not answer (it has just died,
    nothing on its socket): the lists are answered from the plan, so the front checks the
    caller first, as with no worker ready (it gave the list to anyone)."""
    front = build_front(make_settings(data_dir=str(tmp_path / "data"),
                                      viewer_tokens="viewer-secret"), 2, tmp_path)
    for w in front.workers:
        w.ready = True  # (nothing listens on its socket)
    front.store.open()
    try:
        async with front_client(front) as c:
            none = await c.get("/api/v1/arms")
            cams = await c.get("/api/v1/cameras")
            auth = await c.get("/api/v1/arms", headers={"authorization": "Bearer viewer-secret"})
    finally:
        for w in front.workers:
            await w.client.aclose()
        front.store.close()
    assert none.status_code == 401 and none.json()["code"] == "unauthorized", none.text
    assert cams.status_code == 401, cams.text
    assert auth.status_code == 200, auth.text
    assert [(a["name"], a["link"]["state"]) for a in auth.json()] == [("rbe3001", "down"),
                                                                       ("angler", "down")]
