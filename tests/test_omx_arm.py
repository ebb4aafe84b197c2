"""The OpenManipulator-X arm type (app/arms/openmanipulator_x): its registry entry, profile,
kinematics model (pitch, every IK branch, the Jacobian, the joint chain the dashboard draws),
its simulated bus of XM430s (the public DynamixelSDK pings model 1020 there) and its driver
over the simulated link: joints, the gripper servo, faults and reboot."""

from __future__ import annotations

import asyncio
import math
import signal
import socket
import subprocess
import sys
from collections.abc import AsyncIterator, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from dynamixel_sdk import COMM_SUCCESS

from app.arms import ARM_TYPES, arm_type
from app.arms.dynamixel.sim_bus import DynamixelBus
from app.arms.dynamixel.sim_xm430 import Xm430Servo
from app.arms.loading import check_profile, load_arms, load_profile
from app.arms.model import chain_points
from app.arms.openmanipulator_x.driver import OmxDriver
from app.config import homed_at_start
from app.device.factory import make_sim_device
from app.errors import JointLimit, Unreachable
from app.links.sim import SimLink
from app.telemetry.hub import TelemetryHub
from kinematics import omx
from protocol import dynamixel as dxl
from protocol import xm430
from tests.test_dynamixel_sim import SdkBus, patient, sdk_over_pty

PROFILE = load_profile("openmanipulator_x")
TYPE = arm_type("openmanipulator_x")
MODEL = TYPE.model(PROFILE)


# ------------------------------------------------------------------ registry and profile


def test_one_registry_line_and_the_type() -> None:
    assert ARM_TYPES["openmanipulator_x"] == "app.arms.openmanipulator_x"
    assert TYPE.name == PROFILE.model == "openmanipulator_x"
    assert TYPE.protocol == "dynamixel" and TYPE.control_table is xm430
    assert TYPE.has_pitch is MODEL.has_pitch is True
    assert TYPE.joints == len(PROFILE.joints) == 4
    assert TYPE.routers == ("app.arms.dynamixel.api",)
    # API.md: the default server hosts the rbe3001 and the angler only
    assert [p.model for p in load_arms(None)] == ["rbe3001", "angler"]


def test_profile_gripper_is_servo_15_in_current_based_position_mode() -> None:
    g = PROFILE.gripper
    assert g.actuated and g.motor_id == omx.IDS[4] == 15
    assert xm430.OPERATING_MODES[g.operating_mode or 0] == "current_based_position"
    assert [j.motor_id for j in PROFILE.joints] == list(omx.IDS[:4])
    assert [j.operating_mode for j in PROFILE.joints] == [3, 3, 3, 3]  # position mode
    assert not any(j.needs_homing for j in PROFILE.joints)  # absolute encoders


def test_profile_refused_without_motor_ids() -> None:
    data = PROFILE.model_dump()
    data["joints"][2]["motor_id"] = None
    with pytest.raises(ValueError, match="need a Dynamixel motor_id"):
        check_profile(data)
    data = PROFILE.model_dump()
    data["geometry"].pop("l4")
    with pytest.raises(ValueError, match="geometry needs"):
        check_profile(data)


# ------------------------------------------------------------------ kinematics model


def test_model_fk_and_pitch_are_kinematics_omx() -> None:
    q = np.array([[0.0, 0.0, 0.0, 0.0], [0.3, -0.5, 0.4, 0.2]])
    assert np.allclose(MODEL.fk(q), omx.fk(q)[:, :3])
    pitch = MODEL.pitch(q)
    assert pitch is not None and np.allclose(pitch, omx.fk(q)[:, 3])
    # every joint at 0: an inverted L, the tip at (286, 0, 204.5) mm, pitch 0
    assert np.allclose(MODEL.fk(q[0]), [0.286, 0.0, 0.2045], atol=1e-12)
    assert float(MODEL.pitch(q[0])) == pytest.approx(0.0, abs=1e-12)  # type: ignore[arg-type]


def test_chain_draws_the_joint_origins() -> None:
    rng = np.random.default_rng(3)
    for q in rng.uniform(MODEL.lower, MODEL.upper, size=(50, 4)):
        assert np.allclose(chain_points(MODEL.chain(), q), MODEL.joint_origins(q), atol=1e-12)
    assert MODEL.describe()["points"] == list(omx.POINTS)


def test_ik_with_pitch_every_branch_round_trips() -> None:
    rng = np.random.default_rng(7)
    seen = 0
    for q in rng.uniform(MODEL.lower, MODEL.upper, size=(200, 4)):
        p, pitch = MODEL.fk(q), float(MODEL.pitch(q))  # type: ignore[arg-type]
        sols = MODEL.ik(p, pitch)
        assert any(np.allclose(s.positions, q, atol=1e-7) for s in sols)
        for s in sols:  # every branch reaches the tip at the pitch
            assert np.allclose(MODEL.fk(s.positions), p, atol=1e-9)
            assert float(MODEL.pitch(s.positions)) == pytest.approx(  # type: ignore[arg-type]
                pitch, abs=1e-9)
            assert s.within_limits == (not MODEL.violations(s.positions))
        seen += len(sols)
    assert seen > 200  # more than one branch where the limits allow


def test_ik_without_pitch_picks_one_within_the_limits() -> None:
    p = np.array([0.2, 0.05, 0.1])
    sols = MODEL.ik(p)
    assert sols and all(s.within_limits for s in sols)
    assert np.allclose(MODEL.fk(sols[0].positions), p, atol=1e-9)
    best = MODEL.ik_best(p, np.zeros(4))
    assert np.allclose(MODEL.fk(best.positions), p, atol=1e-9)


def test_unreachable_pose_and_pitch_say_why() -> None:
    with pytest.raises(Unreachable, match="out of reach"):
        MODEL.ik(np.array([0.6, 0.0, 0.1]))
    with pytest.raises(Unreachable, match="out of reach at pitch"):
        MODEL.ik(np.array([0.38, 0.0, 0.08]), pitch=1.5)  # far, tool straight up
    with pytest.raises(JointLimit):  # reachable only outside the joint limits
        MODEL.ik_best(np.array([0.05, 0.0, 0.05]), None, pitch=math.pi / 2)


def test_jacobian_against_finite_differences_of_tip_and_pitch() -> None:
    rng = np.random.default_rng(11)
    h = 1e-6
    for q in rng.uniform(MODEL.lower, MODEL.upper, size=(20, 4)):
        def f(x: np.ndarray) -> np.ndarray:
            return np.array([*MODEL.fk(x), float(MODEL.pitch(x))])  # type: ignore[arg-type]
        num = np.stack([(f(q + h * e) - f(q - h * e)) / (2 * h) for e in np.eye(4)], axis=1)
        assert np.allclose(MODEL.jacobian(q), num, atol=1e-6)


def test_line_ik_turns_the_pitch_evenly() -> None:
    q0 = np.array(omx.HOME)
    p = np.array([0.2, -0.05, 0.12])
    near = MODEL.line_ik(p, q0, -0.6, None)
    start = MODEL.fk(q0)
    p0 = float(MODEL.pitch(q0))  # type: ignore[arg-type]
    q = q0
    for s in np.linspace(0.0, 1.0, 11):
        q = near(start + s * (p - start), q)
        assert np.allclose(MODEL.fk(q), start + s * (p - start), atol=1e-9)
        assert float(MODEL.pitch(q)) == pytest.approx(  # type: ignore[arg-type]
            p0 + s * (-0.6 - p0), abs=1e-9)


# ------------------------------------------------------------------ simulator


def test_simulator_holds_five_xm430s_in_their_modes() -> None:
    bus = make_sim_device(PROFILE)
    assert isinstance(bus, DynamixelBus)
    assert [s.id for s in bus.servos] == [11, 12, 13, 14, 15]
    assert all(isinstance(s, Xm430Servo) for s in bus.servos)
    assert [s.get("operating_mode") for s in bus.servos] == [3, 3, 3, 3, 5]
    assert {s.get("model_number") for s in bus.servos} == {xm430.MODEL_NUMBER}


@pytest.fixture()
def sdk_package_bus(tmp_path: Path) -> Iterator[SdkBus]:
    bus = make_sim_device(PROFILE)
    assert isinstance(bus, DynamixelBus)
    with sdk_over_pty(bus, tmp_path / "ttyOMX") as sdk:
        yield sdk


def test_sdk_pings_model_1020_on_the_package_simulator(sdk_package_bus: SdkBus) -> None:
    port, ph, _ = sdk_package_bus
    for i in omx.IDS:
        assert patient(ph.ping, port, i) == (1020, COMM_SUCCESS, 0)
    assert patient(ph.read1ByteTxRx, port, 15, 11) == (5, COMM_SUCCESS, 0)


def test_sim_cli_serves_the_profile_over_tcp() -> None:
    """`armserver sim openmanipulator_x`: the package's simulator, the same bytes as the arm."""
    proc = subprocess.Popen([sys.executable, "-m", "app.sim.serve", "openmanipulator_x",
                             "--listen", "tcp://127.0.0.1:0"], stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None
        port = int(proc.stdout.readline().split("socket://127.0.0.1:")[1].split(")")[0])
        with socket.create_connection(("127.0.0.1", port), timeout=5) as sock:
            for packet, sid in ((dxl.ping(15), 15), (dxl.read(15, 11, 1), 15)):
                sock.sendall(packet)
                parser = dxl.Parser()
                events: list[object] = []
                while not events:
                    parser.feed(sock.recv(256))
                    events = list(parser)
                assert isinstance(events[0], dxl.Packet) and events[0].id == sid
                if packet[7] == dxl.Instruction.PING:
                    assert dxl.from_bytes(events[0].params[:2], signed=False) == 1020
                else:
                    assert events[0].params == bytes([5])  # current-based position mode
    finally:
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=10) == 0


# ------------------------------------------------------------------ driver


async def _until(cond: Any, timeout: float = 5.0) -> None:
    deadline = asyncio.get_running_loop().time() + timeout
    while not cond():
        if asyncio.get_running_loop().time() > deadline:
            raise AssertionError("condition not met in time")
        await asyncio.sleep(0.02)


@pytest.fixture()
async def driver() -> AsyncIterator[tuple[OmxDriver, DynamixelBus]]:
    profile = homed_at_start(PROFILE)
    bus = make_sim_device(profile)
    assert isinstance(bus, DynamixelBus)
    drv = TYPE.driver(profile, SimLink(bus, address="sim:omx"), TelemetryHub("omx"))
    assert isinstance(drv, OmxDriver)
    await drv.start()
    try:
        assert await drv.wait_connected(5.0), drv.link.last_error
        yield drv, bus
    finally:
        await drv.close()


async def test_driver_sets_up_every_servo_and_reads_the_joints(
        driver: tuple[OmxDriver, DynamixelBus]) -> None:
    drv, bus = driver
    assert all(drv.homed)
    assert all(s.get("torque_enable") == 1 for s in bus.servos)
    assert drv.positions is not None and np.allclose(drv.positions, 0.0, atol=1e-9)
    assert drv.gripper == pytest.approx(0.5)  # the simulated servo starts mid-turn: 0 m
    assert bus.servo(15).get("operating_mode") == 5  # type: ignore[union-attr]
    sample = drv.hub.latest
    assert sample is not None
    q = np.array([0.2, -0.3, 0.4, 0.1])
    await drv.command_joints(q)
    await _until(lambda: drv.positions is not None
                 and np.allclose(drv.positions, q, atol=2 * 2 * math.pi / 4096))
    assert drv.torques_raw is not None  # Present Current read as joint torque


async def test_gripper_opens_and_closes_its_servo(driver: tuple[OmxDriver, DynamixelBus]) -> None:
    drv, bus = driver
    g = PROFILE.gripper
    await drv.set_gripper(1.0)  # closed: -0.010 m, +0.667 rad on the servo
    want = round(2048 + g.min * g.rad_per_m * 4096 / (2 * math.pi))
    assert bus.servo(15).get("goal_position") == want == 2483  # type: ignore[union-attr]
    await _until(lambda: drv.gripper is not None and abs(drv.gripper - 1.0) < 0.01)
    await drv.set_gripper(0.0)
    assert bus.servo(15).get("goal_position") == 2048 - (2483 - 2048)  # type: ignore[union-attr]
    await _until(lambda: drv.gripper is not None and abs(drv.gripper) < 0.01)


async def test_gripper_fault_is_reported_and_cleared_by_reboot(
        driver: tuple[OmxDriver, DynamixelBus]) -> None:
    drv, bus = driver
    bus.inject_hardware_error(15, "overload")
    await _until(lambda: drv.faults)
    [f] = drv.faults
    assert (f["servo"], f["joint"], f["bits"]) == (15, "gripper", ["overload"])
    await drv.reboot(15)
    await _until(lambda: not drv.faults)
    assert bus.servo(15).get("operating_mode") == 5  # type: ignore[union-attr]
    assert bus.servo(15).get("torque_enable") == 1  # type: ignore[union-attr]


async def test_ping_and_register_reads_through_the_driver(
        driver: tuple[OmxDriver, DynamixelBus]) -> None:
    drv, _ = driver
    assert await drv.ping(12) == [(12, 1020, 46)]
    assert await drv.read_register(13, xm430.item("current_limit")) == 1193
    assert await drv.read_register(15, xm430.item("operating_mode")) == 5
