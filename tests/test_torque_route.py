"""`PUT /api/v1/arms/{arm}/torque` (an addition to API.md): the joints' torque off, the arm free
to be moved by hand, or on again holding where the hand left it. Through the real app over the
simulated arms, judged on the device's side of the link (the simulated servos' Torque Enable,
Goal Position and Present Position) and by the answers' codes. Refusals change nothing: a
joint that falls without torque (the angler's z winch) unless the body says its load is held,
a device without a torque switch (the rbe3001), an arm in a teleoperation session, another
client's lease, a body that is not one."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from _wait import wait_for

from app.service import ArmService
from tests.conftest import make_settings, running_client

API = "/api/v1"
CONFIG = Path(__file__).resolve().parents[1] / "config" / "teleop_omx.toml"


def servos(arm: ArmService) -> list[Any]:
    """The simulated joint servos behind the arm's link (the device side)."""
    bus = arm.driver.link.device
    return [bus.servo(j.motor_id) for j in arm.profile.joints]


async def test_torque_off_refused_while_the_winch_would_fall_then_off_and_on_holding() -> None:
    async with running_client(make_settings()) as (app, c):
        angler: ArmService = app.state.services["angler"]
        events: list[dict[str, Any]] = []
        sub = angler.hub.subscribe()
        try:
            r = await c.put(f"{API}/arms/angler/torque", json={"on": False})
            assert r.status_code == 409 and r.json()["code"] == "in_use", r.text
            assert "z falls without torque" in r.json()["detail"], r.text
            assert all(sv.torque for sv in servos(angler))  # nothing switched

            r = await c.put(f"{API}/arms/angler/torque",
                            json={"on": False, "load_supported": True})
            assert r.status_code == 200, r.text
            assert r.json() == {"arm": "angler", "on": False}
            assert not any(sv.torque for sv in servos(angler))
            # the winch's load, held by nobody in the simulator, goes down as a real one does
            z = angler.profile.joints.index(next(j for j in angler.profile.joints
                                                if j.falls_without_torque))
            before = servos(angler)[z].pos
            await wait_for(lambda: abs(servos(angler)[z].pos - before) > 10,
                           what="the free winch paying out")

            r = await c.put(f"{API}/arms/angler/torque", json={"on": True})
            assert r.status_code == 200 and r.json() == {"arm": "angler", "on": True}, r.text
            assert all(sv.torque for sv in servos(angler))
            # each servo holds where it was left: its goal is its present position
            for sv in servos(angler):
                assert abs(sv.get("goal_position") - sv.get("present_position")) <= 1
            here = [sv.pos for sv in servos(angler)]
            await wait_for(lambda: angler.hub.published > 20, what="samples")
            assert np.allclose([sv.pos for sv in servos(angler)], here, atol=1.0)
            _samples, got, _dropped = sub.take()
            events = [e for e in map(_json, got) if e.get("event") == "torque"]
        finally:
            sub.close()
        assert [e["data"] for e in events] == [{"on": False}, {"on": True}]


def _json(raw: str) -> dict[str, Any]:
    import orjson

    out: dict[str, Any] = orjson.loads(raw)
    return out


async def test_the_refusals_change_nothing() -> None:
    async with running_client(make_settings()) as (app, c):
        angler: ArmService = app.state.services["angler"]
        r = await c.put(f"{API}/arms/rbe3001/torque", json={"on": False})
        assert r.status_code == 409 and r.json()["code"] == "not_supported", r.text
        r = await c.put(f"{API}/arms/nope/torque", json={"on": False})
        assert r.status_code == 404 and r.json()["code"] == "unknown_arm", r.text
        for body in ({"on": "no"}, {}, {"on": False, "load_supported": 1}, [False]):
            r = await c.put(f"{API}/arms/angler/torque", json=body)
            assert r.status_code == 422, (body, r.text)
        r = await c.put(f"{API}/arms/angler/torque", content=b"{not json",
                        headers={"content-type": "application/json"})
        assert r.status_code == 422 and r.json()["code"] == "invalid_json", r.text
        # another client's lease
        r = await c.post(f"{API}/arms/angler/lease")
        assert r.status_code in (200, 201), r.text
        r = await c.put(f"{API}/arms/angler/torque", json={"on": False, "load_supported": True})
        assert r.status_code == 409 and r.json()["code"] == "leased", r.text
        assert all(sv.torque for sv in servos(angler))
        # torque on (holding where it is) is open to every operator, like the estop's hold
        r = await c.put(f"{API}/arms/angler/torque", json={"on": True})
        assert r.status_code == 200, r.text
        assert all(sv.torque for sv in servos(angler))


async def test_the_estop_latch_lets_torque_off_and_on_through() -> None:
    """Torque off is the safe write and torque on moves nothing: neither waits for a release."""
    async with running_client(make_settings()) as (app, c):
        angler: ArmService = app.state.services["angler"]
        assert (await c.post(f"{API}/arms/angler/estop")).status_code == 200
        r = await c.put(f"{API}/arms/angler/torque", json={"on": False, "load_supported": True})
        assert r.status_code == 200, r.text
        assert not any(sv.torque for sv in servos(angler))
        r = await c.put(f"{API}/arms/angler/torque", json={"on": True})
        assert r.status_code == 200, r.text
        assert all(sv.torque for sv in servos(angler))
        assert angler.estop  # still latched


async def test_an_arm_in_a_teleoperation_session_is_busy() -> None:
    async with running_client(make_settings(config=str(CONFIG))) as (app, c):
        r = await c.post(f"{API}/teleop", json={"leader": "leader", "follower": "follower",
                                                "rate_hz": 50})
        assert r.status_code == 201, r.text
        sid = r.json()["id"]
        for arm in ("leader", "follower"):
            r = await c.put(f"{API}/arms/{arm}/torque", json={"on": False,
                                                              "load_supported": True})
            assert r.status_code == 409 and r.json()["code"] == "busy", r.text
            assert sid in r.json()["detail"]
            assert all(sv.torque for sv in servos(app.state.services[arm]))
        assert (await c.delete(f"{API}/teleop/{sid}")).status_code == 200
        r = await c.put(f"{API}/arms/follower/torque", json={"on": False, "load_supported": True})
        assert r.status_code == 200, r.text
