"""Joint calibration against the rbe3001 simulator started as the hardware ships (issue 24):
encoders zeroed wherever the board was powered on (the firmware's ZeroPID() at start-up), so
the server cannot know where the joints are until a pose is declared; the calibration is
stored under the hardware's identity (the HID serial number) and found again after a restart
of the server with the same board, not with another one on the same port."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest

from app.arms.loading import load_arms, load_profile
from app.config import ArmProfile
from tests._wait import wait_for
from tests.conftest import make_settings, running_client

API = "/api/v1/arms/rbe3001"
ROOT = Path(__file__).resolve().parent.parent
JIG = [0.0, 1.5708, 0.0]


def as_shipped(serial: str = "0671FF485550755187121712") -> ArmProfile:
    """The rbe3001 profile on a simulated board that starts like the hardware: not calibrated,
    powered on in the jig (its encoders read zero there), with a USB serial number."""
    p = load_profile("rbe3001")
    link = p.link.model_copy(update={"calibrated_at_start": False, "serial_number": serial,
                                     "sim_power_on_pose": "jig"})
    return p.model_copy(update={"link": link})


async def _detail(client: httpx.AsyncClient) -> dict[str, Any]:
    r = await client.get(API)
    assert r.status_code == 200, r.text
    body: dict[str, Any] = r.json()
    return body


async def test_an_uncalibrated_rbe3001_refuses_moves_and_is_calibrated_by_its_jig_pose() -> None:
    settings = make_settings()
    async with running_client(settings, profiles=[as_shipped()]) as (app, client):
        detail = await _detail(client)
        assert detail["calibrated"] == [False, False, False]
        state = (await client.get(f"{API}/state")).json()
        assert state["calibrated"] == [False, False, False]
        # the encoders read zero in the jig: the server's q = 0 is not where the arm is
        np.testing.assert_allclose(state["positions"], [0.0, 0.0, 0.0], atol=0.01)

        r = await client.post(f"{API}/move/joints", json={"positions": [0.2, 0.6, 0.3]})
        assert r.status_code == 409 and r.json()["code"] == "not_calibrated", r.text
        detail_text = r.json()["detail"]
        assert "base" in detail_text and "/api/v1/arms/rbe3001/calibration" in detail_text
        r = await client.post(f"{API}/move/pose", json={"x": 0.2, "y": 0.0, "z": 0.2})
        assert r.status_code == 409 and r.json()["code"] == "not_calibrated", r.text
        # pass-through position goals too (SET_PID in ticks)
        r = await client.post(f"{API}/rbe3001/set-pid",
                              json={"joints": [{"position_ticks": 30.0}] * 3})
        assert r.status_code == 409 and r.json()["code"] == "not_calibrated", r.text

        cal = (await client.get(f"{API}/calibration")).json()
        assert cal["poses"]["jig"] == JIG and cal["gravity"] is None
        assert [j["source"] for j in cal["joints"]] == [None, None, None]
        assert cal["identity"].endswith("0671FF485550755187121712")

        r = await client.post(f"{API}/calibration", json={"pose": "nowhere"})
        assert r.status_code == 422 and r.json()["code"] == "invalid_request"
        r = await client.post(f"{API}/calibration", json={"pose": "jig", "positions": JIG})
        assert r.status_code == 422
        r = await client.post(f"{API}/calibration", json={"pose": "jig"})
        assert r.status_code == 200, r.text
        cal = r.json()
        assert [j["calibrated"] for j in cal["joints"]] == [True, True, True]
        assert [j["source"] for j in cal["joints"]] == ["declared"] * 3
        assert cal["stored"] is True
        # the device reads zero ticks at the jig pose (where it was powered on; the PID's
        # gravity droop since is a few ticks): that is each joint's offset
        np.testing.assert_allclose([j["offset"] for j in cal["joints"]], JIG, atol=0.02)

        state = await wait_for(lambda: _fresh_state(app), what="a sample after calibrating")
        np.testing.assert_allclose(state["positions"], JIG, atol=0.01)
        assert state["calibrated"] == [True, True, True]

        # now the arm moves, and the server's pose is the simulated arm's own
        r = await client.post(f"{API}/move/joints",
                              json={"positions": [0.2, 0.9, 0.4], "wait": True})
        assert r.status_code == 200 and r.json()["status"] == "done", r.text
        fw = app.state.services["rbe3001"].driver.link.device
        fw = getattr(fw, "device", fw)  # (under the simulated world's tap)
        np.testing.assert_allclose(fw.q, [0.2, 0.9, 0.4], atol=0.05)


def _fresh_state(app: Any) -> dict[str, Any] | None:
    latest = app.state.services["rbe3001"].hub.latest
    return latest if latest is not None and latest["calibrated"] == [True] * 3 else None


async def test_the_calibration_survives_a_restart_on_the_same_board_only() -> None:
    settings = make_settings()
    async with running_client(settings, profiles=[as_shipped()]) as (_app, client):
        r = await client.post(f"{API}/calibration", json={"positions": JIG})
        assert r.status_code == 200 and r.json()["stored"] is True, r.text

    # the same board (serial number) after a restart: calibrated from the store
    async with running_client(settings, profiles=[as_shipped()]) as (_app, client):
        await wait_for(lambda: _calibrated(client), what="the stored calibration applied")
        cal = (await client.get(f"{API}/calibration")).json()
        assert [j["source"] for j in cal["joints"]] == ["stored"] * 3
        np.testing.assert_allclose((await client.get(f"{API}/state")).json()["positions"],
                                   JIG, atol=0.01)
        r = await client.post(f"{API}/move/joints",
                              json={"positions": [0.0, 1.2, 0.2], "wait": True})
        assert r.status_code == 200 and r.json()["status"] == "done", r.text

    # another board on the same port: not calibrated
    async with running_client(settings, profiles=[as_shipped("OTHER-BOARD-2")]) as (_a, client):
        detail = await _detail(client)
        assert detail["calibrated"] == [False, False, False]
        r = await client.post(f"{API}/move/joints", json={"positions": [0.0, 1.2, 0.2]})
        assert r.status_code == 409 and r.json()["code"] == "not_calibrated"


async def _calibrated(client: httpx.AsyncClient) -> bool:
    return bool((await _detail(client))["calibrated"] == [True, True, True])


async def test_forgetting_the_calibration_needs_an_instructor_and_refuses_moves_again() -> None:
    settings = make_settings(operator_tokens="op", instructor_tokens="teach")
    op = {"Authorization": "Bearer op"}
    async with running_client(settings, profiles=[as_shipped()], headers=op) as (_app, client):
        assert (await client.post(f"{API}/calibration", json={"pose": "jig"})).status_code == 200
        r = await client.delete(f"{API}/calibration")
        assert r.status_code == 403
        r = await client.delete(f"{API}/calibration", headers={"Authorization": "Bearer teach"})
        assert r.status_code == 200, r.text
        assert [j["calibrated"] for j in r.json()["joints"]] == [False] * 3
        assert r.json()["stored"] is False
        r = await client.post(f"{API}/move/joints", json={"positions": [0.0, 1.2, 0.2]})
        assert r.status_code == 409 and r.json()["code"] == "not_calibrated"


async def test_simulated_arms_start_calibrated() -> None:
    async with running_client() as (_app, client):
        assert (await _detail(client))["calibrated"] == [True, True, True]
        cal = (await client.get(f"{API}/calibration")).json()
        assert [j["source"] for j in cal["joints"]] == ["profile"] * 3


@pytest.mark.parametrize("chosen, l2, l3", [("velocity_kinematics", 0.1651, 0.206375),
                                            ("fk_function", 0.16599916, 0.1999996)])
async def test_link_lengths_follow_the_profile_set(chosen: str, l2: float, l3: float) -> None:
    p = load_profile("rbe3001")
    p = ArmProfile.model_validate({**p.model_dump(), "geometry_set": chosen})
    assert p.geometry["l2"] == l2 and p.geometry["l3"] == l3
    async with running_client(profiles=[p]) as (_app, client):
        r = await client.post(f"{API}/kinematics/forward", json={"positions": [0.0, 0.0, 0.0]})
        assert r.status_code == 200, r.text
        tip = r.json()["tip"]
        # q = 0: link 2 level, link 3 hanging straight down
        assert tip["x"] == pytest.approx(l2, abs=1e-6)
        assert tip["z"] == pytest.approx(0.2032 - l3, abs=1e-6)


async def test_readme_rbe3001_day_one() -> None:
    """README "From a freshly flashed board to a first move (rbe3001)", command by command,
    on the config it names."""
    profiles = load_arms(str(ROOT / "config" / "rbe3001-day-one.example.toml"))
    async with running_client(profiles=profiles) as (_app, client):
        cal = (await client.get(f"{API}/calibration")).json()
        assert "jig" in cal["poses"] and not any(j["calibrated"] for j in cal["joints"])
        r = await client.post(f"{API}/move/joints", json={"positions": [0, 1.2, 0.3]})
        assert r.status_code == 409 and r.json()["code"] == "not_calibrated"
        r = await client.post(f"{API}/calibration", json={"pose": "jig"})
        assert r.status_code == 200 and r.json()["stored"] is True, r.text
        r = await client.post(f"{API}/move/joints", json={"positions": [0, 1.2, 0.3],
                                                          "wait": True})
        assert r.status_code == 200 and r.json()["status"] == "done", r.text
        r = await client.post(f"{API}/calibration/gravity", json={"wait": True})
        assert r.status_code == 202 and r.json()["status"] == "done", r.text
        state = await wait_for(lambda: _rest_with_force(client), what="a sample at rest")
        f = state["tip_force"]
        assert np.linalg.norm([f["x"], f["y"], f["z"]]) < 0.1


async def _rest_with_force(client: httpx.AsyncClient) -> dict[str, Any] | None:
    s: dict[str, Any] = (await client.get(f"{API}/state")).json()
    return s if s["tip_force"] is not None and not any(s["velocities"]) else None


def test_a_real_link_starts_not_calibrated_where_the_profile_cannot_know_the_zero() -> None:
    """Built, not started: a serial or HID link's joints marked zero_known = false start not
    calibrated; with power_on_pose the profile knows them (the firmware's power-on zero)."""
    from app.service import ArmService

    p = load_profile("rbe3001")
    serial = p.model_copy(update={"link": p.link.model_copy(
        update={"kind": "serial", "address": "socket://127.0.0.1:9"})})
    svc = ArmService(serial)
    assert svc.driver.calibrated == [False, False, False]
    assert svc.detail().calibrated == [False, False, False]
    powered = serial.model_copy(update={"power_on_pose": "jig"})
    svc = ArmService(powered)
    assert svc.driver.calibrated == [True, True, True]
    # the firmware reads 0 ticks at the jig pose
    np.testing.assert_allclose(svc.calibration.offsets(), JIG, atol=1e-9)
    view = svc.calibration_view()
    assert [j.source for j in view.joints] == ["profile"] * 3 and view.power_on_pose == "jig"


def test_the_hardware_identity_names_the_board_or_the_bus_and_its_ids() -> None:
    """What the calibration is stored under: a simulated board's serial number; for a
    Dynamixel arm on a serial port (which reports no serial number of its own), the port and
    the servo IDs."""
    from app.service import ArmService

    svc = ArmService(as_shipped("BOARD-7"))
    svc.driver.link.identity = "sim-serial:BOARD-7"  # (what the link says once open)
    assert svc.driver.hardware_identity() == "rbe3001:sim-serial:BOARD-7"
    p = load_profile("angler")
    p = p.model_copy(update={"link": p.link.model_copy(
        update={"kind": "serial", "address": "/dev/ttyUSB0"})})
    ids = ",".join(str(j.motor_id) for j in p.joints)
    assert ArmService(p).driver.hardware_identity() == f"angler:serial:/dev/ttyUSB0:ids={ids}"
