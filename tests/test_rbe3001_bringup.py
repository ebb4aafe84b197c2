"""The rbe3001 on the firmware builds a student may have flashed (issue 24, items 4 and 5),
against the simulated firmware built the same way: a build without STATUS (38) is named at
connect, in the arm's detail and the log, with what to do; SET_GAIN and SET_CLAW, which "do
not provide any return values", work whether the build answers zeros, the echo, other bytes
or nothing."""

from __future__ import annotations

import contextlib
import logging
from collections.abc import AsyncIterator
from typing import Any

import httpx
import pytest
from fastapi import FastAPI

from app.arms.loading import load_profile
from app.config import ArmProfile
from app.web.factory import create_app
from tests._wait import wait_for
from tests.conftest import make_settings, running_client

API = "/api/v1/arms/rbe3001"


def built(**link: Any) -> ArmProfile:
    p = load_profile("rbe3001")
    return p.model_copy(update={"link": p.link.model_copy(update=link)})


@contextlib.asynccontextmanager
async def unready(profile: ArmProfile) -> AsyncIterator[tuple[FastAPI, httpx.AsyncClient]]:
    """The app over `profile` without waiting for a first sample (there may be none)."""
    app = create_app(make_settings(), profiles=[profile])
    async with app.router.lifespan_context(app):
        transport = httpx.ASGITransport(app=app)
        async with httpx.AsyncClient(transport=transport, base_url="http://armserver.test",
                                     timeout=30.0) as client:
            yield app, client


@pytest.mark.parametrize("build, said", [("stock_99", "error 99"),
                                         ("stock_silent", "answers nothing to STATUS")])
async def test_a_firmware_without_status_is_named_in_the_detail_and_the_log(
        build: str, said: str, caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.WARNING)
    async with unready(built(sim_firmware=build)) as (_app, client):
        async def named() -> dict[str, Any] | None:
            # (the link retries its open with a backoff: between a retry's open and its
            # set-up's failure it is connected a moment, a moment a loaded machine stretches)
            detail: dict[str, Any] = (await client.get(API)).json()
            return (detail if detail.get("firmware") and not detail["link"]["connected"]
                    else None)

        detail = await wait_for(named, what="the firmware named in the detail, not connected")
        assert said in detail["firmware"] and "STATUS" in detail["firmware"]
        assert "flash the course firmware" in detail["firmware"].lower()
        assert said in detail["link"]["last_error"]
        r = await client.get(f"{API}/state")
        assert r.status_code == 503 and r.json()["code"] == "link_down"
        await wait_for(lambda: any(said in rec.getMessage() for rec in caplog.records),
                       what="the log line")


async def test_the_status_build_has_no_firmware_note() -> None:
    async with running_client(profiles=[built()]) as (_app, client):
        assert (await client.get(API)).json()["firmware"] is None


@pytest.mark.parametrize("reply, how", [("zeros", "acknowledged"), ("echo", "acknowledged"),
                                        ("silent", "sent"), ("other", "other")])
async def test_set_gain_and_set_claw_work_whatever_the_build_answers(
        reply: str, how: str, caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.WARNING)
    async with running_client(profiles=[built(sim_gain_claw_reply=reply)]) as (app, client):
        r = await client.post(f"{API}/rbe3001/set-gain",
                              json={"axis": 1, "kp": 0.006, "ki": 0.0, "kd": 0.0})
        assert r.status_code == 200, r.text
        assert r.json() == {"ok": True, "command": "SET_GAIN", "reply": how}
        r = await client.post(f"{API}/rbe3001/set-claw", json={"value": 0.8})
        assert r.status_code == 200, r.text
        assert r.json()["reply"] == how
        fw = app.state.services["rbe3001"].driver.link.device
        fw = getattr(fw, "device", fw)  # (under the simulated world's tap)
        assert fw.gains[1] == pytest.approx([0.006, 0.0, 0.0])  # (float32 on the wire)
        assert fw.claw_setpoint == pytest.approx(0.8)
        # the gripper reports it, and the arm still polls and moves afterwards
        r = await client.post(f"{API}/gripper", json={"value": 0.2})
        assert r.status_code == 200, r.text
        r = await client.post(f"{API}/move/joints", json={"positions": [0.1, 0.6, 0.3],
                                                          "wait": True})
        assert r.status_code == 200 and r.json()["status"] == "done", r.text
        if reply == "other":
            assert any("neither zeros nor the echo" in rec.getMessage()
                       for rec in caplog.records)
