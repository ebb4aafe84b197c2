"""The RBE3001 firmware simulator, driven only by bytes through the codec."""

from __future__ import annotations

import math
import struct

import pytest

from app.arms.loading import load_profile
from app.arms.rbe3001.sim import CYCLE_S, Rbe3001Firmware
from protocol.rbe3001 import (
    Ack,
    JointSetpoint,
    SetClaw,
    SetGain,
    SetPid,
    SetPidReply,
    Status,
    StatusReply,
    decode_reply,
    encode_command,
)

TICKS_PER_RAD = 4096 / (2 * math.pi)


def make() -> Rbe3001Firmware:
    fw = Rbe3001Firmware(load_profile("rbe3001"))
    fw.advance(0.0)
    return fw


def ask(fw: Rbe3001Firmware, cmd: SetPid | Status | SetGain | SetClaw, now: float):
    replies = fw.receive(encode_command(cmd), now)
    assert len(replies) == 1
    delay, data = replies[0]
    assert 0.0 <= delay <= 0.002
    assert len(data) == 64
    return decode_reply(cmd, data)


def set_pid(*ticks: float) -> SetPid:
    a, b, c = (JointSetpoint(t) for t in ticks)
    return SetPid((a, b, c))


def run(fw: Rbe3001Firmware, start: float, seconds: float, cmd=None) -> list[StatusReply]:
    """Poll STATUS every 10 ms of simulated time; return the replies."""
    out = []
    steps = round(seconds / 0.01)
    for k in range(1, steps + 1):
        out.append(ask(fw, cmd or Status(), start + k * 0.01))
    return out


def test_status_at_rest() -> None:
    fw = make()
    reply = ask(fw, Status(), 0.0)
    assert isinstance(reply, StatusReply)
    assert reply.position_ticks == (0.0, 0.0, 0.0)
    assert reply.velocity_ticks_s == (0.0, 0.0, 0.0)
    assert all(0.0 <= a <= 1.0 for a in reply.strain_adc)


def test_every_reply_zeroes_the_float_area_as_pidserver() -> None:
    """PidServer.cpp: "re-initialize the packet to all zeros" before writing the readings;
    the design's other servers were written the same way."""
    fw = make()
    status = struct.pack("<I15f", 38, *([7.0] * 15))
    _, data = fw.receive(status, 0.0)[0]
    assert data[40:] == bytes(24)
    pid = struct.pack("<I15f", 37, *([0.0] * 9 + [7.0] * 6))
    _, data = fw.receive(pid, 0.0)[0]
    assert data[40:] == bytes(24)
    for cmd in (SetGain(1, 0.005, 0.0, 0.0), SetClaw(0.5)):
        _, data = fw.receive(encode_command(cmd), 0.01)[0]
        assert data == struct.pack("<I", cmd.command_id) + bytes(60)


def test_echo_option_keeps_the_echoing_build() -> None:
    fw = Rbe3001Firmware(load_profile("rbe3001"), echo=True)
    status = struct.pack("<I15f", 38, *([7.0] * 15))
    _, data = fw.receive(status, 0.0)[0]
    assert struct.unpack("<6f", data[40:]) == (7.0,) * 6
    raw = encode_command(SetClaw(0.5))
    assert fw.receive(raw, 0.0)[0][1] == raw
    profile = load_profile("rbe3001")
    profile.link.sim_echo = True
    assert Rbe3001Firmware(profile).echo is True
    assert Rbe3001Firmware(load_profile("rbe3001")).echo is False


def test_velocity_is_recomputed_every_61_cycles_and_stale_between() -> None:
    fw = make()
    ask(fw, set_pid(1000.0, 0.0, 0.0), 0.0)
    seen = []
    for k in range(1, 200):  # every cycle for half a second of a moving base
        seen.append(ask(fw, Status(), k * CYCLE_S).velocity_ticks_s[0])
    changes = [k for k in range(1, len(seen)) if seen[k] != seen[k - 1]]
    assert len(changes) >= 2
    assert all(b - a == 61 for a, b in zip(changes, changes[1:], strict=False))
    assert seen[0] == 0.0 and max(seen) > 100.0  # moving, yet zero until the first update


def test_gravity_loads_the_shoulder_when_extended() -> None:
    # q = 0: upper arm level, forearm hanging straight down (kinematics/rrr.py convention).
    fw = make()
    reply = ask(fw, Status(), 1.0)
    base, shoulder, elbow = reply.strain_adc
    assert base == pytest.approx(0.5, abs=0.001)
    assert elbow == pytest.approx(0.5, abs=0.001)
    assert shoulder - 0.5 > 0.05  # ~0.6 N m at 5 N m per ADC unit
    # The shoulder droops a few ticks under gravity (ki = 0) and holds there.
    assert -20.0 < reply.position_ticks[1] < 0.0


def test_gravity_loads_shoulder_and_elbow_more_when_stretched_out() -> None:
    hanging = make()
    stretched = Rbe3001Firmware(load_profile("rbe3001"), start_q=(0.0, 0.0, -1.2))
    stretched.advance(0.0)
    a = ask(hanging, Status(), 1.0).strain_adc
    b = ask(stretched, Status(), 1.0).strain_adc
    assert b[1] - 0.5 > a[1] - 0.5 + 0.03
    assert 0.5 - b[2] > 0.03  # the motor holds the forearm up: negative q2 torque


def test_set_pid_moves_over_time_and_converges() -> None:
    fw = make()
    target = 1.0 * TICKS_PER_RAD
    first = ask(fw, set_pid(target, 0.0, 0.0), 0.0)
    assert isinstance(first, SetPidReply)
    assert first.position_ticks[0] == 0.0  # nothing moved yet
    one_cycle = ask(fw, Status(), CYCLE_S)
    assert 0.0 <= one_cycle.position_ticks[0] < 5.0  # no jump
    trace = run(fw, CYCLE_S, 1.5)
    base = [r.position_ticks[0] for r in trace]
    assert 50.0 < base[9] < target - 100.0  # after 0.1 s: under way, far from done
    assert all(b2 >= b1 - 30.0 for b1, b2 in zip(base, base[1:]))  # no violent reversal
    assert max(base) < target * 1.1  # overshoot under 10 %
    assert abs(base[-1] - target) < 10.0
    moving = [r.velocity_ticks_s[0] for r in trace[:30]]
    assert max(moving) > 500.0  # ticks/s: ~1-3 rad/s while moving
    assert trace[-1].velocity_ticks_s[0] == pytest.approx(0.0, abs=20.0)


def test_set_pid_reply_carries_readings() -> None:
    fw = make()
    ask(fw, set_pid(300.0, 0.0, 0.0), 0.0)
    reply = ask(fw, set_pid(300.0, 0.0, 0.0), 0.2)
    assert isinstance(reply, SetPidReply)
    status = ask(fw, Status(), 0.2)
    assert reply.position_ticks == status.position_ticks
    assert reply.velocity_ticks_s == status.velocity_ticks_s
    assert reply.strain_adc == status.strain_adc


def test_setpoint_within_deadband_is_ignored() -> None:
    fw = make()
    ask(fw, set_pid(100.0, 0.0, 0.0), 0.0)
    ask(fw, set_pid(100.005, 0.0, 0.0), 0.01)
    assert fw.setpoint[0] == 100.0
    ask(fw, set_pid(100.5, 0.0, 0.0), 0.02)
    assert fw.setpoint[0] == 100.5


def test_set_gain_and_kp_zero_stops_tracking() -> None:
    fw = make()
    cmd = SetGain(0, 0.0, 0.0, 0.0)
    raw = encode_command(cmd)
    replies = fw.receive(raw, 0.0)
    assert decode_reply(cmd, replies[0][1]) == Ack(39)
    ask(fw, set_pid(500.0, 0.0, 0.0), 0.0)
    end = run(fw, 0.0, 0.5)[-1]
    assert end.position_ticks[0] == 0.0  # base has no gravity: with no drive it stays put
    # Restoring a gain makes it track again.
    ask(fw, SetGain(0, 0.005, 0.0, 0.0), 0.5)
    assert run(fw, 0.5, 1.0)[-1].position_ticks[0] == pytest.approx(500.0, abs=10.0)


def test_integral_gain_narrows_the_gravity_droop_as_the_firmware_does() -> None:
    """The firmware's "integral" is a running mean of the error (PID_Bowler
    `RunAbstractPIDCalc`), so at rest it equals the error and ki adds to kp: ki = kp halves
    the shoulder's standing droop, it does not remove it (a textbook integral would)."""
    droop = []
    for ki in (0.0, 0.005):
        fw = make()
        if ki:
            ask(fw, SetGain(1, 0.005, ki, 0.0), 0.0)
        tail = run(fw, 0.0, 2.0)[-50:]  # the last half second, at rest
        assert len({r.position_ticks[1] for r in tail}) == 1, "not at rest"
        droop.append(tail[-1].position_ticks[1])
    assert droop[0] == pytest.approx(-6.0, abs=1.0)
    assert droop[1] == pytest.approx(droop[0] / 2, abs=0.5)


def test_a_controller_cycle_is_pid_bowlers_arithmetic() -> None:
    """One cycle's output, three cycles after a new setpoint, by hand from PID_Bowler's
    `RunAbstractPIDCalc`: D is the error's change over the cycle (the error before a new
    setpoint counts as 0), I the error's running mean over 20 cycles, zeroed at a sign change."""
    fw = make()
    ask(fw, SetGain(0, 0.001, 0.002, 0.0005), 0.0)
    ask(fw, set_pid(fw.setpoint[0] + 100.0, fw.setpoint[1], fw.setpoint[2]), 0.0)
    sp = fw.setpoint[0]
    # e 100: I = 100 / 20 = 5, D = 100 - 0: 0.1 + 0.05 + 0.01
    assert fw._pid(0, sp - 100.0) == pytest.approx(0.16)
    # e 90: I = 4.5 + 5 * 19 / 20 = 9.25, D = -10: 0.09 - 0.005 + 0.0185
    assert fw._pid(0, sp - 90.0) == pytest.approx(0.1035)
    # e -10: the sign changed, I = 0; D = -100: -0.01 - 0.05
    assert fw._pid(0, sp + 10.0) == pytest.approx(-0.06)
    # a large error: the output clamp (0.3..0.7 around stop 0.5)
    assert fw._pid(0, sp - 5000.0) == pytest.approx(0.2)
    # SET_GAIN keeps the controller's history (setPIDConstants sets the gains only)
    ask(fw, SetGain(0, 0.0, 0.0, 0.001), 0.0)
    assert fw._pid(0, sp - 4990.0) == pytest.approx(0.001 * (4990.0 - 5000.0))


def test_set_claw_moves_at_a_finite_rate() -> None:
    fw = make()
    cmd = SetClaw(1.0)
    raw = encode_command(cmd)
    assert fw.receive(raw, 0.0)[0][1] == raw[:4] + bytes(60)
    fw.advance(0.1)
    assert 0.1 < fw.claw < 0.5
    fw.advance(1.0)
    assert fw.claw == 1.0
    ask(fw, SetClaw(0.25), 1.0)
    fw.advance(2.0)
    assert fw.claw == pytest.approx(0.25)


def test_unknown_id_and_wrong_length_are_silent() -> None:
    fw = make()
    assert fw.receive(struct.pack("<I15f", 65, *([0.0] * 15)), 0.0) == []
    assert fw.receive(encode_command(Status())[:63], 0.0) == []
    assert fw.receive(b"\x00" + encode_command(Status()), 0.0) == []  # report id not stripped
    assert fw.receive(struct.pack("<I15f", 40, 2.0, *([0.0] * 14)), 0.0) == []  # claw 2.0


def test_long_gap_is_capped_and_deterministic() -> None:
    a, b = make(), make()
    for fw in (a, b):
        ask(fw, set_pid(800.0, -200.0, 300.0), 0.0)
        fw.advance(1e6)  # a huge gap must not hang
    assert a.cycles == b.cycles <= 801
    assert ask(a, Status(), 1e6) == ask(b, Status(), 1e6)


def test_encoder_readings_are_quarter_ticks() -> None:
    fw = make()
    ask(fw, set_pid(700.0, 0.0, 0.0), 0.0)
    for r in run(fw, 0.0, 0.3):
        for p in r.position_ticks:
            assert (p * 4) == int(p * 4)  # 4-sample average of whole ticks


def test_no_gain_can_spin_a_joint_past_its_end_stops() -> None:
    """A negative gain turns the loop unstable: the joint runs to the mechanism's end stop and
    stays there, as on the arm, instead of spinning for ever."""
    from app.arms.loading import load_profile

    profile = load_profile("rbe3001")
    fw = Rbe3001Firmware(profile)
    t = 0.0
    fw.receive(encode_command(SetGain(1, 50.0, 0.0, 0.0)), t)  # valid here; sign flipped below
    fw.gains[1] = [-50.0, 0.0, 0.0]
    fw.receive(encode_command(SetPid((JointSetpoint(0, 0, 0), JointSetpoint(500, 0, 0),
                                      JointSetpoint(0, 0, 0)))), t)
    for _ in range(200):  # 10 s
        t += 0.05
        fw.advance(t)
    lo, hi = fw.hard_stops[1]
    assert lo == pytest.approx(profile.joints[1].min - 0.3)
    assert lo <= fw.q[1] <= hi and fw.q[1] == pytest.approx(lo)
    assert fw.qd[1] == 0.0
