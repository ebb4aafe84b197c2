"""Protocol pass-through routes: RBE3001 packets and Dynamixel registers, against the simulated
firmware and MX-28 bus, with every refusal checked before anything is sent."""

from __future__ import annotations

import asyncio

import httpx
import numpy as np
import pytest
from _wait import held_still, wait_for
from _walk import pid_walk
from conftest import running_client
from fastapi import FastAPI

from app.arms.loading import load_profile
from app.config import homed_at_start
from app.service import ArmService

API = "/api/v1"
RB = f"{API}/arms/rbe3001/rbe3001"
DX = f"{API}/arms/angler/dynamixel"


async def test_rbe3001_status(app_client: httpx.AsyncClient) -> None:
    r = await app_client.get(f"{RB}/status")
    assert r.status_code == 200, r.text
    body = r.json()
    assert len(body["position_ticks"]) == 3 and len(body["strain_adc"]) == 3
    assert all(0.0 <= a <= 1.0 for a in body["strain_adc"])


async def test_rbe3001_set_pid_moves_within_limits(
        app_and_client: tuple[FastAPI, httpx.AsyncClient]) -> None:
    app, client = app_and_client
    svc = app.state.services["rbe3001"]
    tr = svc.model.transmission
    # one step within 0.03 s of motion at the limit: answered with the positions
    q0 = np.asarray(svc.driver.positions, dtype=float)
    ticks = tr.to_ticks(q0 + np.array([0.02, 0.02, -0.02]))
    r = await client.post(f"{RB}/set-pid", json={"joints": [{"position_ticks": float(t)}
                                                            for t in ticks]})
    assert r.status_code == 200, r.text
    assert len(r.json()["position_ticks"]) == 3
    # in such steps, anywhere within the limits
    await pid_walk(client, svc, [0.2, 0.6, 0.3])
    for _ in range(100):
        st = (await client.get(f"{API}/arms/rbe3001/state")).json()
        if np.allclose(st["positions"], [0.2, 0.6, 0.3], atol=0.02):
            break
        await asyncio.sleep(0.02)
    assert np.allclose(st["positions"], [0.2, 0.6, 0.3], atol=0.02)
    # a step the PID would take faster than the limit: refused, nothing sent
    before = list(svc.driver.link.device.setpoint)
    jump = tr.to_ticks(np.array([0.2, 0.6, 0.3]) + np.array([0.5, 0.0, 0.0]))
    r = await client.post(f"{RB}/set-pid", json={"joints": [{"position_ticks": float(t)}
                                                            for t in jump]})
    assert r.status_code == 422 and r.json()["code"] == "velocity_limit", r.text
    assert "base" in r.json()["detail"] and "move/joints" in r.json()["detail"]
    assert list(svc.driver.link.device.setpoint) == before
    # outside the shoulder limit: refused before anything is sent
    far = tr.to_ticks(np.array([0.0, 3.0, 0.0]))
    r = await client.post(f"{RB}/set-pid", json={"joints": [{"position_ticks": float(t)}
                                                            for t in far]})
    assert r.status_code == 422 and r.json()["code"] == "joint_limit"
    r = await client.post(f"{RB}/set-pid", json={"joints": [{"position_ticks": 1e300}] * 3})
    assert r.status_code == 422


async def test_rbe3001_gain_and_claw(app_and_client: tuple[FastAPI, httpx.AsyncClient]) -> None:
    app, client = app_and_client
    r = await client.post(f"{RB}/set-gain", json={"axis": 1, "kp": 0.01, "ki": 0.0, "kd": 0.001})
    assert r.status_code == 200 and r.json() == {"ok": True, "command": "SET_GAIN",
                                                  "reply": "acknowledged"}
    r = await client.post(f"{RB}/set-claw", json={"value": 0.3})
    assert r.status_code == 200 and r.json()["command"] == "SET_CLAW"
    assert app.state.services["rbe3001"].driver.gripper == 0.3
    r = await client.post(f"{RB}/set-gain", json={"axis": 3, "kp": 0, "ki": 0, "kd": 0})
    assert r.status_code == 422


async def test_set_gain_keeps_a_proportional_gain_that_holds_the_arm(
        app_and_client: tuple[FastAPI, httpx.AsyncClient]) -> None:
    """With kp 0 a joint holds nothing: through a raw-access profile's SET_GAIN the simulated
    shoulder falls past its lower limit. Without raw access kp below the joint's `min_kp` is 422
    `out_of_range` naming the joint, nothing sent; at `min_kp` it is taken."""
    app, client = app_and_client
    svc = app.state.services["rbe3001"]
    fw = svc.driver.link.device
    before = [list(g) for g in fw.gains]
    for axis, name in enumerate(("base", "shoulder", "elbow")):
        r = await client.post(f"{RB}/set-gain", json={"axis": axis, "kp": 0.001, "ki": 0.01,
                                                      "kd": 0.0})
        assert r.status_code == 422 and r.json()["code"] == "out_of_range", r.text
        assert name in r.json()["detail"] and "min_kp" in r.json()["detail"]
    assert [list(g) for g in fw.gains] == before
    kp = svc.profile.joints[1].min_kp
    r = await client.post(f"{RB}/set-gain", json={"axis": 1, "kp": kp, "ki": 0.0, "kd": 0.0})
    assert r.status_code == 200 and fw.gains[1] == pytest.approx([kp, 0.0, 0.0]), r.text
    raw = homed_at_start(load_profile("rbe3001")).model_copy(update={"raw_access": True})
    async with running_client(profiles=[raw]) as (app2, c2):
        arm = app2.state.services["rbe3001"]
        lower = float(arm.model.lower[1])
        r = await c2.post(f"{RB}/set-gain", json={"axis": 1, "kp": 0, "ki": 0, "kd": 0})
        assert r.status_code == 200, r.text
        await wait_for(lambda: arm.positions[1] < lower, timeout=10,
                       what="the shoulder, with kp 0, below its lower limit")


async def test_set_gain_keeps_the_loop_from_chattering(
        app_and_client: tuple[FastAPI, httpx.AsyncClient]) -> None:
    """The firmware's integral is the error's running mean, so at rest ki adds to kp: kp + ki
    above the joint's `max_kp_ki` is 422 `out_of_range` naming the joint, nothing sent, unless
    raw access; at it, taken. Through a raw-access profile kp 0.05 has the simulated shoulder
    chatter at rest faster than its speed limit."""
    app, client = app_and_client
    svc = app.state.services["rbe3001"]
    fw = svc.driver.link.device
    before = [list(g) for g in fw.gains]
    for axis, name in enumerate(("base", "shoulder", "elbow")):
        for kp, ki in ((0.05, 0.0), (0.005, 0.05), (0.02, 0.02), (1000.0, 0.0)):
            r = await client.post(f"{RB}/set-gain", json={"axis": axis, "kp": kp, "ki": ki,
                                                          "kd": 0.0})
            assert r.status_code == 422 and r.json()["code"] == "out_of_range", r.text
            assert name in r.json()["detail"] and "max_kp_ki" in r.json()["detail"]
    assert [list(g) for g in fw.gains] == before
    top = svc.profile.joints[1].max_kp_ki
    # the firmware's kp and the rest of the bound as ki: their sum is above 0.03 in floats
    assert top == 0.03 and 0.005 + 0.025 > top
    r = await client.post(f"{RB}/set-gain", json={"axis": 1, "kp": 0.005, "ki": 0.025,
                                                  "kd": 1.0})
    assert r.status_code == 200 and fw.gains[1] == pytest.approx([0.005, 0.025, 1.0]), r.text
    raw = homed_at_start(load_profile("rbe3001")).model_copy(update={"raw_access": True})
    async with running_client(profiles=[raw]) as (app2, c2):
        arm = app2.state.services["rbe3001"]
        sim = arm.driver.link.device
        limit = raw.joints[1].max_velocity
        r = await c2.post(f"{RB}/set-gain", json={"axis": 1, "kp": 0.05, "ki": 0, "kd": 0})
        assert r.status_code == 200, r.text
        await wait_for(lambda: abs(sim.qd[1]) > limit, timeout=10,
                       what="the shoulder, at kp 0.05, faster than its speed limit at rest")


async def test_protocol_mismatch_is_409_not_supported(app_client: httpx.AsyncClient) -> None:
    r = await app_client.get(f"{API}/arms/angler/rbe3001/status")
    assert r.status_code == 409 and r.json()["code"] == "not_supported"
    r = await app_client.post(f"{API}/arms/rbe3001/dynamixel/ping", json={})
    assert r.status_code == 409 and r.json()["code"] == "not_supported"
    r = await app_client.get(f"{API}/arms/rbe3001/dynamixel/1/registers/model_number")
    assert r.status_code == 409 and r.json()["code"] == "not_supported"


async def test_dynamixel_ping(app_client: httpx.AsyncClient) -> None:
    r = await app_client.post(f"{DX}/ping", json={"id": 2})
    assert r.status_code == 200
    assert r.json()["devices"] == [{"id": 2, "model_number": 30,
                                    "firmware_version": r.json()["devices"][0]["firmware_version"]}]
    r = await app_client.post(f"{DX}/ping")  # no body: broadcast
    assert r.status_code == 200
    assert [d["id"] for d in r.json()["devices"]] == [1, 2, 3, 4]
    r = await app_client.post(f"{DX}/ping", json={"id": 77})
    assert r.status_code == 200 and r.json()["devices"] == []  # absent: an answer, not a 504


async def test_dynamixel_register_read(app_client: httpx.AsyncClient) -> None:
    r = await app_client.get(f"{DX}/1/registers/model_number")
    assert r.status_code == 200
    assert r.json() == {"id": 1, "name": "model_number", "address": 0, "size": 2, "raw": 30,
                        "unit": None, "value": None}
    r = await app_client.get(f"{DX}/3/registers/present_position")
    assert r.status_code == 200 and r.json()["unit"] == "deg"
    assert r.json()["value"] == r.json()["raw"] * 0.088


async def test_dynamixel_register_refusals(app_client: httpx.AsyncClient) -> None:
    r = await app_client.get(f"{DX}/1/registers/no_such_thing")
    assert r.status_code == 422 and r.json()["code"] == "unknown_register"
    r = await app_client.put(f"{DX}/1/registers/goal_positon", json={"raw": 0})
    assert r.status_code == 422 and r.json()["code"] == "unknown_register"
    r = await app_client.put(f"{DX}/1/registers/present_position", json={"raw": 0})
    assert r.status_code == 422 and r.json()["code"] == "read_only"
    r = await app_client.put(f"{DX}/1/registers/led", json={"raw": 2})
    assert r.status_code == 422 and r.json()["code"] == "out_of_range"
    r = await app_client.put(f"{DX}/9/registers/goal_position", json={"raw": 2048})
    assert r.status_code == 422 and r.json()["code"] == "unknown_id"
    r = await app_client.put(f"{DX}/3/registers/goal_position", json={"raw": 10**30})
    assert r.status_code == 422 and r.json()["code"] == "out_of_range"
    r = await app_client.get(f"{DX}/253/registers/led")
    assert r.status_code == 422 and r.json()["code"] == "invalid_request"


async def test_dynamixel_goal_position_obeys_the_joint_limits(
        app_and_client: tuple[FastAPI, httpx.AsyncClient]) -> None:
    app, client = app_and_client
    svc = app.state.services["angler"]
    k = next(i for i, j in enumerate(svc.profile.joints) if j.motor_id == 3)
    q = svc.driver.positions.copy()
    q[k] = svc.model.upper[k] + 0.5
    too_far = int(round(svc.model.transmission.to_ticks(q)[k]))
    r = await client.put(f"{DX}/3/registers/goal_position", json={"raw": too_far})
    assert r.status_code == 422 and r.json()["code"] == "joint_limit"
    q[k] = (svc.model.lower[k] + svc.model.upper[k]) / 2
    ok = int(round(svc.model.transmission.to_ticks(q)[k]))
    r = await client.put(f"{DX}/3/registers/goal_position", json={"raw": ok})
    assert r.status_code == 200 and r.json()["raw"] == ok
    r = await client.get(f"{DX}/3/registers/goal_position")
    assert r.json()["raw"] == ok


async def test_dynamixel_sync_read_write_and_reboot(app_client: httpx.AsyncClient) -> None:
    r = await app_client.post(f"{DX}/sync-read", json={"name": "model_number", "ids": [1, 2, 2, 4]})
    assert r.status_code == 200
    assert r.json() == {"name": "model_number", "values": {"1": 30, "2": 30, "4": 30}}
    r = await app_client.post(f"{DX}/sync-write", json={"name": "led", "values": {"1": 1, "2": 1}})
    assert r.status_code == 200 and r.json()["command"] == "SYNC_WRITE led"
    r = await app_client.post(f"{DX}/sync-read", json={"name": "led", "ids": [1, 2, 3]})
    assert r.json()["values"] == {"1": 1, "2": 1, "3": 0}
    r = await app_client.post(f"{DX}/sync-write", json={"name": "led", "values": {"1": 0, "2": 5}})
    assert r.status_code == 422 and r.json()["code"] == "out_of_range"
    r = await app_client.post(f"{DX}/sync-read", json={"name": "led", "ids": [1]})
    assert r.json()["values"] == {"1": 1}  # all or nothing: nothing was sent
    r = await app_client.post(f"{DX}/sync-write", json={"name": "goal_position",
                                                        "values": {"8": 2048}})
    assert r.status_code == 422 and r.json()["code"] == "unknown_id"
    r = await app_client.post(f"{DX}/1/reboot")
    assert r.status_code == 200 and r.json()["command"] == "REBOOT 1"


async def test_estop_blocks_writes_but_not_reads_or_torque_off(
        app_client: httpx.AsyncClient) -> None:
    assert (await app_client.post(f"{API}/arms/angler/estop")).status_code == 200
    r = await app_client.put(f"{DX}/1/registers/goal_velocity", json={"raw": 10})
    assert r.status_code == 409 and r.json()["code"] == "estop_latched"
    r = await app_client.post(f"{DX}/1/reboot")
    assert r.status_code == 409 and r.json()["code"] == "estop_latched"
    r = await app_client.get(f"{DX}/1/registers/model_number")
    assert r.status_code == 200
    r = await app_client.put(f"{DX}/1/registers/led", json={"raw": 1})
    assert r.status_code == 200


@pytest.mark.parametrize("gains", [(-0.001, 0.0, 0.0), (0.005, 1e5, 0.0), (0.005, 0.0, -1.0)])
async def test_set_gain_outside_0_to_1000_is_refused_and_nothing_is_sent(
        app_and_client: tuple[FastAPI, httpx.AsyncClient], gains: tuple[float, float, float]
) -> None:
    app, client = app_and_client
    kp, ki, kd = gains
    svc = app.state.services["rbe3001"]
    before = [list(g) for g in svc.driver.link.device.gains]
    r = await client.post("/api/v1/arms/rbe3001/rbe3001/set-gain",
                              json={"axis": 1, "kp": kp, "ki": ki, "kd": kd})
    assert r.status_code == 422 and r.json()["code"] == "invalid_request"
    assert [list(g) for g in svc.driver.link.device.gains] == before
    assert any("greater than or equal" in str(e) or "less than or equal" in str(e)
               for e in r.json()["detail"])


@pytest.mark.parametrize("name, raw", [("id", 9), ("baud_rate", 0), ("operating_mode", 1),
                                       ("status_return_level", 0)])
async def test_driver_settings_of_the_arms_servos_are_refused(
        app_and_client: tuple[FastAPI, httpx.AsyncClient], name: str, raw: int) -> None:
    app, client = app_and_client
    bus = app.state.services["angler"].driver.link.device
    before = bus.servo(2).get(name)
    await client.put(f"{API}/arms/angler/dynamixel/2/registers/torque_enable", json={"raw": 0})
    r = await client.put(f"{API}/arms/angler/dynamixel/2/registers/{name}", json={"raw": raw})
    assert r.status_code == 409 and r.json()["code"] == "in_use"
    assert name in r.json()["detail"]
    r = await client.get(f"{API}/arms/angler/dynamixel/2/registers/id")
    assert r.status_code == 200 and r.json()["raw"] == 2  # still answering as id 2
    assert bus.servo(2).get(name) == before
    r = await client.post(f"{API}/arms/angler/dynamixel/2/reboot")  # torque on, set up again
    assert r.status_code == 200, r.text


async def test_a_joint_that_falls_without_torque_keeps_it_through_passthrough(
        app_and_client: tuple[FastAPI, httpx.AsyncClient]) -> None:
    """The angler's z winch pays out its load once its servo's torque is off (the profile's
    `falls_without_torque`): gravity would move it where no planned move may go. Torque off
    to its servo is 409 `in_use` through the register write and SYNC_WRITE (all or nothing:
    theta3's, in the same SYNC_WRITE, is not sent either), latched or not; the other joints'
    torque goes off as before. A reboot, which switches the torque off until the servo is set
    up again, is 409 `in_use` while the servo holds torque unless the body says the load is
    supported; then it runs (z comes back not homed, as a rebooted multi-turn servo does)."""
    app, client = app_and_client
    svc = app.state.services["angler"]
    bus = svc.driver.link.device
    for attempt in ("PUT", "SYNC", "LATCHED"):
        if attempt == "LATCHED":
            assert (await client.post(f"{API}/arms/angler/estop")).status_code == 200
        r = (await client.post(f"{DX}/sync-write", json={"name": "torque_enable",
                                                         "values": {"3": 0, "4": 0}})
             if attempt == "SYNC" else
             await client.put(f"{DX}/4/registers/torque_enable", json={"raw": 0}))
        assert r.status_code == 409 and r.json()["code"] == "in_use", (attempt, r.text)
        detail = r.json()["detail"]
        assert "servo 4" in detail and "let z fall" in detail, detail
        assert "falls_without_torque" in detail and "/arms/angler/move/joints" in detail
        assert bus.servo(4).torque and bus.servo(3).torque, attempt
    r = await client.put(f"{DX}/3/registers/torque_enable", json={"raw": 0})  # latched: safe
    assert r.status_code == 200 and not bus.servo(3).torque, r.text
    r = await client.post(f"{DX}/4/reboot", json={"load_supported": True})
    assert r.status_code == 409 and r.json()["code"] == "estop_latched", r.text
    assert (await client.delete(f"{API}/arms/angler/estop")).status_code == 200
    r = await client.post(f"{DX}/3/reboot")  # theta3 does not fall: no question asked
    assert r.status_code == 200 and bus.servo(3).torque, r.text
    for body in ({"load_supported": "yes"}, {"load_supported": 1}):  # said, not implied
        r = await client.post(f"{DX}/4/reboot", json=body)
        assert r.status_code == 422 and r.json()["code"] == "invalid_request", (body, r.text)
    for body in (None, {}, {"load_supported": False}):
        r = await client.post(f"{DX}/4/reboot", json=body)
        assert r.status_code == 409 and r.json()["code"] == "in_use", (body, r.text)
        assert "load_supported" in r.json()["detail"] and "z falls" in r.json()["detail"]
        assert bus.servo(4).torque and svc.driver.homed[3], body  # no REBOOT went out
    r = await client.post(f"{DX}/4/reboot", json={"load_supported": True})
    assert r.status_code == 200 and r.json()["command"] == "REBOOT 4", r.text
    assert bus.servo(4).torque and not svc.driver.homed[3]


async def test_the_force_and_the_gains_a_servo_follows_its_plan_with_are_the_drivers(
        app_and_client: tuple[FastAPI, httpx.AsyncClient]) -> None:
    """Goal PWM limits the PWM in a position mode (e-manual, Goal PWM(100)): written 0 during a
    planned move of z and 885 again, the simulated winch caught up at 0.127 m/s against its
    0.05 m/s limit. Goal PWM, the PWM limit and every gain of the arm's own servos are 409
    `in_use` through pass-through (register write and SYNC_WRITE), naming raw access as the
    way; nothing is written and the move ends done."""
    app, client = app_and_client
    svc = app.state.services["angler"]
    bus = svc.driver.link.device
    before = {(i, n): bus.servo(i).get(n) for i in (1, 4)
              for n in ("goal_pwm", "pwm_limit", "position_p_gain", "velocity_i_gain")}
    q = list(svc.positions)
    r = await client.post(f"{API}/arms/angler/move/joints",
                          json={"positions": [q[0], q[1], q[2], 0.12]})
    assert r.status_code == 202, r.text
    motion = r.json()["id"]
    for name, raw in (("goal_pwm", 0), ("pwm_limit", 10), ("position_p_gain", 0),
                      ("velocity_i_gain", 0)):
        r = await client.put(f"{DX}/4/registers/{name}", json={"raw": raw})
        assert r.status_code == 409 and r.json()["code"] == "in_use", (name, r.text)
        assert "raw_access" in r.json()["detail"], r.text
        r = await client.post(f"{DX}/sync-write", json={"name": name, "values": {"1": raw}})
        assert r.status_code == 409 and r.json()["code"] == "in_use", (name, r.text)
    for _ in range(1000):  # the move takes about 1.5 s: bounded at 20 s
        r = await client.get(f"{API}/arms/angler/motions/{motion}")
        if r.json()["status"] not in ("queued", "running"):
            break
        await asyncio.sleep(0.02)
    assert r.status_code == 200 and r.json()["status"] == "done", r.text
    assert {k: bus.servo(k[0]).get(k[1]) for k in before} == before


async def test_no_other_servo_may_take_an_id_of_the_arms(
        app_and_client: tuple[FastAPI, httpx.AsyncClient]) -> None:
    """A servo on the arm's bus that is not the arm's (id 7 here) may be set up through
    pass-through, but not to an id (or Secondary ID) of the arm's own servos: it would take
    the arm's commands (x's goals would move it too) and collide with x's replies."""
    app, client = app_and_client
    bus = app.state.services["angler"].driver.link.device
    from app.arms.dynamixel.sim_mx28 import Mx28Servo
    extra = bus.add_servo(Mx28Servo, id=7, baudrate=1_000_000)
    try:
        for name in ("id", "secondary_id"):
            for way in ("PUT", "SYNC"):
                r = (await client.put(f"{DX}/7/registers/{name}", json={"raw": 2})
                     if way == "PUT" else
                     await client.post(f"{DX}/sync-write", json={"name": name,
                                                                  "values": {"7": 2}}))
                assert r.status_code == 409 and r.json()["code"] == "in_use", (name, r.text)
                assert "servo for x" in r.json()["detail"], r.text
        assert (extra.id, extra.get("secondary_id")) == (7, 255)
        r = await client.put(f"{DX}/7/registers/led", json={"raw": 1})  # its own settings
        assert r.status_code == 200 and extra.get("led") == 1, r.text
        # another id of its own: the simulated servo answers the WRITE from its new id, as
        # ROBOTIS's device library does; that status is the write's (it had been a 504)
        r = await client.put(f"{DX}/7/registers/id", json={"raw": 9})
        assert r.status_code == 200 and r.json()["raw"] == 9, r.text
        assert extra.id == 9
        r = await client.get(f"{DX}/9/registers/led")
        assert r.status_code == 200 and r.json()["raw"] == 1, r.text
        r = await client.get(f"{DX}/7/registers/led")  # nobody answers there now
        assert r.status_code == 504 and r.json()["code"] == "device_timeout", r.text
    finally:
        bus.remove_servo(extra)


async def test_raw_access_and_the_servos_own_shutdown_keep_torque_off_and_the_reboot_open(
        app_and_client: tuple[FastAPI, httpx.AsyncClient]) -> None:
    """Where the servo's torque is already off (its own shutdown after an overload), a reboot
    of a falling joint's servo asks nothing: the load has already fallen or rests. A profile
    with raw access may switch z's torque off through pass-through (its owner's choice)."""
    app, client = app_and_client
    svc = app.state.services["angler"]
    bus = svc.driver.link.device
    bus.servo(4).set("torque_enable", 0)  # as the servo's own Shutdown does
    r = await client.post(f"{DX}/4/reboot")
    assert r.status_code == 200 and bus.servo(4).torque, r.text
    raw = homed_at_start(load_profile("angler")).model_copy(update={"raw_access": True})
    async with running_client(profiles=[raw]) as (app, client):
        bus = app.state.services["angler"].driver.link.device
        r = await client.put(f"{DX}/4/registers/torque_enable", json={"raw": 0})
        assert r.status_code == 200 and not bus.servo(4).torque, r.text
        r = await client.post(f"{DX}/4/reboot")  # (its torque off: as above)
        assert r.status_code == 200 and bus.servo(4).torque, r.text
        r = await client.put(f"{DX}/4/registers/goal_pwm", json={"raw": 400})  # and the force
        assert r.status_code == 200 and bus.servo(4).get("goal_pwm") == 400, r.text


async def _y_alone_leaves_x(client: httpx.AsyncClient, svc: ArmService,
                            q1: np.ndarray) -> None:
    """A planned move of the angler's y alone from `q1`, watched every 2 ms: x stays where it
    is (a move that started from an older command drove x back towards it first)."""
    seen: list[np.ndarray] = []

    async def watch() -> None:
        while True:
            seen.append(np.array(svc.positions, dtype=float))
            await asyncio.sleep(0.002)

    watcher = asyncio.create_task(watch())
    try:
        goal = [q1[0], q1[1] + 0.005, q1[2], q1[3]]
        r = await client.post(f"{API}/arms/angler/move/joints",
                              json={"positions": goal, "wait": True})
        assert r.status_code == 200 and r.json()["status"] == "done", r.text
    finally:
        watcher.cancel()
    xs = np.array([q[0] for q in seen])
    assert len(xs) > 10 and np.max(np.abs(xs - q1[0])) < 1e-3, (q1[0], xs.min(), xs.max())


async def test_torque_goes_off_through_passthrough_but_on_again_only_by_a_reboot(
        app_and_client: tuple[FastAPI, httpx.AsyncClient]) -> None:
    """Torque off, the joints moved by a hand (the simulated world's), torque on again: through
    pass-through that was a write like any other, the server's record of what the arm was told
    kept its last command, and the next planned move started there: a move of y alone drove x
    16 mm back towards it first, a path no check had seen. Now torque on to the arm's own
    servos is 409 `in_use` (nothing written); the README's way, a reboot of each servo and the
    arm homed where the hand left it, has the next move go from there."""
    app, client = app_and_client
    svc = app.state.services["angler"]
    bus = svc.driver.link.device
    tol = 1e-4
    q0 = await held_still(lambda: svc.positions, tol)
    for i in (1, 2, 3):  # (z's winch falls without torque: its torque stays on, next test)
        r = await client.put(f"{DX}/{i}/registers/torque_enable", json={"raw": 0})
        assert r.status_code == 200, r.text
    moved = [q0[0] + 0.03, q0[1] + 0.02, q0[2], q0[3]]
    r = await client.put(f"{API}/arms/angler/world/hand",  # z holds: the hand cannot move it
                         json={"positions": moved[:3] + [q0[3] + 0.01], "wait": True})
    assert r.status_code == 409 and r.json()["code"] == "conflict", r.text
    assert "z hold torque" in r.json()["detail"], r.text
    r = await client.put(f"{API}/arms/angler/world/hand",
                         json={"positions": moved, "speed": 0.1, "wait": True})
    assert r.status_code == 200, r.text
    q1 = await held_still(lambda: svc.positions, tol)
    np.testing.assert_allclose(q1, moved, atol=1e-3)
    for way in ("PUT", "SYNC"):
        r = (await client.put(f"{DX}/1/registers/torque_enable", json={"raw": 1}) if way == "PUT"
             else await client.post(f"{DX}/sync-write", json={"name": "torque_enable",
                                                              "values": {"1": 1, "2": 1}}))
        assert r.status_code == 409 and r.json()["code"] == "in_use", r.text
        assert "reboot" in r.json()["detail"]
        assert not any(bus.servo(i).torque for i in (1, 2, 3))
    for i in (1, 2, 3):
        r = await client.post(f"{DX}/{i}/reboot")
        assert r.status_code == 200, r.text
    assert all(bus.servo(i).torque for i in (1, 2, 3, 4))
    # a rebooted multi-turn servo has lost its turns (x, y): declared where the hand left them
    r = await client.post(f"{API}/arms/angler/home", json={"positions": moved})
    assert r.status_code == 200 and all(r.json()["homed"]), r.text
    q1 = await held_still(lambda: svc.positions, tol)
    np.testing.assert_allclose(q1, moved, atol=1e-3)
    await _y_alone_leaves_x(client, svc, q1)


async def test_torque_off_through_passthrough_then_on_again_by_the_torque_route(
        app_and_client: tuple[FastAPI, httpx.AsyncClient]) -> None:
    """The other way back from a pass-through torque off: `PUT /arms/{arm}/torque` `{"on":
    true}` writes each servo's present position as its goal before the torque, and the arm
    holds where the hand left it (no reboot: the multi-turn joints keep their turns and stay
    homed). The torque off already made the arm told nothing on those joints, so the next
    planned move goes from where they are: a move of y alone leaves x where it is."""
    app, client = app_and_client
    svc = app.state.services["angler"]
    bus = svc.driver.link.device
    tol = 1e-4
    q0 = await held_still(lambda: svc.positions, tol)
    r = await client.post(f"{API}/arms/angler/move/joints",  # a command the servos then hold
                          json={"positions": [q0[0] - 0.01, q0[1], q0[2], q0[3]], "wait": True})
    assert r.status_code == 200 and r.json()["status"] == "done", r.text
    q0 = await held_still(lambda: svc.positions, tol)
    for i in (1, 2, 3):
        r = await client.put(f"{DX}/{i}/registers/torque_enable", json={"raw": 0})
        assert r.status_code == 200, r.text
    told = svc.setpoint()
    assert told is not None
    np.testing.assert_allclose(told[:3], svc.positions[:3])  # told nothing: where they are
    moved = [q0[0] + 0.03, q0[1] + 0.02, q0[2], q0[3]]
    r = await client.put(f"{API}/arms/angler/world/hand",
                         json={"positions": moved, "speed": 0.1, "wait": True})
    assert r.status_code == 200, r.text
    np.testing.assert_allclose(await held_still(lambda: svc.positions, tol), moved, atol=1e-3)
    told = svc.setpoint()  # (a recording's action): where the hand left the joints
    assert told is not None
    np.testing.assert_allclose(told, moved, atol=1e-3)
    r = await client.put(f"{DX}/1/registers/torque_enable", json={"raw": 1})
    assert r.status_code == 409 and "/torque" in r.json()["detail"], r.text
    r = await client.put(f"{API}/arms/angler/torque", json={"on": True})
    assert r.status_code == 200, r.text
    assert all(bus.servo(i).torque for i in (1, 2, 3, 4))
    assert (await client.get(f"{API}/arms/angler")).json()["homed"] == [True] * 4
    q1 = await held_still(lambda: svc.positions, tol)
    np.testing.assert_allclose(q1, moved, atol=1e-3)
    await _y_alone_leaves_x(client, svc, q1)
