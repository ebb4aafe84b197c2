"""Teleoperation between unlike arms (config/three-arms.example.toml): an rbe3001 (3 joints,
no wrist) leads an OpenManipulator-X (4 joints, a wrist) through the tip, the OMX's IK
nearest where it is; the one-to-one mapping is refused between them."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from _wait import wait_for

from app.service import ArmService
from tests.conftest import make_settings, running_client

API = "/api/v1"
CONFIG = Path(__file__).resolve().parents[1] / "config" / "three-arms.example.toml"


async def test_an_rbe3001_leads_an_omx_through_the_tip() -> None:
    async with running_client(make_settings(config=str(CONFIG))) as (app, c):
        leader: ArmService = app.state.services["rbe3001"]
        follower: ArmService = app.state.services["omx"]
        body = {"leader": "rbe3001", "follower": "omx", "rate_hz": 50}
        r = await c.post(f"{API}/teleop", json=body)
        assert r.status_code == 422 and r.json()["code"] == "invalid_request", r.text
        assert "mapping `tip`" in r.json()["detail"]
        r = await c.post(f"{API}/teleop", json={**body, "mapping": "tip"})
        assert r.status_code == 201, r.text
        sid = r.json()["id"]
        for x, y, z in ((0.15, 0.05, 0.15), (0.18, -0.06, 0.1)):
            r = await c.post(f"{API}/arms/rbe3001/move/pose", json={"x": x, "y": y, "z": z,
                                                                    "wait": True})
            assert r.status_code == 200 and r.json()["status"] == "done", r.text

            def tips_agree() -> bool:
                lp = np.asarray(leader.model.fk(leader.positions))
                fp = np.asarray(follower.model.fk(follower.positions))
                return bool(np.linalg.norm(lp - fp) < 0.002)
            await wait_for(tips_agree, what="the OMX's tip on the rbe3001's")
        r = await c.delete(f"{API}/teleop/{sid}")
        assert r.status_code == 200 and r.json()["commands"] > 0, r.text
