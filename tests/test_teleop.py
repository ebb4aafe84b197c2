"""Teleoperation between two simulated OpenManipulator-X arms (config/teleop_omx.toml), each
behind its real link, through the HTTP API: the follower tracks a leader moved by a planned
move (joints and tip mappings), holds on a stale leader and on a refused target, the session
ends on either arm's estop and on DELETE, and the refusals (lease, leader == follower,
unknown arms, the rate's bounds, a follower already following)."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import orjson
import pytest
from _wait import held_still, wait_for
from fastapi import FastAPI

from app.config import FaultConfig
from app.runtime.control_thread import on_home
from app.service import ArmService
from tests.conftest import make_settings, running_client

API = "/api/v1"
CONFIG = Path(__file__).resolve().parents[1] / "config" / "teleop_omx.toml"
TICK = 2 * np.pi / 4096  # rad: one encoder tick of the XM430
TOL = 8 * TICK  # the default settle tolerance
START = {"leader": "leader", "follower": "follower", "rate_hz": 50}


@pytest.fixture()
async def pair() -> AsyncIterator[tuple[FastAPI, httpx.AsyncClient]]:
    async with running_client(make_settings(config=str(CONFIG))) as p:
        yield p


def arm_of(app: FastAPI, name: str) -> ArmService:
    arm: ArmService = app.state.services[name]
    return arm


async def session(c: httpx.AsyncClient, sid: str) -> dict[str, Any]:
    r = await c.get(f"{API}/teleop")
    assert r.status_code == 200, r.text
    found = [t for t in r.json() if t["id"] == sid]
    assert len(found) == 1
    return dict(found[0])


async def start(c: httpx.AsyncClient, **over: Any) -> dict[str, Any]:
    r = await c.post(f"{API}/teleop", json={**START, **over})
    assert r.status_code == 201, r.text
    return dict(r.json())


def joint_path_distance(points: np.ndarray, path: np.ndarray) -> np.ndarray:
    """Each point's distance (rad, Euclidean over the joints) to the polyline `path`."""
    a, b = path[:-1], path[1:]
    ab = b - a
    out = []
    for p in points:
        t = np.clip(np.einsum("ij,ij->i", p - a, ab)
                    / np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-18), 0.0, 1.0)
        out.append(float(np.min(np.linalg.norm(a + t[:, None] * ab - p, axis=1))))
    return np.asarray(out)


async def test_follower_tracks_a_leader_moved_by_a_planned_move(
        pair: tuple[FastAPI, httpx.AsyncClient]) -> None:
    app, c = pair
    leader, follower = arm_of(app, "leader"), arm_of(app, "follower")
    t = await start(c)
    assert t["status"] == "running" and t["rate_hz"] == 50 and t["mapping"] == "joints"
    await wait_for(lambda: follower.positions is not None
                   and np.allclose(follower.positions, leader.positions, atol=TOL),
                   what="the follower where the leader is")
    lsub, fsub = leader.subscribe(4000), follower.subscribe(4000)
    try:
        goal = [0.6, -0.5, 0.4, 0.7]
        r = await c.post(f"{API}/arms/leader/move/joints", json={"positions": goal,
                                                                 "wait": True})
        assert r.status_code == 200 and r.json()["status"] == "done", r.text
        await wait_for(lambda: np.allclose(follower.positions, goal, atol=TOL),
                       what="the follower at the leader's goal")
        lq = np.array([orjson.loads(x)["positions"] for x in lsub.take()[0]], dtype=float)
        fq = np.array([orjson.loads(x)["positions"] for x in fsub.take()[0]], dtype=float)
    finally:
        lsub.close()
        fsub.close()
    # the follower went the leader's way: every sample within one period's motion (50 Hz, at
    # the speed the leader's plan may reach) of the leader's joint path (each servo follows
    # its goal with its own lag, so the follower is off the straight joint line by a little)
    d = joint_path_distance(fq, lq)
    one_period = float(np.max(leader.model.vmax)) * leader.profile.tracking_margin / 50
    assert float(np.max(d)) < one_period, (
        f"the follower left the leader's path by {np.max(d):.4f} rad (one period: "
        f"{one_period:.4f})")
    figures = await session(c, t["id"])
    assert figures["commands"] > 25 and figures["status"] == "running"
    lat = figures["latency_ms"]
    assert lat is not None and 0.0 <= lat["p50"] <= lat["p99"] < float("inf")
    assert figures["achieved_hz"] > 0
    r = await c.delete(f"{API}/teleop/{t['id']}")
    assert r.status_code == 200 and r.json()["status"] == "ended", r.text
    assert "stopped by" in r.json()["reason"]
    # the follower holds where it is, and no longer follows
    here = np.array(follower.positions, dtype=float)
    r = await c.post(f"{API}/arms/leader/move/joints", json={"positions": [0.0, -0.3, 0.3, 0.5],
                                                             "wait": True})
    assert r.status_code == 200, r.text
    np.testing.assert_allclose(follower.positions, here, atol=TOL)
    assert (await session(c, t["id"]))["status"] == "ended"


async def test_tip_mapping_puts_the_followers_tip_on_the_leaders(
        pair: tuple[FastAPI, httpx.AsyncClient]) -> None:
    app, c = pair
    leader, follower = arm_of(app, "leader"), arm_of(app, "follower")
    t = await start(c, mapping="tip", rate_hz=30)
    assert t["mapping"] == "tip"
    r = await c.post(f"{API}/arms/leader/move/pose", json={"x": 0.2, "y": 0.05, "z": 0.15,
                                                           "wait": True})
    assert r.status_code == 200 and r.json()["status"] == "done", r.text

    def tips_agree() -> bool:
        lp = np.asarray(leader.model.fk(leader.positions))
        fp = np.asarray(follower.model.fk(follower.positions))
        return bool(np.linalg.norm(lp - fp) < 0.002)
    await wait_for(tips_agree, what="the follower's tip on the leader's")
    assert (await c.delete(f"{API}/teleop/{t['id']}")).status_code == 200


@pytest.mark.parametrize("which", ["follower", "leader"])
async def test_estop_on_either_arm_ends_the_session(
        pair: tuple[FastAPI, httpx.AsyncClient], which: str) -> None:
    app, c = pair
    follower = arm_of(app, "follower")
    t = await start(c)

    async def commanding() -> bool:
        return bool((await session(c, t["id"]))["commands"] > 5)
    await wait_for(commanding, what="the session commanding the follower")
    r = await c.post(f"{API}/arms/{which}/estop")
    assert r.status_code == 200, r.text

    async def ended() -> dict[str, Any] | None:
        s = await session(c, t["id"])
        return s if s["status"] == "ended" else None
    s = await wait_for(ended, what="the session ended by the estop")
    assert s["reason"] == f"emergency stop on {which}"
    assert s["achieved_hz"] == 0.0
    await held_still(lambda: follower.positions, TOL)
    # a new session with either arm latched is refused
    r = await c.post(f"{API}/teleop", json=START)
    assert r.status_code == 409 and r.json()["code"] == "estop_latched", r.text
    assert (await c.delete(f"{API}/arms/{which}/estop")).status_code == 200


async def test_a_stale_leader_holds_the_follower(pair: tuple[FastAPI, httpx.AsyncClient]) -> None:
    app, c = pair
    leader, follower = arm_of(app, "leader"), arm_of(app, "follower")
    t = await start(c)
    await wait_for(lambda: np.allclose(follower.positions, leader.positions, atol=TOL))
    assert leader.link_status().kind == "sim"

    async def set_drop(rate: float) -> None:
        # the leader's simulated link loses every reply: its samples go stale, then stop
        async def apply() -> None:
            leader.driver.link.set_faults(FaultConfig(drop=rate))  # the simulator's injection
        await on_home(leader.home_loop, apply)

    await set_drop(1.0)
    before = await session(c, t["id"])

    async def holding() -> dict[str, Any] | None:
        s = await session(c, t["id"])
        return s if s["holds"] >= before["holds"] + 20 else None
    held = await wait_for(holding, what="20 holds on the stale leader")
    assert held["status"] == "running" and held["held"] == "deadman"
    # no command while the leader is stale: the count stands
    again = await wait_for(holding)
    assert again["commands"] == held["commands"]
    await held_still(lambda: follower.positions, TOL)
    await set_drop(0.0)

    async def commanding() -> dict[str, Any] | None:
        s = await session(c, t["id"])
        return s if s["commands"] > held["commands"] + 10 else None
    await wait_for(commanding, what="commands again once the leader is fresh")
    assert (await c.delete(f"{API}/teleop/{t['id']}")).status_code == 200


async def test_a_refused_target_holds_and_the_session_goes_on(
        pair: tuple[FastAPI, httpx.AsyncClient]) -> None:
    app, c = pair
    leader, follower = arm_of(app, "leader"), arm_of(app, "follower")
    goal = [0.6, -0.5, 0.4, 0.7]
    p = np.asarray(follower.model.fk(np.array(goal)), dtype=float)
    box = {"name": "cup", "min": dict(zip("xyz", (p - 0.02).tolist(), strict=True)),
           "max": dict(zip("xyz", (p + 0.02).tolist(), strict=True))}
    r = await c.put(f"{API}/arms/follower/safety", json={"zones": [box]})
    assert r.status_code == 200, r.text
    t = await start(c)
    r = await c.post(f"{API}/arms/leader/move/joints", json={"positions": goal, "wait": True})
    assert r.status_code == 200, r.text

    async def refused() -> dict[str, Any] | None:
        s = await session(c, t["id"])
        return s if s["last_refusal"] == "keep_out" and s["holds"] > 5 else None
    s = await wait_for(refused, what="the follower's guard refusing the zone")
    assert s["status"] == "running" and s["held"] == "refused:keep_out"
    here = await held_still(lambda: follower.positions, TOL)
    tip = np.asarray(follower.model.fk(here), dtype=float)
    assert not np.all(np.abs(tip - p) < 0.02), "the follower's tip entered the zone"
    assert not np.allclose(leader.positions, here, atol=0.05)
    assert (await c.delete(f"{API}/teleop/{t['id']}")).status_code == 200


async def test_refusals(pair: tuple[FastAPI, httpx.AsyncClient]) -> None:
    _, c = pair

    async def refused(body: dict[str, Any], status: int, code: str) -> None:
        r = await c.post(f"{API}/teleop", json=body)
        assert r.status_code == status and r.json()["code"] == code, r.text

    await refused({**START, "follower": "leader"}, 422, "invalid_request")
    await refused({**START, "leader": "nope"}, 404, "unknown_arm")
    await refused({**START, "follower": "nope"}, 404, "unknown_arm")
    for rate in (29.9, 100.5, 0, -50):
        await refused({**START, "rate_hz": rate}, 422, "invalid_request")
    await refused({**START, "scale": [1.0, 1.0]}, 422, "invalid_request")
    await refused({**START, "mapping": "cartesian"}, 422, "invalid_request")
    r = await c.delete(f"{API}/teleop/t99-00000000")
    assert r.status_code == 404 and r.json()["code"] == "not_found", r.text
    assert (await c.get(f"{API}/teleop")).json() == []
    # one session per follower, even for two requests at once
    both = await asyncio.gather(c.post(f"{API}/teleop", json=START),
                                c.post(f"{API}/teleop", json=START))
    assert sorted(r.status_code for r in both) == [201, 409], [r.text for r in both]
    t = next(r.json() for r in both if r.status_code == 201)
    assert next(r.json() for r in both if r.status_code == 409)["code"] == "busy"
    await refused(START, 409, "busy")
    assert (await c.delete(f"{API}/teleop/{t['id']}")).status_code == 200


async def test_the_followers_lease_is_needed(pair: tuple[FastAPI, httpx.AsyncClient]) -> None:
    _, c = pair
    r = await c.post(f"{API}/arms/follower/lease")
    assert r.status_code in (200, 201), r.text
    lease = r.json()["id"]
    r = await c.post(f"{API}/teleop", json=START)
    assert r.status_code == 409 and r.json()["code"] == "leased", r.text
    r = await c.post(f"{API}/teleop", json=START, headers={"X-Arm-Lease": "not-it"})
    assert r.status_code == 409 and r.json()["code"] == "leased", r.text
    assert (await c.get(f"{API}/teleop")).json() == []
    # the leader's lease is not asked for: the session does not move the leader
    r = await c.post(f"{API}/teleop", json=START, headers={"X-Arm-Lease": lease})
    assert r.status_code == 201, r.text
    sid = r.json()["id"]
    assert (await session(c, sid))["status"] == "running"
    # the lease given up and another taken: the session ends, the follower holds
    r = await c.delete(f"{API}/arms/follower/lease/{lease}", headers={"X-Arm-Lease": lease})
    assert r.status_code in (200, 204), r.text
    r = await c.post(f"{API}/arms/follower/lease")
    assert r.status_code in (200, 201) and r.json()["id"] != lease, r.text

    async def ended() -> dict[str, Any] | None:
        s = await session(c, sid)
        return s if s["status"] == "ended" else None
    s = await wait_for(ended, what="the session ended by the new lease")
    assert s["reason"] == "the follower's lease is another client's now"


async def test_a_stop_on_the_follower_ends_the_session(
        pair: tuple[FastAPI, httpx.AsyncClient]) -> None:
    app, c = pair
    follower = arm_of(app, "follower")
    t = await start(c)
    r = await c.post(f"{API}/arms/follower/stop")
    assert r.status_code == 200, r.text

    async def ended() -> dict[str, Any] | None:
        s = await session(c, t["id"])
        return s if s["status"] == "ended" else None
    s = await wait_for(ended, what="the session ended by the follower's stop")
    assert s["reason"] == "follower stopped (POST /stop)"
    here = await held_still(lambda: follower.positions, TOL)
    r = await c.post(f"{API}/arms/leader/move/joints", json={"positions": [0.4, -0.3, 0.2, 0.5],
                                                             "wait": True})
    assert r.status_code == 200, r.text
    np.testing.assert_allclose(follower.positions, here, atol=TOL)
