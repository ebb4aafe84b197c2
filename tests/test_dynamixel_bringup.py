"""Issue 24's day-one items on the simulated hardware: the inverse-velocity route (design
document section 4.2) checked against finite differences of the forward kinematics, and its
422 near a singularity; stale queue entries dropped at start; a bus at 57,600 bps polled at
the rate it carries; a link at the wrong baud rate saying where the servos answer."""

from __future__ import annotations

import asyncio
import logging
import time
from pathlib import Path

import httpx
import numpy as np
import pytest
from _wait import wait_for

from app.arms.dynamixel.bus_rate import poll_bytes, poll_cost_s, poll_rate
from app.arms.dynamixel.sim_bus import DynamixelBus
from app.arms.loading import load_profile
from app.config import ArmProfile
from app.sim.servers import serve_pty
from app.web.factory import create_app
from tests.conftest import make_settings, running_client

API = "/api/v1"

STEP = 1e-6  # joint step of the finite differences, rad or m


async def _fk(client: httpx.AsyncClient, arm: str, q: np.ndarray) -> np.ndarray:
    r = await client.post(f"{API}/arms/{arm}/kinematics/forward",
                          json={"positions": [float(v) for v in q]})
    assert r.status_code == 200, r.text
    tip = r.json()["tip"]
    return np.array([tip["x"], tip["y"], tip["z"]])


@pytest.mark.parametrize(("arm", "q", "v"), [
    ("rbe3001", [0.3, 0.6, -0.4], [0.01, -0.02, 0.015]),
    ("angler", [0.01, -0.02, 0.5, 0.05], [0.002, -0.001, 0.003]),
])
async def test_inverse_velocity_matches_finite_differences_of_fk(
        app_client: httpx.AsyncClient, arm: str, q: list[float], v: list[float]) -> None:
    r = await app_client.post(f"{API}/arms/{arm}/kinematics/inverse-velocity",
                              json={"positions": q, "velocity": dict(zip("xyz", v, strict=True))})
    assert r.status_code == 200, r.text
    body = r.json()
    qd = np.array(body["velocities"])
    assert qd.shape == (len(q),)
    # the tip moves at v when the joints move at qd: (fk(q + h qd) - fk(q - h qd)) / 2h
    q0 = np.array(q)
    dt = STEP / max(float(np.max(np.abs(qd))), 1e-9)
    tip_rate = (await _fk(app_client, arm, q0 + dt * qd)
                - await _fk(app_client, arm, q0 - dt * qd)) / (2 * dt)
    np.testing.assert_allclose(tip_rate, v, atol=1e-6)
    assert body["condition"] >= 1.0
    tv = body["tip_velocity"]
    np.testing.assert_allclose([tv["x"], tv["y"], tv["z"]], v, atol=1e-12)
    if arm == "angler":  # four joints, three tip coordinates: the least-norm solution
        jac = np.array((await app_client.post(
            f"{API}/arms/{arm}/kinematics/forward", json={"positions": q})).json()["jacobian"])
        np.testing.assert_allclose(qd, jac.T @ np.linalg.solve(jac @ jac.T, v), atol=1e-12)


async def test_inverse_velocity_near_a_singularity_is_422_with_the_reason(
        app_client: httpx.AsyncClient) -> None:
    # rbe3001 stretched out (q3 = 90 deg: links 2 and 3 in line): the Jacobian loses rank
    r = await app_client.post(f"{API}/arms/rbe3001/kinematics/inverse-velocity",
                              json={"positions": [0.0, 0.5, 1.5707963267948966],
                                    "velocity": {"x": 0.01, "y": 0.0, "z": 0.0}})
    assert r.status_code == 422, r.text
    assert r.json()["code"] == "unreachable"
    assert "near a singularity" in r.json()["detail"]
    r = await app_client.post(f"{API}/arms/rbe3001/kinematics/inverse-velocity",
                              json={"positions": [0.0, 0.5], "velocity": {"x": 0, "y": 0, "z": 0}})
    assert r.status_code == 422, r.text


# ------------------------------------------------------------------ stale queue (item 11)

ALICE, BOB, TEACH = "tok-alice-1", "tok-bob-2", "tok-teach-4"


def _h(token: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {token}"}


async def test_queue_entries_of_names_no_token_has_are_dropped_at_start(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """A data folder left by a server with tokens: on start, an entry of a name no current
    token has is dropped and logged; an open server keeps none, and answers a move, not 409
    `leased`."""
    data = str(tmp_path / "data")
    tokened = {"operator_tokens": f"alice:{ALICE},bob:{BOB}", "instructor_tokens":
               f"teach:{TEACH}", "claim_s": 30.0, "slot_s": 60.0, "data_dir": data}
    arm = "rbe3001"
    async with running_client(make_settings(**tokened)) as (_, c):
        a = (await c.post(f"{API}/arms/{arm}/queue", headers=_h(ALICE))).json()
        b = (await c.post(f"{API}/arms/{arm}/queue", headers=_h(BOB))).json()
        assert a["name"] == "alice" and b["name"] == "bob"
    # alice's token is gone: her entry is dropped, bob's kept
    bob_only = {**tokened, "operator_tokens": f"bob:{BOB}"}
    with caplog.at_level(logging.WARNING, logger="app.classroom.queue"):
        async with running_client(make_settings(**bob_only)) as (_, c):
            q = (await c.get(f"{API}/arms/{arm}/queue", headers=_h(TEACH))).json()
            assert [e["name"] for e in q["entries"]] == ["bob"]
    assert any("'alice' dropped" in r.getMessage() and "no current token" in r.getMessage()
               for r in caplog.records)
    # an open server (the same data folder, `make run`): no queue, and a move is answered
    async with running_client(make_settings(data_dir=data, claim_s=30.0)) as (app, c):
        q = (await c.get(f"{API}/arms/{arm}/queue")).json()
        assert q["entries"] == []
        here = [float(v) for v in app.state.services[arm].driver.positions]
        r = await c.post(f"{API}/arms/{arm}/move/joints", json={"positions": here, "wait": True})
        assert r.status_code == 200, r.text
        assert r.json()["status"] == "done"


# ------------------------------------------------------------------ the bus's rate (item 3)


def _angler_at(baudrate: int, **link: object) -> ArmProfile:
    p = load_profile("angler")
    return p.model_copy(update={"link": p.link.model_copy(
        update={"baudrate": baudrate, "homed_at_start": True, **link})})


def test_poll_cost_at_57600_is_the_issue_figure() -> None:
    # 4 servos: 18 bytes out, 4 x 25 back; 10 bits a byte; the e-manual's 500 us return delay
    assert poll_bytes(4) == 118
    assert poll_cost_s(4, 57_600, None) == pytest.approx(118 * 10 / 57_600 + 4 * 500e-6)
    assert 0.020 < poll_cost_s(4, 57_600, 0.0) < 0.021  # "about 20 ms" (issue 24)
    hz, warning = poll_rate(200.0, 4, 57_600, 0.0)
    assert hz == 39.0 and warning is not None and "39 Hz" in warning
    assert poll_rate(200.0, 4, 1_000_000, 0.0) == (200.0, None)  # 1 Mbps carries 200 Hz


async def test_a_bus_at_57600_polls_at_the_rate_it_carries(
        caplog: pytest.LogCaptureFixture) -> None:
    profile = _angler_at(57_600)
    expected, _ = poll_rate(profile.link.poll_hz, 4, 57_600, profile.link.return_delay_us)
    with caplog.at_level(logging.WARNING, logger="app.arms.dynamixel.servos"):
        async with running_client(profiles=[profile]) as (app, c):
            svc = app.state.services["angler"]
            await wait_for(lambda: svc.driver.profile.link.poll_hz == expected,
                           what="the bus's poll rate")
            detail = (await c.get(f"{API}/arms/angler")).json()
            assert detail["poll_hz"] == expected == 39.0
            polls0, t0 = svc.driver.stats["polls"], time.monotonic()
            await asyncio.sleep(1.0)  # a rate over a window: this sleep is the measurement
            rate = (svc.driver.stats["polls"] - polls0) / (time.monotonic() - t0)
            # generous: a loaded two-core machine may fall behind, never run ahead
            assert 0.5 * expected <= rate <= 1.1 * expected, rate
    assert any("polling at 39 Hz, not the profile's 200 Hz" in r.getMessage()
               for r in caplog.records)


async def test_a_mismatched_baud_rate_says_what_answers(tmp_path: Path) -> None:
    """Servos set up but left at 57,600 on a pty: the link at 1 Mbps hears nothing, scans the
    other rates and says where they answer (the arm's detail and log)."""
    bus = DynamixelBus(ids=(1, 2, 3, 4), baudrate=1_000_000, operating_modes={1: 4, 2: 4, 4: 4})
    for s in bus.servos:
        s.set("baud_rate", 1)  # 57,600
    path = tmp_path / "ttyDXL"
    server = await serve_pty(bus, path)
    profile = _angler_at(1_000_000, kind="serial", address=str(path))
    app = create_app(make_settings(), profiles=[profile])  # never ready: no wait_ready
    try:
        async with app.router.lifespan_context(app), httpx.AsyncClient(
                transport=httpx.ASGITransport(app=app), base_url="http://armserver.test") as c:
            svc = app.state.services["angler"]
            said = ("no servo answers at the profile's 1,000,000 bps; servos answer at 57,600 "
                    "bps (ID 1, 2, 3, 4): run armserver setup-servos, or set link.baudrate = "
                    "57600")
            # each attempt to open the link scans anew (backoff at most 2 s) and says what that
            # scan heard: on a busy machine one servo's reply on the pty can come after the
            # window (a clean clone's run heard ID 1, 2, 3), a later scan hears all four
            await wait_for(lambda: said in (svc.driver.link.last_error or ""),
                           what="the scan's finding, every servo in it")
            detail = (await c.get(f"{API}/arms/angler")).json()
            assert said in detail["link"]["last_error"], detail["link"]
            assert detail["link"]["state"] != "up"
    finally:
        await server.close()
