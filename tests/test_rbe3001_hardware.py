"""The rbe3001 as the real firmware behaves (issue 10): replies that zero the float area (no
echo to match on), stale velocity, strain-gauge calibration labelled for what it is, a force
tare and one singularity rule for tip force. Over real transports (pty, socket://) and the
real app; nothing of our own code is mocked."""

from __future__ import annotations

import asyncio
import contextlib
import math

import httpx
import numpy as np
import pytest
from _wait import fresh_state, new_samples, wait_for
from conftest import (
    OPERATOR,
    PTY_REPLY_S,
    VIEWER,
    make_settings,
    running_client,
    with_reply_timeout,
)

from app.arms import model_for
from app.arms.loading import load_profile
from app.arms.rbe3001.driver import Rbe3001Driver
from app.arms.rbe3001.sim import Rbe3001Firmware
from app.config import FaultConfig, ForceConfig
from app.errors import DeviceTimeout
from app.links.serial import SerialLink
from app.links.sim import SimLink
from app.links.threaded import ThreadLink
from app.service import ArmService
from app.sim.serve import serve_pty, serve_tcp
from app.telemetry.hub import TelemetryHub
from kinematics.singular import TIP_FORCE_MAX_COND, condition_number
from protocol import rbe3001 as rb

API = "/api/v1"

@pytest.fixture(params=[SerialLink, ThreadLink], ids=["asyncio", "thread"])
def serial_link(request):
    """Each serial link: on the loop (pyserial-asyncio), and on a thread of its own (issue 27,
    the default for a profile's serial link)."""
    return request.param



#: The firmware served from this process over a real transport: conftest's reply timeout for it.
IN_PROCESS = with_reply_timeout(load_profile("rbe3001"))


async def _started(link, profile=None) -> Rbe3001Driver:
    profile = profile or load_profile("rbe3001")
    driver = Rbe3001Driver(profile, link, TelemetryHub(profile.name))
    await driver.start()
    assert await driver.wait_connected(5.0), f"never connected: {link.last_error}"
    return driver


async def _exercise(driver: Rbe3001Driver) -> None:
    """Samples flow, and every command the arm has gets its answer."""
    seq0 = driver.hub.latest["seq"]
    await wait_for(lambda: driver.hub.latest["seq"] > seq0 + 10, what="samples flowing")
    assert not driver.stale
    status = await driver.status()
    assert isinstance(status, rb.StatusReply)
    assert await driver.set_gain(1, 0.005, 0.0, 0.0) == "acknowledged"
    assert await driver.set_claw(0.5) == "acknowledged" and driver.gripper == 0.5
    reply = await driver.set_pid([(200.0, 0, 0), (0.0, 0, 0), (0.0, 0, 0)])
    assert isinstance(reply, rb.SetPidReply)
    async def there() -> bool:
        return abs((await driver.status()).position_ticks[0] - 200.0) < 15

    with contextlib.suppress(AssertionError):  # judged below, with the numbers
        await wait_for(there, every=0.05)
    assert abs((await driver.status()).position_ticks[0] - 200.0) < 15
    assert driver.stats["corrupt"] == 0


@pytest.mark.parametrize("echo", [False, True], ids=["zeroing", "echoing"])
async def test_driver_over_a_socket_url_against_both_firmware_builds(echo, serial_link):
    server = await serve_tcp(Rbe3001Firmware(load_profile("rbe3001"), echo=echo))
    driver = await _started(serial_link(f"socket://127.0.0.1:{server.port}"), IN_PROCESS)
    try:
        await _exercise(driver)
    finally:
        await driver.close()
        await server.close()


@pytest.mark.parametrize("echo", [False, True], ids=["zeroing", "echoing"])
async def test_driver_over_a_pty_against_both_firmware_builds(echo, tmp_path, serial_link):
    path = tmp_path / "ttyRBE"
    server = await serve_pty(Rbe3001Firmware(load_profile("rbe3001"), echo=echo), path)
    driver = await _started(serial_link(str(path)),
                            with_reply_timeout(load_profile("rbe3001"), PTY_REPLY_S))
    try:
        await _exercise(driver)
    finally:
        await driver.close()
        await server.close()


async def test_driver_in_process_against_the_zeroing_default():
    profile = load_profile("rbe3001")
    assert profile.link.sim_echo is False  # faithful by default
    driver = await _started(SimLink(Rbe3001Firmware(profile)), profile)
    try:
        await _exercise(driver)
    finally:
        await driver.close()


async def test_a_late_status_reply_never_answers_the_next_status():
    """Zeroing firmware, no tag: two STATUS replies look alike but for their readings. The
    first STATUS times out; its reply comes later with the old reading; the arm meanwhile
    reads 1000 ticks further on. The next STATUS must answer the new reading."""
    fw = Rbe3001Firmware(load_profile("rbe3001"))
    link = SimLink(fw)
    driver = await _started(link)
    try:
        link.set_faults(FaultConfig(latency_s=driver.timeout * 1.6))
        with pytest.raises(DeviceTimeout):
            await driver.status()
        link.set_faults(FaultConfig())
        fw.offset[0] += 1000.0  # the base encoder now reads 1000 ticks more ...
        fw.setpoint[0] += 1000.0  # ... and the controller holds it there
        # the 4-sample encoder average catches up: 10 ms of the firmware's 400 Hz, on the
        # loop's clock that steps the simulated firmware (a busy machine only waits longer)
        await asyncio.sleep(0.02)
        for _ in range(5):
            reply = await driver.status()
            assert reply.position_ticks[0] > 900.0, reply
        assert driver.stats["stale_replies"] >= 1  # the late ones were seen and dropped
    finally:
        await driver.close()


async def test_an_unknown_command_error_packet_is_a_device_error():
    """Later SimplePacketComs builds answer an id they do not serve with error id 99."""
    m = rb.ReplyMatcher()
    m.request(rb.SetClaw(0.1))
    err = (99).to_bytes(4, "little") + (40).to_bytes(4, "little") + bytes(56)
    with pytest.raises(rb.UnknownToFirmware):
        m.match(err)


# ------------------------------------------------------------------ singularity rule


def test_tip_force_is_null_near_the_elbow_singularity_never_huge():
    model = model_for(load_profile("rbe3001"))
    tau = np.array([0.0, 0.1, 0.0])  # 0.1 N m on the shoulder
    ordinary = model.tip_force(np.array([0.0, 0.6, 0.3]), tau)
    assert ordinary is not None and np.linalg.norm(ordinary) < 2.0
    for q2 in (-math.pi / 2 + 0.001, math.pi / 2 - 0.003):  # stretched, folded
        q = np.array([0.0, 0.6, q2])
        assert model.tip_force(q, tau) is None
        why = model.tip_force_unavailable(q)
        assert why is not None and "condition number" in why
    # One rule everywhere: null exactly where cond(J) exceeds the constant.
    for q in np.random.default_rng(3).uniform(model.lower, model.upper, size=(200, 3)):
        cond = float(condition_number(model.jacobian(q)))
        assert (model.tip_force(q, tau) is None) == (cond > TIP_FORCE_MAX_COND)


async def test_samples_and_detail_say_why_tip_force_is_null_at_a_singular_pose():
    profile = load_profile("rbe3001")
    fw = Rbe3001Firmware(profile, start_q=(0.0, 0.6, math.pi / 2 - 0.003))  # folded
    driver = await _started(SimLink(fw), profile)
    try:
        await new_samples(driver.hub, 5)
        sample = driver.hub.latest
        assert sample["torques"] is not None and sample["tip_force"] is None
        info = ArmService(profile, driver).force_info()
        assert info is not None and info.tip_force_unavailable is not None
        assert "condition number" in info.tip_force_unavailable
        assert info.max_condition_number == TIP_FORCE_MAX_COND
    finally:
        await driver.close()


# ------------------------------------------------------------------ calibration constants


def test_strain_constants_take_the_published_form_and_placeholders_are_flagged():
    profile = load_profile("rbe3001")
    assert profile.force is not None and profile.force.calibrated is False
    assert "placeholder" in profile.force.note
    k = 178.5
    f = ForceConfig(k=[k, k, k], y=[-0.5760 * k, -0.4610 * k, -0.4835 * k], calibrated=True)
    assert f.scale == [k, k, k]
    assert f.offset == pytest.approx([0.5760, 0.4610, 0.4835])
    legacy = ForceConfig(adc_scale=[5.0] * 3, adc_offset=[0.5] * 3)
    assert legacy.k == [5.0] * 3 and legacy.y == [-2.5] * 3
    with pytest.raises(ValueError):
        ForceConfig(k=[1.0, 0.0, 1.0], y=[0.0, 0.0, 0.0])
    with pytest.raises(ValueError):
        ForceConfig(calibrated=True)


def test_profile_states_a_settle_tolerance_the_hardware_can_hold():
    tol = [j.settle_tolerance for j in load_profile("rbe3001").joints]
    # at least the firmware's motor hysteresis (2 ticks) and under a proportional band (40)
    ticks = [t * 4096 / (2 * math.pi) for t in tol]
    assert all(2.0 < t < 40.0 for t in ticks), ticks


# ------------------------------------------------------------------ the Force API


async def test_detail_labels_placeholder_constants(app_client: httpx.AsyncClient):
    d = (await app_client.get(f"{API}/arms/rbe3001")).json()
    force = d["force"]
    assert force["source"] == "strain_gauges" and force["calibrated"] is False
    assert "placeholder" in force["note"] and "Calibrating the strain gauges" in force["note"]
    assert force["tare"] is None and force["max_condition_number"] == TIP_FORCE_MAX_COND
    assert force["tip_force_unavailable"] is None and force["condition_number"] < 20


async def _torques(client: httpx.AsyncClient) -> list[float]:
    return (await client.get(f"{API}/arms/rbe3001/state")).json()["torques"]


async def _settled_torques(client: httpx.AsyncClient) -> list[float]:
    """The torques once the arm has settled under gravity (a steady load on the shoulder)."""
    async def steady() -> list[float] | None:
        a = await _torques(client)
        await asyncio.sleep(0.1)  # the window "steady" is judged over
        b = await _torques(client)
        return b if np.allclose(a, b, atol=0.005) else None

    return list(await wait_for(steady, what="steady torques"))


async def test_tare_zeroes_torques_and_tip_force_until_cleared(app_client: httpx.AsyncClient):
    before = await _settled_torques(app_client)
    assert abs(before[1]) > 0.05  # the gravity load (placeholder constants, but not zero)
    r = await app_client.post(f"{API}/arms/rbe3001/force/tare")
    assert r.status_code == 200, r.text
    body = r.json()
    assert body["joints"] == ["base", "shoulder", "elbow"]
    np.testing.assert_allclose(body["offsets"], before, atol=0.02)
    state = await fresh_state(app_client, "rbe3001")  # a sample taken after the tare
    np.testing.assert_allclose(state["torques"], [0.0, 0.0, 0.0], atol=0.02)
    f = state["tip_force"]
    assert f is not None and math.hypot(f["x"], f["y"], f["z"]) < 0.5
    d = (await app_client.get(f"{API}/arms/rbe3001")).json()
    np.testing.assert_allclose(d["force"]["tare"], body["offsets"])
    r = await app_client.delete(f"{API}/arms/rbe3001/force/tare")
    assert r.status_code == 200 and r.json()["offsets"] is None
    await fresh_state(app_client, "rbe3001")  # a sample taken after the tare is cleared
    np.testing.assert_allclose(await _torques(app_client), before, atol=0.02)
    assert (await app_client.get(f"{API}/arms/rbe3001")).json()["force"]["tare"] is None


async def test_tare_needs_an_operator_and_a_known_arm():
    settings = make_settings(operator_tokens=OPERATOR, viewer_tokens=VIEWER)
    async with running_client(settings) as (_, client):
        url = f"{API}/arms/rbe3001/force/tare"
        r = await client.post(url)
        assert r.status_code == 401 and r.json()["code"] == "unauthorized"
        r = await client.post(url, headers={"Authorization": f"Bearer {VIEWER}"})
        assert r.status_code == 403 and r.json()["code"] == "forbidden"
        r = await client.post(f"{API}/arms/nope/force/tare",
                              headers={"Authorization": f"Bearer {OPERATOR}"})
        assert r.status_code == 404 and r.json()["code"] == "unknown_arm"
        r = await client.post(url, headers={"Authorization": f"Bearer {OPERATOR}"})
        assert r.status_code == 200 and len(r.json()["offsets"]) == 3
