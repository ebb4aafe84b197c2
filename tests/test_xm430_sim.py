"""XM430-W350 servos on the simulated Dynamixel bus: the public DynamixelSDK sees model 1020
over a pty, the XM430's control table answers, and MX-28 servos on the same bus are unchanged."""

from __future__ import annotations

import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from dynamixel_sdk import COMM_SUCCESS, GroupSyncRead, GroupSyncWrite

from app.arms.dynamixel.sim_bus import DynamixelBus
from app.arms.dynamixel.sim_mx28 import Mx28Servo
from app.arms.dynamixel.sim_xm430 import Xm430Servo
from app.sim.serve import main
from kinematics import omx
from protocol import dynamixel as dxl
from protocol import xm430
from protocol.dynamixel import ErrorCode
from tests.test_dynamixel_sim import SdkBus, patient, sdk_over_pty

OMX_IDS = omx.IDS  # 11..15: joints 1..4 and the gripper


def _omx_bus(extra_mx28: tuple[int, ...] = ()) -> DynamixelBus:
    return DynamixelBus(ids=(*OMX_IDS, *extra_mx28),
                        models={i: Xm430Servo for i in OMX_IDS})


def test_servo_classes_and_table() -> None:
    bus = _omx_bus(extra_mx28=(1,))
    assert type(bus.servos[0]) is Mx28Servo and bus.servos[0].id == 1
    assert all(type(s) is Xm430Servo for s in bus.servos[1:])
    s = bus.servos[1]
    assert len(s.mem) == xm430.TABLE_END
    assert (s.get("model_number"), s.get("velocity_limit"), s.get("position_p_gain"),
            s.get("current_limit")) == (1020, 200, 800, 1193)
    assert s.get("goal_current") == 1193


def test_write_checks_on_the_xm430_items() -> None:
    s = Xm430Servo(11)
    at = xm430.item
    # Goal Current within Current Limit: beyond it, the data limit error; nothing changes
    assert s.write(at("current_limit").address, dxl.to_bytes(500, 2)) == 0
    assert s.write(at("goal_current").address, dxl.to_bytes(600, 2)) == ErrorCode.DATA_LIMIT
    assert s.get("goal_current") == 1193
    assert s.write(at("goal_current").address, dxl.to_bytes(-500, 2)) == 0
    assert s.get("goal_current") == -500
    # operating modes 0 and 5 exist on the XM430, not on the MX-28
    for mode in (0, 5):
        assert s.write(11, bytes([mode])) == 0
        assert Mx28Servo(1).write(11, bytes([mode])) == ErrorCode.DATA_RANGE
    assert s.write(11, bytes([2])) == ErrorCode.DATA_RANGE
    # Present Load's address holds Present Current, read-only
    assert s.write(126, dxl.to_bytes(1, 2)) == ErrorCode.ACCESS


def test_current_based_position_mode_moves_multi_turn_at_no_load_speed() -> None:
    s = Xm430Servo(12, operating_mode=5)
    assert s.write(64, b"\x01") == 0
    goal = 2048 + 4096  # a full turn beyond
    assert s.write(116, dxl.to_bytes(goal, 4)) == 0
    s.advance(0.5, 0.5)
    # no profile: the motor runs at its no-load speed, 46 rpm at 12 V
    cap = 46.0 / 60.0 * 4096
    assert s.vel == pytest.approx(cap)
    assert s.get("present_current") > 0  # load model shown as current
    s.advance(2.0, 2.5)
    assert s.get("present_position") == goal


def test_sim_xm430_is_slower_than_the_mx28() -> None:
    xm, mx = Xm430Servo(11), Mx28Servo(1)
    for s in (xm, mx):
        assert s.write(64, b"\x01") == 0
        assert s.write(116, dxl.to_bytes(4000, 4)) == 0
        s.advance(0.1, 0.1)
    assert xm.vel == pytest.approx(46.0 / 55.0 * mx.vel)


@pytest.fixture()
def sdk_omx(tmp_path: Path) -> Iterator[SdkBus]:
    with sdk_over_pty(_omx_bus(extra_mx28=(1,)), tmp_path / "ttyOMX") as sdk:
        yield sdk


def test_sdk_pings_model_1020(sdk_omx: SdkBus) -> None:
    port, ph, _ = sdk_omx
    assert patient(ph.ping, port, 11) == (1020, COMM_SUCCESS, 0)
    assert patient(ph.ping, port, 1) == (30, COMM_SUCCESS, 0)
    found, result = patient(ph.broadcastPing, port)
    assert result == COMM_SUCCESS
    assert found == {1: [30, 45], **{i: [1020, 46] for i in OMX_IDS}}
    assert patient(ph.read2ByteTxRx, port, 13, 0) == (1020, COMM_SUCCESS, 0)
    assert patient(ph.read2ByteTxRx, port, 13, 38) == (1193, COMM_SUCCESS, 0)


def test_sdk_sync_write_moves_the_arm_joints(sdk_omx: SdkBus) -> None:
    port, ph, _ = sdk_omx
    joints = OMX_IDS[:4]
    for i in joints:
        assert patient(ph.write1ByteTxRx, port, i, 64, 1) == (COMM_SUCCESS, 0)
    goals = {11: 2048, 12: 1331, 13: 2276, 14: 2504}  # ~ the home pose (0, -1.05, 0.35, 0.70)
    writer = GroupSyncWrite(port, ph, 116, 4)
    for i, g in goals.items():
        assert writer.addParam(i, list(dxl.to_bytes(g, 4)))
    assert writer.txPacket() == COMM_SUCCESS
    reader = GroupSyncRead(port, ph, 132, 4)
    for i in joints:
        assert reader.addParam(i)
    deadline = time.monotonic() + 20.0
    while True:
        assert patient(reader.txRxPacket) == COMM_SUCCESS
        present = {i: reader.getData(i, 132, 4) for i in joints}
        if present == goals or time.monotonic() > deadline:
            break
        time.sleep(0.05)
    assert present == goals


def test_cli_xm430_ids_must_be_on_the_bus(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["dynamixel", "--listen", "tcp://127.0.0.1:0", "--ids", "11,12",
                 "--xm430", "11,13"]) == 2
    assert "no servo 13" in capsys.readouterr().out


def test_cli_serves_xm430_over_tcp() -> None:
    ids = ",".join(str(i) for i in OMX_IDS)
    proc = subprocess.Popen(
        [sys.executable, "-m", "app.sim.serve", "dynamixel", "--listen", "tcp://127.0.0.1:0",
         "--ids", f"1,{ids}", "--xm430", ids], stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None
        port = int(proc.stdout.readline().split("socket://127.0.0.1:")[1].rstrip(")\n"))
        with socket.create_connection(("127.0.0.1", port), timeout=5) as sock:
            for sid, model in ((11, 1020), (15, 1020), (1, 30)):
                sock.sendall(dxl.ping(sid))
                parser = dxl.Parser()
                events: list[object] = []
                while not events:
                    parser.feed(sock.recv(256))
                    events = list(parser)
                reply = events[0]
                assert isinstance(reply, dxl.Packet) and reply.id == sid
                assert dxl.from_bytes(reply.params[:2], signed=False) == model
    finally:
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=10) == 0
