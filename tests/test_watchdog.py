"""The motion watchdog, through the API over the simulated arms with faults injected on their
links at run time: a device that stops answering mid-move fails the motion with the device's
code (`device_timeout`) and an event `watchdog`, and the arm holds where it was; a link cut
mid-move fails it with `link_down`. Nothing is reported done that was not (API.md)."""

from __future__ import annotations

import asyncio
import json
import time
from typing import Any

import httpx
import numpy as np
import pytest
from _wait import wait_for
from conftest import running_client
from fastapi import FastAPI

from app.config import FaultConfig
from app.links.sim import SimLink

API = "/api/v1"
#: Shortest move to cut in the middle, s (the far targets take longer at full speed).
MOVE_S = 1.2
#: How far into the move the fault is injected (its progress, 0..1): under way, well short of
#: the end. Waited for, not timed: a busy machine starts a move late.
FAULT_AT = 0.1
#: The fault must be noticed within MOVE_S - FAULT_AT_S, s: well before the shortest move,
#: faulted at FAULT_AT of its way, would have ended.
FAULT_AT_S = 0.4


def _far_target(svc: Any) -> list[float]:
    """A target within the limits, far (in every joint) from where the arm is."""
    lo, hi = svc.model.lower, svc.model.upper
    q = svc.driver.positions
    return [float(lo[k] + 0.2 * (hi[k] - lo[k])) if q[k] > (lo[k] + hi[k]) / 2
            else float(hi[k] - 0.2 * (hi[k] - lo[k])) for k in range(len(q))]


async def _motion(client: httpx.AsyncClient, arm: str, mid: str) -> dict[str, Any]:
    r = await client.get(f"{API}/arms/{arm}/motions/{mid}")
    assert r.status_code == 200, r.text
    return r.json()  # type: ignore[no-any-return]


async def _under_way(client: httpx.AsyncClient, arm: str, mid: str) -> None:
    async def moving() -> bool:
        m = await _motion(client, arm, mid)
        return m["status"] == "running" and m["progress"] >= FAULT_AT

    await wait_for(moving, what=f"motion {mid} under way")


async def _wait_ended(client: httpx.AsyncClient, arm: str, mid: str,
                      timeout: float = 10.0) -> dict[str, Any]:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        m = await _motion(client, arm, mid)
        if m["status"] not in ("queued", "running"):
            return m
        await asyncio.sleep(0.02)
    raise AssertionError(f"motion {mid} did not end: {m}")


async def _start_move(client: httpx.AsyncClient, arm: str, target: list[float]) -> str:
    r = await client.post(f"{API}/arms/{arm}/move/joints", json={"positions": target})
    assert r.status_code == 202, r.text
    assert r.json()["planned_duration"] >= MOVE_S, r.json()  # long enough to cut
    return r.json()["id"]  # type: ignore[no-any-return]


def _events(sub: Any) -> list[dict[str, Any]]:
    _, events, _ = sub.take()
    return [json.loads(e) for e in events]


async def _events_with(sub: Any, names: set[str], timeout: float = 3.0) -> list[dict[str, Any]]:
    """The events so far, waiting (bounded) until every one of `names` is among them: events
    cross from the control thread to the subscribers' loop with `call_soon_threadsafe`, so
    the motion's end can be read over HTTP before its events have arrived."""
    out: list[dict[str, Any]] = []
    deadline = time.monotonic() + timeout
    while True:
        out += _events(sub)
        if names <= {e["event"] for e in out} or time.monotonic() > deadline:
            return out
        await asyncio.sleep(0.02)


async def _steady(svc: Any, window_s: float = 0.5, timeout: float = 5.0) -> np.ndarray:
    """Positions once the device answers again and the arm has stopped moving."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if not svc.driver.stale and svc.driver.positions is not None:
            q0 = svc.driver.positions.copy()
            await asyncio.sleep(window_s)
            q1 = svc.driver.positions
            if not svc.driver.stale and np.all(np.abs(q1 - q0) < _tol(svc) / 2):
                return q1.copy()
        else:
            await asyncio.sleep(0.02)
    raise AssertionError(f"{svc.name} never held still: {svc.driver.positions}")


def _tol(svc: Any) -> np.ndarray:
    return np.array([0.03 if k == "revolute" else 0.002 for k in svc.model.kinds])


@pytest.mark.parametrize("arm", ["rbe3001", "angler"])
async def test_device_silent_mid_move_fails_with_device_timeout_and_holds(arm: str) -> None:
    async with running_client() as (app, client):
        svc = app.state.services[arm]
        link: SimLink = svc.driver.link
        sub = svc.hub.subscribe()
        try:
            target = _far_target(svc)
            start = svc.driver.positions.copy()
            mid = await _start_move(client, arm, target)
            await _under_way(client, arm, mid)
            assert (await _motion(client, arm, mid))["status"] == "running"
            link.set_faults(FaultConfig(drop=1.0))  # the device hears us, never answers
            t_fault = time.monotonic()
            m = await _wait_ended(client, arm, mid)
            detected_s = time.monotonic() - t_fault
            assert m["status"] == "failed" and m["code"] == "device_timeout", m
            assert m["reason"]
            assert detected_s < MOVE_S - FAULT_AT_S, f"noticed only after {detected_s:.2f} s"
            events = await _events_with(sub, {"watchdog", "motion_ended"})
            dog = [e for e in events if e["event"] == "watchdog"]
            assert dog and dog[0]["data"]["id"] == mid, [e["event"] for e in events]
            assert dog[0]["data"]["code"] == "device_timeout"
            ended = [e for e in events if e["event"] == "motion_ended"]
            assert ended and ended[0]["data"]["status"] == "failed"
            assert all(e["data"].get("status") != "done" for e in ended)

            link.set_faults(FaultConfig())  # the device answers again
            held = await _steady(svc)
            await asyncio.sleep(0.5)  # under test: it holds there for 0.5 s
            assert np.all(np.abs(svc.driver.positions - held) < _tol(svc)), "arm moved on"
            # it held near where it was, not at the target it was heading for
            assert np.max(np.abs(held - np.array(target)) / (svc.model.upper - svc.model.lower)
                          ) > 0.1, (held, target, start)
            assert svc.motion.current is None
            state = (await client.get(f"{API}/arms/{arm}/state")).json()
            assert state["motion"]["id"] == mid and state["motion"]["status"] == "failed"
            assert not state["stale"] and state["link"] == "up"
            # and the arm still works
            r = await client.post(f"{API}/arms/{arm}/move/joints",
                                  json={"positions": [float(v) for v in held], "wait": True})
            assert r.status_code == 200 and r.json()["status"] == "done", r.text
        finally:
            sub.close()


@pytest.mark.parametrize("arm", ["rbe3001", "angler"])
async def test_link_lost_mid_move_fails_with_link_down(arm: str) -> None:
    async with running_client() as (app, client):
        svc = app.state.services[arm]
        link: SimLink = svc.driver.link
        sub = svc.hub.subscribe()
        try:
            mid = await _start_move(client, arm, _far_target(svc))
            await _under_way(client, arm, mid)
            link.set_faults(FaultConfig(reconnect_after_s=0.5))
            link.disconnect()
            m = await _wait_ended(client, arm, mid)
            assert m["status"] == "failed" and m["code"] == "link_down", m
            names = [e["event"] for e in await _events_with(sub, {"watchdog", "link_lost"})]
            assert "watchdog" in names and "link_lost" in names, names
            assert await svc.driver.wait_connected(5.0)
            await _steady(svc)
            assert svc.motion.current is None
            r = await client.get(f"{API}/health")
            assert r.json()["arms"][arm]["state"] == "up"
        finally:
            sub.close()


async def test_corrupt_replies_mid_move_fail_with_the_devices_code() -> None:
    """Every reply corrupted: the motion fails with `corrupt_reply` (the device's own code),
    never `done`."""
    async with running_client() as (app, client):
        svc = app.state.services["rbe3001"]
        link: SimLink = svc.driver.link
        mid = await _start_move(client, "rbe3001", _far_target(svc))
        await _under_way(client, "rbe3001", mid)
        link.set_faults(FaultConfig(corrupt=1.0))
        m = await _wait_ended(client, "rbe3001", mid)
        link.set_faults(FaultConfig())
        assert m["status"] == "failed" and m["code"] in ("corrupt_reply", "device_timeout"), m


def _unused(app: FastAPI) -> None:
    """(keeps the FastAPI import for type hints in editors)"""
