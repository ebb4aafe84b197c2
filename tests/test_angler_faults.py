"""Faults, reboot, homing and "done means done" on the angler (API.md "Faults and homing"),
driven against the MX-28 bus simulator: over the in-process link, a real pty, and the HTTP API.
Faults are injected through the simulator's own API (as `armserver sim dynamixel --fault`)."""

from __future__ import annotations

import asyncio
import json
from collections.abc import AsyncIterator
from typing import Any

import httpx
import numpy as np
import pytest
from _wait import new_samples, wait_for
from fastapi import FastAPI

from app.arms.dynamixel.driver import DynamixelDriver
from app.arms.dynamixel.sim_bus import DynamixelBus
from app.arms.loading import load_profile
from app.config import homed_at_start
from app.device.factory import make_sim_device
from app.links.serial import SerialLink
from app.links.sim import SimLink
from app.sim.serve import serve_pty
from app.telemetry.hub import TelemetryHub
from app.web.factory import create_app
from protocol import mx28
from protocol.dynamixel import ErrorCode
from tests.conftest import make_settings, wait_ready

API = "/api/v1/arms/angler"
X, Y, T3, Z = 0, 1, 2, 3  # joint indices; x is servo 2, y servo 1 (design wiring)


async def _until(cond: Any, timeout: float = 5.0) -> None:
    deadline = asyncio.get_running_loop().time() + timeout
    while not cond():
        if asyncio.get_running_loop().time() > deadline:
            raise AssertionError("condition not met in time")
        await asyncio.sleep(0.02)


async def _driver(bus: DynamixelBus | None = None, link: Any = None,
                  homed: bool = True) -> tuple[DynamixelDriver, DynamixelBus | None]:
    profile = load_profile("angler")
    profile = homed_at_start(profile) if homed else profile
    if link is None:
        bus = bus or make_sim_device(profile)  # type: ignore[assignment]
        link = SimLink(bus, address="sim:angler")  # type: ignore[arg-type]
    drv = DynamixelDriver(profile, link, TelemetryHub("angler"))
    await drv.start()
    assert await drv.wait_connected(5.0), link.last_error
    return drv, bus


def _bus(app: FastAPI) -> DynamixelBus:
    return app.state.services["angler"].driver.link.device  # type: ignore[no-any-return]


@pytest.fixture
async def sim_app() -> AsyncIterator[tuple[FastAPI, httpx.AsyncClient]]:
    """The default server (built-in simulated config: the angler starts homed)."""
    app = create_app(make_settings())
    async with app.router.lifespan_context(app):
        await wait_ready(app)
        async with httpx.AsyncClient(transport=httpx.ASGITransport(app=app),
                                     base_url="http://armserver.test", timeout=30.0) as c:
            yield app, c
    assert app.state.internal_errors == 0


# ------------------------------------------------------------------ driver


async def test_a_faulted_servo_is_reported_and_the_others_keep_being_served():
    drv, bus = await _driver()
    assert bus is not None
    try:
        events = drv.hub.subscribe()
        bus.inject_hardware_error(2, "overload")  # servo 2 drives x
        await _until(lambda: drv.faults)
        [f] = drv.faults
        assert (f["joint"], f["servo"], f["bits"], f["raw"]) == ("x", 2, ["overload"], 0x20)
        assert "reboot" in f["advice"] and "/dynamixel/2/reboot" in f["advice"]
        seq = drv.hub.latest["seq"]
        await wait_for(lambda: drv.hub.latest["seq"] > seq + 10, what="polls going on")
        assert not drv.stale  # polls go on
        # reads keep working, on the faulted servo too (its status has the Alert bit)
        assert await drv.read_register(2, mx28.TABLE["hardware_error_status"]) == 0x20
        assert await drv.read_register(2, mx28.TABLE["torque_enable"]) == 0  # shutdown
        _, evs, _ = events.take()
        [ev] = [m for m in map(json.loads, evs) if m["event"] == "fault"]
        assert ev["data"]["servo"] == 2 and ev["data"]["bits"] == ["overload"]
        assert ev["data"]["cleared"] is False
        events.close()
        # reboot: one REBOOT, the servo set up again, the fault gone, x no longer homed
        await drv.reboot(2)
        await _until(lambda: not drv.faults)
        assert await drv.read_register(2, mx28.TABLE["torque_enable"]) == 1
        pv = await drv.read_register(2, mx28.TABLE["profile_velocity"])
        assert pv == drv.profile_velocity[2] > 0
        goal = await drv.read_register(2, mx28.TABLE["goal_position"])
        present = await drv.read_register(2, mx28.TABLE["present_position"])
        assert abs(goal - present) <= 1
        assert drv.homed == [False, True, True, True]
    finally:
        await drv.close()


@pytest.mark.parametrize("refusal", [0, ErrorCode.RESULT_FAIL])
async def test_set_up_with_a_faulted_servo_brings_the_link_up(refusal):
    """Torque-on after a shutdown is ignored (only the Alert bit shows) or answered with an
    error, depending on the firmware: neither keeps the link from coming up."""
    bus = make_sim_device(load_profile("angler"))
    assert isinstance(bus, DynamixelBus)
    bus.set_torque_refusal(refusal)
    bus.inject_hardware_error(3, ["overheating"])  # before the server connects
    drv, _ = await _driver(bus)
    try:
        assert drv.link.state.value == "up"
        await _until(lambda: drv.faults)
        assert [(f["servo"], f["joint"], f["bits"]) for f in drv.faults] == \
            [(3, "theta3", ["overheating"])]
        # the healthy servos were set up: torque on, speed capped
        torque = await drv.sync_read(mx28.TABLE["torque_enable"], [1, 2, 3, 4])
        assert torque == {1: 1, 2: 1, 3: 0, 4: 1}
    finally:
        await drv.close()


async def test_profile_velocity_never_above_the_velocity_limit():
    bus = make_sim_device(load_profile("angler"))
    assert isinstance(bus, DynamixelBus)
    for s in bus.servos:
        s.set("velocity_limit", 100)  # EEPROM, as a lab may have set it
    drv, _ = await _driver(bus)
    try:
        pv = await drv.sync_read(mx28.TABLE["profile_velocity"], [1, 2, 3, 4])
        assert pv[1] == pv[2] == 100  # the x/y joints would ask 236
        assert pv[3] <= 100 and pv[4] <= 100
    finally:
        await drv.close()


async def test_return_delay_time_is_set_where_torque_is_off_and_left_where_it_is_on():
    """The profile's `return_delay_us` (0 for the angler) is written at set-up to servos whose
    torque is off (after power-on), and not to a servo holding torque (an EEPROM write needs
    torque off, and the driver never drops a load for it)."""
    bus = make_sim_device(load_profile("angler"))
    assert isinstance(bus, DynamixelBus)
    assert {s.get("return_delay_time") for s in bus.servos} == {250}  # the e-manual default
    bus.servo(4).set("torque_enable", 1)  # the winch holds its load: a server restart
    drv, _ = await _driver(bus)
    try:
        delays = {i: bus.servo(i).get("return_delay_time") for i in (1, 2, 3, 4)}
        assert delays == {1: 0, 2: 0, 3: 0, 4: 250}
        assert bus.servo(4).get("torque_enable") == 1  # never switched off for it
        # and the servos answer at once: a READ's status comes without the 500 us delay
        assert await drv.read_register(3, mx28.TABLE["return_delay_time"]) == 0
    finally:
        await drv.close()


async def test_a_silent_servo_of_the_arm_is_a_timeout_not_absent():
    """Silence from one of the arm's own servos (a lost reply) must not be reported as "no
    servo there": that answer would be wrong. Only ids the arm does not have are absent."""
    from app.config import FaultConfig
    from app.errors import DeviceTimeout

    drv, _ = await _driver()
    try:
        link = drv.link
        assert isinstance(link, SimLink)
        link.set_faults(FaultConfig(drop=1.0))
        with pytest.raises(DeviceTimeout):
            await drv.ping(4)
        assert await drv.ping(77) == []
    finally:
        await drv.close()


async def test_ping_of_an_absent_id_is_an_empty_answer():
    drv, _ = await _driver()
    try:
        assert await drv.ping(77) == []
        assert [p[0] for p in await drv.ping(4)] == [4]
    finally:
        await drv.close()


async def test_a_power_cycle_un_homes_the_multi_turn_joints():
    drv, bus = await _driver()
    assert bus is not None
    try:
        assert drv.homed == [True] * 4
        bus.power_cycle([4, 3])  # z's winch and theta3 lose power; the host is not told
        await _until(lambda: not drv.homed[Z] and not drv.homed[2])
        # theta3 too: extended position mode restarts its count within one turn (issue 24)
        assert drv.homed == [True, True, False, False]
    finally:
        await drv.close()


async def test_faults_and_homing_over_a_real_pty(tmp_path):
    """A serial link (not simulated): x, y, z start not homed; a fault is read over the pty."""
    bus = make_sim_device(load_profile("angler"))
    assert isinstance(bus, DynamixelBus)
    path = tmp_path / "ttyDXL"
    server = await serve_pty(bus, path)
    drv, _ = await _driver(link=SerialLink(str(path)), homed=False)
    try:
        assert drv.homed == [False] * 4  # theta3 too (issue 24)
        bus.inject_hardware_error(1, "electrical_shock")
        await _until(lambda: drv.faults)
        assert drv.faults[0]["servo"] == 1 and drv.faults[0]["joint"] == "y"
        assert drv.faults[0]["bits"] == ["electrical_shock"]
    finally:
        await drv.close()
        await server.close()


# ------------------------------------------------------------------ API


async def test_the_advice_for_a_falling_joints_servo_says_how_its_reboot_goes(sim_app):
    """z falls without torque: its fault's advice names the reboot's `load_supported` (an
    input-voltage alert leaves the torque on, and the reboot asks); x's does not."""
    app, c = sim_app
    svc = app.state.services["angler"]
    for i in (2, 4):
        _bus(app).inject_hardware_error(i, "input_voltage")
    await _until(lambda: len(svc.driver.faults) == 2)
    advice = {f["servo"]: f["advice"] for f in (await c.get(API)).json()["faults"]}
    assert "z falls without torque" in advice[4] and '{"load_supported": true}' in advice[4]
    assert "load_supported" not in advice[2] and "/dynamixel/2/reboot" in advice[2]
    r = await c.post(f"{API}/dynamixel/4/reboot", json={"load_supported": True})
    assert r.status_code == 200, r.text
    r = await c.post(f"{API}/dynamixel/2/reboot")
    assert r.status_code == 200, r.text
    await _until(lambda: not svc.driver.faults)


async def test_api_fault_refuses_moves_until_reboot_then_homing(sim_app):
    app, c = sim_app
    r = await c.get(API)
    assert r.json()["faults"] == [] and r.json()["homed"] == [True] * 4
    _bus(app).inject_hardware_error(2, "overload")
    svc = app.state.services["angler"]
    await _until(lambda: svc.driver.faults)
    detail = (await c.get(API)).json()
    assert detail["faults"][0]["servo"] == 2 and detail["faults"][0]["bits"] == ["overload"]
    state = (await c.get(f"{API}/state")).json()
    assert state["faults"] == detail["faults"] and state["homed"] == [True] * 4
    # moves and position commands refused: which servo, which bits, how to clear it
    r = await c.post(f"{API}/move/joints", json={"positions": [0.01, 0, 0, 0.05]})
    assert r.status_code == 409 and r.json()["code"] == "fault"
    assert "servo 2" in r.json()["detail"] and "overload" in r.json()["detail"]
    assert "/dynamixel/2/reboot" in r.json()["detail"]
    r = await c.put(f"{API}/dynamixel/3/registers/goal_position", json={"raw": 2050})
    assert r.status_code == 409 and r.json()["code"] == "fault"
    # reads and the pass-through register read keep working
    r = await c.get(f"{API}/dynamixel/2/registers/hardware_error_status")
    assert r.status_code == 200 and r.json()["raw"] == 0x20
    # reboot clears it; x (a multi-turn screw) comes back not homed
    r = await c.post(f"{API}/dynamixel/2/reboot")
    assert r.status_code == 200, r.text
    await _until(lambda: not svc.driver.faults)
    detail = (await c.get(API)).json()
    assert detail["faults"] == [] and detail["homed"] == [False, True, True, True]
    r = await c.post(f"{API}/move/joints", json={"positions": [0.01, 0, 0, 0.05]})
    assert r.status_code == 409 and r.json()["code"] == "not_homed"
    assert "x" in r.json()["detail"] and f"{API}/home" in r.json()["detail"]
    # a move that leaves x where it is may go
    q = svc.driver.positions
    r = await c.post(f"{API}/move/joints", json={"positions": [float(q[0]), 0.0, 0.1, 0.05],
                                                 "wait": True})
    assert r.status_code == 200 and r.json()["status"] == "done", r.text
    # home: the current pose is the profile's home pose
    r = await c.post(f"{API}/home")
    assert r.status_code == 200 and r.json()["homed"] == [True] * 4
    await new_samples(svc.hub, 2)  # a reading converted with the new home
    assert svc.driver.positions[X] == pytest.approx(0.0, abs=1e-5)
    r = await c.post(f"{API}/move/joints", json={"positions": [0.002, 0, 0, 0.05], "wait": True})
    assert r.status_code == 200 and r.json()["status"] == "done", r.text


async def test_api_a_real_link_starts_not_homed_and_home_takes_positions():
    app = create_app(make_settings(), [load_profile("angler")])  # homed_at_start not set
    async with app.router.lifespan_context(app):
        await wait_ready(app)
        async with httpx.AsyncClient(transport=httpx.ASGITransport(app=app),
                                     base_url="http://armserver.test", timeout=30.0) as c:
            assert (await c.get(API)).json()["homed"] == [False] * 4
            r = await c.post(f"{API}/move/pose", json={"x": 0.0, "y": 0.11, "z": 0.0})
            assert r.status_code == 409 and r.json()["code"] == "not_homed"
            assert "y" in r.json()["detail"]
            # theta3 alone does not turn either (issue 24: its zero is the MATLAB's, its count
            # restarts within one turn at power-up)
            q0 = app.state.services["angler"].driver.positions
            r = await c.post(f"{API}/move/joints", json={
                "positions": [float(q0[X]), float(q0[Y]), 0.2, float(q0[Z])], "wait": True})
            assert r.status_code == 409 and r.json()["code"] == "not_homed", r.text
            assert "theta3" in r.json()["detail"]
            for bad in ({"positions": [0.0, 0.0]}, {"positions": [0.5, 0, 0, 0]}):
                r = await c.post(f"{API}/home", json=bad)
                assert r.status_code == 422, r.text
            assert (await c.get(API)).json()["homed"] == [False] * 4
            r = await c.post(f"{API}/home", json={"positions": [0.01, -0.02, 0.0, 0.06]})
            assert r.status_code == 200 and r.json()["homed"] == [True] * 4
            q = app.state.services["angler"].driver.positions
            np.testing.assert_allclose(q[[X, Y, Z]], [0.01, -0.02, 0.06], atol=1e-5)
            r = await c.post(f"{API}/move/joints", json={"positions": [0.012, -0.02, 0.2, 0.06],
                                                         "wait": True})
            assert r.json()["status"] == "done", r.text
    assert app.state.internal_errors == 0


async def test_home_is_refused_while_a_motion_runs(sim_app):
    _, c = sim_app
    r = await c.post(f"{API}/move/joints", json={"positions": [0.02, 0, 0, 0.05]})
    assert r.status_code == 202 or r.status_code == 200, r.text
    r = await c.post(f"{API}/home")
    assert r.status_code == 409 and r.json()["code"] == "busy"
    await c.post(f"{API}/stop")


async def test_done_means_the_joints_are_where_they_were_sent(sim_app):
    app, c = sim_app
    svc = app.state.services["angler"]
    target = [0.0123, -0.0045, 0.3, 0.061]
    r = await c.post(f"{API}/move/joints", json={"positions": target, "wait": True})
    assert r.json()["status"] == "done", r.text
    tol = [j.settle_tolerance for j in svc.profile.joints]
    err = np.abs(np.array(r.json()["final_positions"]) - target)
    assert np.all(err <= tol), (err, tol)


async def test_a_joint_without_torque_is_never_done(sim_app):
    """Torque switched off through the server refuses the move up front (409 `torque_off`,
    tests/test_torque_off_moves.py); a servo whose torque went off behind the server's back (a
    servo that reset after a brown-out: it comes up with torque off, as after a reboot without
    the set-up) fails the motion at its settle check, naming the ways back that work."""
    app, c = sim_app
    bus = app.state.services["angler"].driver.link.device
    r = await c.put(f"{API}/dynamixel/1/registers/torque_enable", json={"raw": 0})  # y
    assert r.status_code == 200
    r = await c.post(f"{API}/move/joints", json={"positions": [0.0, 0.0015, 0, 0.05],
                                                 "wait": True})
    assert r.status_code == 409 and r.json()["code"] == "torque_off", r.text
    assert "torque of y is off" in r.json()["detail"], r.text
    r = await c.put("/api/v1/arms/angler/torque", json={"on": True})
    assert r.status_code == 200, r.text
    bus.servo(1).set("torque_enable", 0)  # behind the server's back
    r = await c.post(f"{API}/move/joints", json={"positions": [0.0, 0.0015, 0, 0.05],
                                                 "wait": True})
    body = r.json()
    assert body["status"] == "failed" and body["code"] == "torque_off", body
    assert "y" in body["reason"]
    # the ways back it names are the ones that work: torque on through pass-through is refused
    assert "/dynamixel/{id}/reboot" in body["reason"] and "enable torque" not in body["reason"]
    assert "/arms/angler/torque" in body["reason"], body["reason"]


async def test_a_reconnect_keeps_homing_unless_a_mode_change_reset_the_position():
    drv, bus = await _driver()
    assert bus is not None and isinstance(drv.link, SimLink)
    try:
        events = drv.hub.subscribe()
        drv.link.disconnect()  # an unplugged U2D2: the servos keep their power and position
        await _until(lambda: any('"link_back"' in e for e in events.take()[1]), 10)
        assert drv.homed == [True] * 4
        # someone switched z's servo to (single-turn) position mode: its count is gone
        z = bus.servo(4)
        assert z is not None
        z.set("torque_enable", 0)
        z.set("operating_mode", 3)
        drv.link.disconnect()
        await _until(lambda: any('"link_back"' in e for e in events.take()[1]), 10)
        assert await drv.read_register(4, mx28.TABLE["operating_mode"]) == 4
        assert drv.homed == [True, True, True, False]
        events.close()
    finally:
        await drv.close()
