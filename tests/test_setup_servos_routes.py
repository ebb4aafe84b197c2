"""Servo set-up in the dashboard (issue 24): the routes under /api/v1/setup-servos against the
practice bus, a real factory-state simulated bus the server serves on a pseudo-terminal whose
termios rate its servos honour (app/arms/dynamixel/practice.py), through the same set-up as
`armserver setup-servos`: four factory servos set up one at a time, then the angler profile
connects to that bus and polls it; the set-up's refusals as error codes with nothing written;
the instructor requirement; a port an arm of the server owns refused with the arm's name."""

from __future__ import annotations

import contextlib
import os
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import httpx
import pytest
from _wait import wait_for

from app.arms.loading import load_profile
from app.config import ArmProfile
from app.web.factory import create_app
from tests.conftest import make_settings

API = "/api/v1/setup-servos"
TEACH = {"Authorization": "Bearer teach"}
OP = {"Authorization": "Bearer op"}
VIEW = {"Authorization": "Bearer view"}
ANGLER = {"x": 2, "y": 1, "theta3": 3, "z": 4}  # the profile's motor ids
#: The rates the servos here run at (the full scan of every rate is the CLI tests').
RATES = [57_600, 1_000_000]
#: How long each rate's broadcast waits, s: generous, as other tests share the two cores.
WINDOW = 0.5
#: A loopback port nothing listens on: the twin arm's link, down and retried.
DEAD_PORT = "socket://127.0.0.1:9"


def twin() -> ArmProfile:
    """An arm (not served: its link is down) whose profile gives joint x the ID of joint y;
    its link owns DEAD_PORT."""
    p = load_profile("angler")
    joints = [j.model_copy(update={"motor_id": 1}) if j.name == "x" else j for j in p.joints]
    return p.model_copy(update={"name": "twin", "joints": joints, "link": p.link.model_copy(
        update={"kind": "serial", "address": DEAD_PORT})})


@contextlib.asynccontextmanager
async def server(*profiles: ArmProfile) -> AsyncIterator[tuple[Any, httpx.AsyncClient]]:
    """The app in process with tokens (no wait for its arms: the set-up needs none ready)."""
    settings = make_settings(operator_tokens="op", viewer_tokens="view",
                             instructor_tokens="teach")
    app = create_app(settings, profiles=list(profiles))
    async with app.router.lifespan_context(app), httpx.AsyncClient(
            transport=httpx.ASGITransport(app=app), base_url="http://armserver.test",
            headers=TEACH, timeout=30.0) as c:
        yield app, c
    assert app.state.internal_errors == 0


async def practice(c: httpx.AsyncClient, servos: int) -> str:
    r = await c.post(f"{API}/practice", json={"servos": servos})
    assert r.status_code == 200, r.text
    assert r.json()["servos"] == [{"id": 1, "baudrate": 57_600}] * servos
    port = r.json()["port"]
    assert os.path.islink(port)  # noqa: ASYNC240 (a stat, no I/O to wait for)
    return str(port)


async def assign(c: httpx.AsyncClient, port: str, joint: str, profile: str = "angler"
                 ) -> httpx.Response:
    return await c.post(f"{API}/assign", json={"port": port, "profile": profile,
                                                "joint": joint, "baudrates": RATES,
                                                "timeout": WINDOW})


async def plugged(c: httpx.AsyncClient) -> list[tuple[int, int]]:
    bus = (await c.get(API)).json()["practice"]
    return [(s["id"], s["baudrate"]) for s in bus["servos"]]


async def test_four_factory_servos_one_at_a_time_then_the_angler_polls_the_bus() -> None:
    async with server(twin()) as (app, c):
        info = (await c.get(API, headers=VIEW)).json()
        assert "angler" in info["profiles"] and "twin" in info["profiles"]
        assert info["ports_in_use"] == {DEAD_PORT: "twin"}
        assert info["practice"] == {"running": False, "port": None, "servos": []}
        port = await practice(c, 1)
        scan = (await c.post(f"{API}/scan", json={"port": port, "profile": "angler",
                                                    "baudrates": RATES, "timeout": WINDOW})).json()
        [servo] = scan["servos"]
        assert (servo["id"], servo["baudrate"], servo["model_name"]) == (1, 57_600, "MX-28(2.0)")
        assert servo["factory"] is True and servo["joint"] is None and servo["torque"] is False
        assert "joint y's ID, but not the profile's 1,000,000 bps" in servo["note"]
        assert scan["todo"] == ["x", "y", "theta3", "z"] and scan["joints"] == ANGLER
        assert scan["profile_baudrate"] == 1_000_000 and scan["collisions"] == []
        for k, joint in enumerate(ANGLER):
            if k:  # the next servo joins the bus beside the ones set up
                r = await c.post(f"{API}/practice/servos")
                assert r.status_code == 200 and len(r.json()["servos"]) == k + 1
            r = await assign(c, port, joint)
            assert r.status_code == 200, r.text
            body = r.json()
            assert body["joint"] == joint and body["servo"]["joint"] == joint
            assert (body["servo"]["id"], body["servo"]["baudrate"]) == (ANGLER[joint], 1_000_000)
            assert body["servo"]["mode"] == 4  # the profile's extended position mode
            assert any(line.startswith(f"joint {joint}: set up and verified: ID "
                                       f"{ANGLER[joint]} at 1,000,000 bps")
                       for line in body["said"]), body["said"]
        assert sorted(await plugged(c)) == sorted((i, 1_000_000) for i in ANGLER.values())
        scan = (await c.post(f"{API}/scan", json={"port": port, "profile": "angler",
                                                    "baudrates": RATES, "timeout": WINDOW})).json()
        assert {s["id"]: s["joint"] for s in scan["servos"]} == {i: j for j, i in ANGLER.items()}
        assert scan["todo"] == []
        # nothing left to set up: the next assignment finds only other joints' servos
        r = await assign(c, port, "x")
        assert r.status_code == 200  # x's own servo at its ID and rate is x's again
        r = await assign(c, port, "y")
        assert r.status_code == 200
        # the bus the set-up made is one the angler profile connects to and polls
        p = load_profile("angler")
        angler = p.model_copy(update={"link": p.link.model_copy(
            update={"kind": "serial", "address": port})})
        arm = create_app(make_settings(), profiles=[angler])
        async with arm.router.lifespan_context(arm), httpx.AsyncClient(
                transport=httpx.ASGITransport(app=arm), base_url="http://armserver.test") as a:
            svc = arm.state.services["angler"]
            await wait_for(lambda: svc.hub.latest is not None and not svc.driver.stale,
                           what="the angler polling the practice bus")
            detail = (await a.get("/api/v1/arms/angler")).json()
            assert detail["link"]["state"] == "up", detail["link"]
            polls = svc.driver.stats["polls"]
            await wait_for(lambda: svc.driver.stats["polls"] >= polls + 5, what="more polls")
        assert arm.state.internal_errors == 0
        r = await c.delete(f"{API}/practice")
        assert r.json() == {"running": False, "port": None, "servos": []}


async def test_refusals_have_their_codes_and_write_nothing(tmp_path: Path) -> None:
    async with server(twin()) as (_app, c):
        port = await practice(c, 0)
        r = await assign(c, port, "x")
        assert r.status_code == 409 and r.json()["code"] == "no_servo", r.text
        assert "nothing answered" in r.json()["detail"]
        scan = (await c.post(f"{API}/scan", json={"port": port, "profile": "angler",
                                                    "baudrates": RATES, "timeout": WINDOW})).json()
        assert scan["servos"] == [] and scan["collisions"] == []
        # two factory servos on one ID: their answers collide
        port = await practice(c, 2)
        r = await assign(c, port, "x")
        assert r.status_code == 409 and r.json()["code"] == "several_servos", r.text
        assert "connect one servo at a time" in r.json()["detail"]
        assert await plugged(c) == [(1, 57_600), (1, 57_600)]  # nothing written
        scan = (await c.post(f"{API}/scan", json={"port": port, "profile": "angler",
                                                    "baudrates": RATES, "timeout": WINDOW})).json()
        assert scan["collisions"] and "two servos on one ID" in scan["collisions"][0]
        # a profile that gives joint x the ID of joint y: refused before the port is opened
        port = await practice(c, 1)
        r = await assign(c, port, "x", profile="twin")
        assert r.status_code == 409 and r.json()["code"] == "id_in_use", r.text
        assert "ID 1 is in use by joint y" in r.json()["detail"]
        assert await plugged(c) == [(1, 57_600)]
        # bad requests: 422 with the reason
        regular = tmp_path / "not-a-tty"
        regular.write_text("")
        for body, words in [
            ({"port": port, "profile": "angler", "joint": "w"}, "has no joint 'w'"),
            ({"port": port, "profile": "rbe3001", "joint": "x"}, "no profile 'rbe3001'"),
            ({"port": port, "profile": "nope", "joint": "x"}, "no profile 'nope'"),
            ({"port": "socket://10.1.2.3:4000", "profile": "angler", "joint": "x"}, "loopback"),
            ({"port": str(tmp_path / "absent"), "profile": "angler", "joint": "x"}, "no port"),
            ({"port": str(regular), "profile": "angler", "joint": "x"}, "not a serial device"),
            ({"port": "COM3", "profile": "angler", "joint": "x"}, None),
            ({"port": port, "profile": "angler", "joint": "x", "baudrates": [12345]}, None),
        ]:
            r = await c.post(f"{API}/assign", json=body)
            assert r.status_code == 422, (body, r.text)
            assert r.json()["code"] == "invalid_request", r.text
            if words:
                assert words in r.json()["detail"], r.text
        assert await plugged(c) == [(1, 57_600)]
        # a port that is an arm's link: 409 naming the arm, nothing opened
        for route in ("scan", "assign"):
            r = await c.post(f"{API}/{route}", json={"port": DEAD_PORT, "profile": "angler",
                                                      "joint": "x"} if route == "assign" else
                             {"port": DEAD_PORT, "profile": "angler"})
            assert r.status_code == 409 and r.json()["code"] == "port_in_use", r.text
            assert "arm twin" in r.json()["detail"]


async def test_a_pty_an_arm_owns_is_refused_through_its_symlinks(tmp_path: Path) -> None:
    """The arm's link named by one path, the request by another (a by-id symlink)."""
    from app.arms.dynamixel.sim_bus import DynamixelBus
    from app.sim.servers import serve_pty

    srv = await serve_pty(DynamixelBus(ids=(1, 2, 3, 4)), tmp_path / "ttyARM")
    alias = tmp_path / "by-id-U2D2"
    os.symlink(tmp_path / "ttyARM", alias)
    p = load_profile("angler")
    arm = p.model_copy(update={"link": p.link.model_copy(
        update={"kind": "serial", "address": str(tmp_path / "ttyARM")})})
    try:
        async with server(arm) as (_app, c):
            r = await c.post(f"{API}/scan", json={"port": str(alias), "profile": "angler"})
            assert r.status_code == 409 and r.json()["code"] == "port_in_use", r.text
            assert "arm angler" in r.json()["detail"]
    finally:
        await srv.close()


async def test_a_port_another_program_holds_is_refused() -> None:
    """A link opens its port exclusively (app/links/serial.py), as the set-up does: a port
    held elsewhere (an arm on another worker) is 409 port_in_use, nothing written."""
    import serial

    async with server() as (_app, c):
        port = await practice(c, 1)
        held = serial.serial_for_url(port, baudrate=1_000_000, exclusive=True)
        try:
            r = await assign(c, port, "x")
            assert r.status_code == 409 and r.json()["code"] == "port_in_use", r.text
            assert "held by another program" in r.json()["detail"]
        finally:
            held.close()
        assert await plugged(c) == [(1, 57_600)]


@pytest.mark.parametrize(("method", "path", "body"), [
    ("POST", "/scan", {"port": "socket://127.0.0.1:9", "profile": "angler"}),
    ("POST", "/assign", {"port": "socket://127.0.0.1:9", "profile": "angler", "joint": "x"}),
    ("POST", "/practice", {"servos": 1}),
    ("POST", "/practice/servos", None),
    ("DELETE", "/practice", None),
])
async def test_an_instructor_sets_servos_up(method: str, path: str, body: Any) -> None:
    async with server() as (_app, c):
        for who, status in ((OP, 403), (VIEW, 403), ({"Authorization": ""}, 401)):
            r = await c.request(method, API + path, json=body, headers=who)
            assert r.status_code == status, (who, r.text)
        assert (await c.get(API, headers=VIEW)).status_code == 200
        assert (await c.get(API, headers={"Authorization": ""})).status_code == 401
        r = await c.request(method, API + path, json=body)
        # the instructor passes the gate: what follows is the route's own answer
        assert r.status_code not in (401, 403), r.text


async def test_plugging_needs_a_running_practice_bus() -> None:
    async with server() as (_app, c):
        r = await c.post(f"{API}/practice/servos")
        assert r.status_code == 409 and r.json()["code"] == "conflict"
        await practice(c, 8)
        r = await c.post(f"{API}/practice/servos")
        assert r.status_code == 409 and "8 servos at most" in r.json()["detail"]
