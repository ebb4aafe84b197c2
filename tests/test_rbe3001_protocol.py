"""The RBE3001 packet codec against hand-built byte strings (struct, little-endian)."""

from __future__ import annotations

import math
import struct

import pytest

from protocol.rbe3001 import (
    ERROR_ID,
    N_FLOATS,
    PACKET_SIZE,
    Ack,
    CommandId,
    DecodeError,
    FrameParser,
    JointSetpoint,
    RawPacket,
    ReplyMatcher,
    SetClaw,
    SetGain,
    SetPid,
    SetPidReply,
    Status,
    StatusReply,
    UnknownCommand,
    UnknownToFirmware,
    decode_command,
    decode_packet,
    decode_reply,
    encode_command,
    encode_packet,
    encode_reply,
)


def packet(cid: int, *floats: float) -> bytes:
    vals = list(floats) + [0.0] * (15 - len(floats))
    return struct.pack("<I", cid) + struct.pack("<15f", *vals)


def test_constants() -> None:
    assert PACKET_SIZE == 64 and N_FLOATS == 15
    assert [int(c) for c in CommandId] == [37, 38, 39, 40]


def test_encode_packet_layout() -> None:
    data = encode_packet(0x01020304, [1.0, -2.5])
    assert len(data) == 64
    assert data[:4] == b"\x04\x03\x02\x01"
    assert data[4:8] == b"\x00\x00\x80\x3f"  # 1.0f
    assert data[8:12] == b"\x00\x00\x20\xc0"  # -2.5f
    assert data[12:] == bytes(52)


def test_encode_packet_rejects_too_many_values_and_bad_id() -> None:
    with pytest.raises(ValueError, match="15 floats"):
        encode_packet(37, [0.0] * 16)
    with pytest.raises(ValueError, match="uint32"):
        encode_packet(-1)
    with pytest.raises(ValueError, match="float32"):
        encode_packet(37, [1e300])


def test_decode_packet() -> None:
    raw = decode_packet(packet(38, 1.5, 2.0))
    assert raw == RawPacket(38, (1.5, 2.0) + (0.0,) * 13)


@pytest.mark.parametrize(("n", "word"), [(0, "short"), (63, "short"), (65, "long")])
def test_decode_packet_wrong_length(n: int, word: str) -> None:
    with pytest.raises(DecodeError, match=f"{word} packet: {n} bytes"):
        decode_packet(bytes(n))


def test_encode_set_pid_bytes() -> None:
    cmd = SetPid((JointSetpoint(100.0, 5.0, 0.25), JointSetpoint(-200.0), JointSetpoint(4095.0)))
    assert encode_command(cmd) == packet(37, 100.0, 5.0, 0.25, -200.0, 0, 0, 4095.0, 0, 0)


def test_encode_status_gain_claw_bytes() -> None:
    assert encode_command(Status()) == packet(38)
    assert encode_command(SetGain(2, 0.005, 0.0001, 0.5)) == packet(39, 2.0, 0.005, 0.0001, 0.5)
    assert encode_command(SetClaw(0.75)) == packet(40, 0.75)
    assert encode_command(SetClaw(1.0))[:8] == b"\x28\x00\x00\x00\x00\x00\x80\x3f"


@pytest.mark.parametrize(
    ("cmd", "match"),
    [
        (SetGain(3, 1.0, 0.0, 0.0), "axis"),
        (SetGain(-1, 1.0, 0.0, 0.0), "axis"),
        (SetGain(0, math.nan, 0.0, 0.0), "finite"),
        (SetClaw(1.5), "0..1"),
        (SetClaw(-0.01), "0..1"),
        (SetClaw(math.nan), "finite"),
        (
            SetPid((JointSetpoint(0.0), JointSetpoint(math.inf), JointSetpoint(0.0))),
            r"setpoints\[1\]",
        ),
    ],
)
def test_encode_validation(cmd: SetPid | SetGain | SetClaw, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        encode_command(cmd)


def test_decode_set_pid_reply_interleaved() -> None:
    data = packet(37, 10.0, 1.0, 0.5, 20.0, 2.0, 0.25, 30.0, 3.0, 0.75)
    assert decode_reply(SetPid((JointSetpoint(0),) * 3), data) == SetPidReply(
        (10.0, 20.0, 30.0), (1.0, 2.0, 3.0), (0.5, 0.25, 0.75)
    )


def test_decode_status_reply_blocked() -> None:
    data = packet(38, 10.0, 20.0, 30.0, 1.0, 2.0, 3.0, 0.5, 0.25, 0.75, 99.0)
    assert decode_reply(Status(), data) == StatusReply(
        (10.0, 20.0, 30.0), (1.0, 2.0, 3.0), (0.5, 0.25, 0.75)
    )
    assert decode_reply(38, data) == decode_reply(CommandId.STATUS, data)


def test_decode_ack_ignores_echoed_values() -> None:
    assert decode_reply(SetGain(1, 1, 2, 3), packet(39, 1.0, 1.0, 2.0, 3.0)) == Ack(39)
    assert decode_reply(40, packet(40, math.nan)) == Ack(40)


def test_reply_id_mismatch() -> None:
    with pytest.raises(DecodeError, match="reply id 38 does not match request 37"):
        decode_reply(37, packet(38))


def test_reply_short_packet() -> None:
    with pytest.raises(DecodeError, match="short packet: 10 bytes"):
        decode_reply(Status(), packet(38)[:10])


def test_reply_nan_is_named() -> None:
    data = packet(38, 1.0, 2.0, 3.0, 0.0, math.nan, 0.0)
    with pytest.raises(DecodeError, match=r"velocity_ticks_s\[1\] is nan \(float 4\)"):
        decode_reply(38, data)
    data = packet(37, 0, 0, 0, 0, 0, 0, 0, 0, math.inf)
    with pytest.raises(DecodeError, match=r"strain_adc\[2\] is inf \(float 8\)"):
        decode_reply(37, data)


def test_decode_command_round_trips() -> None:
    cmds = [
        SetPid((JointSetpoint(1.5, 2.0, 0.5), JointSetpoint(-3.0), JointSetpoint(4096.0))),
        Status(),
        SetGain(1, 0.25, 0.125, 0.5),
        SetClaw(0.5),
    ]
    for cmd in cmds:
        assert decode_command(encode_command(cmd)) == cmd


def test_decode_command_unknown_and_bad_fields() -> None:
    with pytest.raises(UnknownCommand, match="unknown command id 65") as info:
        decode_command(packet(65, 1.0))
    assert info.value.command_id == 65
    assert isinstance(info.value, DecodeError)
    with pytest.raises(DecodeError, match="axis 1.5"):
        decode_command(packet(39, 1.5, 1.0))
    with pytest.raises(DecodeError, match="0..1"):
        decode_command(packet(40, 2.0))


def test_encode_reply_matches_firmware_buffers() -> None:
    # PidServer zeroes the whole buffer before writing its nine readings.
    pid = SetPidReply((10.0, 20.0, 30.0), (1.0, 2.0, 3.0), (0.5, 0.25, 0.75))
    request = packet(37, 5.0, 5.0, 5.0, 5.0, 5.0, 5.0, 5.0, 5.0, 5.0, 7.0, 7.0)
    expected = packet(37, 10.0, 1.0, 0.5, 20.0, 2.0, 0.25, 30.0, 3.0, 0.75)
    assert encode_reply(pid, request) == expected
    assert encode_reply(pid, request, echo=True) == expected  # SET_PID zeroes in every build
    # By default every server zeroes as PidServer: STATUS writes floats 0-8 over zeros ...
    status = StatusReply((1.0, 2.0, 3.0), (4.0, 5.0, 6.0), (0.5, 0.5, 0.5))
    readings = packet(38, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 0.5, 0.5, 0.5)
    assert encode_reply(status, packet(38, *[9.0] * 15)) == readings
    assert encode_reply(status) == readings
    # ... and SET_GAIN / SET_CLAW answer the id with fifteen zero floats.
    gain = encode_command(SetGain(2, 0.5, 0.0, 0.25))
    assert encode_reply(Ack(39), gain) == packet(39)
    assert encode_reply(Ack(40), encode_command(SetClaw(0.75))) == packet(40)
    # An echoing build leaves what its server does not write.
    assert encode_reply(status, packet(38, *[9.0] * 15), echo=True) == packet(
        38, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 0.5, 0.5, 0.5, 9.0, 9.0, 9.0, 9.0, 9.0, 9.0
    )
    assert encode_reply(Ack(39), gain, echo=True) == gain


def test_reply_round_trip() -> None:
    reply = StatusReply((100.0, -50.0, 2048.0), (12.5, 0.0, -3.0), (0.5, 0.375, 0.625))
    assert decode_reply(Status(), encode_reply(reply)) == reply
    pid = SetPidReply((1.0, 2.0, 3.0), (4.0, 5.0, 6.0), (0.125, 0.25, 0.5))
    assert decode_reply(37, encode_reply(pid)) == pid


# --- framing and matching without an echo ------------------------------------------------


def test_frame_parser_cuts_a_stream_and_resyncs_on_a_known_id() -> None:
    a, b = packet(38, 1.0), packet(37, 2.0)
    fp = FrameParser()
    assert fp.feed(a[:10]) == []
    assert fp.feed(a[10:] + b[:3]) == [a]
    assert fp.pending == 3
    assert fp.feed(b[3:]) == [b]
    # Garbage before a packet is dropped byte by byte until an id lines up.
    fp = FrameParser()
    assert fp.feed(b"\xff\x01\x02" + a + b) == [a, b]
    assert fp.skipped == 3
    assert fp.feed_report(a) == a and fp.feed_report(a[:63]) is None


def test_matcher_takes_zeroed_and_echoed_acks_and_marks_anything_else() -> None:
    m = ReplyMatcher()
    req = m.request(SetClaw(0.5))
    assert req == packet(40, 0.5)
    assert m.match(packet(40)) == Ack(40)  # PidServer-style build: all zeros
    m.request(SetClaw(0.5))
    assert m.match(packet(40, 0.5)) == Ack(40)  # echoing build
    # SET_GAIN and SET_CLAW "do not provide any return values" (design document): other
    # bytes say nothing of whether the firmware acted; taken, marked (issue 24 item 5)
    m.request(SetGain(1, 0.5, 0.0, 0.0))
    assert m.match(packet(39, 1.0, 0.5, 0.0, 0.25)) == Ack(39, other=True)
    assert m.outstanding is None


def test_matcher_uses_id_and_order_not_a_tag() -> None:
    m = ReplyMatcher()
    m.request(Status())
    # A late SET_CLAW answer while STATUS is outstanding is stale, not an error.
    assert m.match(packet(40)) is None and m.stale == 1
    reply = m.match(packet(38, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 0.5, 0.5, 0.5))
    assert reply == StatusReply((1.0, 2.0, 3.0), (4.0, 5.0, 6.0), (0.5, 0.5, 0.5))
    # Nothing outstanding: every frame is stale.
    assert m.match(packet(38)) is None and m.stale == 2


def test_matcher_refuses_a_reading_with_spare_floats_changed() -> None:
    m = ReplyMatcher()
    m.request(Status())
    with pytest.raises(DecodeError, match="floats 9-14"):
        m.match(packet(38, *([1.0] * 9), 0.0, 0.0, 0.0, 0.0, 0.0, 3.0))
    m.request(SetPid((JointSetpoint(1.0), JointSetpoint(2.0), JointSetpoint(3.0))))
    with pytest.raises(DecodeError, match="nan"):
        m.match(packet(37, math.nan, *([1.0] * 8)))


def test_matcher_remembers_a_checked_reading_and_refuses_the_same_with_a_byte_changed() -> None:
    m = ReplyMatcher()
    good = packet(38, *([1.0] * 9))
    assert m.request(Status()) == encode_command(Status())
    first = m.match(good)
    m.request(Status())
    again = m.match(good)
    assert isinstance(first, StatusReply) and again is first  # the same bytes: decoded once
    m.request(Status())
    with pytest.raises(DecodeError, match="floats 9-14"):
        m.match(packet(38, *([1.0] * 9), 0.0, 0.0, 0.0, 0.0, 0.0, 3.0))
    m.request(Status())
    with pytest.raises(DecodeError, match="nan"):
        m.match(packet(38, math.nan, *([1.0] * 8)))
    m.request(Status())
    assert m.match(good) is first


def test_matcher_reports_the_simplepacketcoms_error_packet() -> None:
    m = ReplyMatcher()
    m.request(SetGain(0, 0.1, 0.0, 0.0))
    err = struct.pack("<II", ERROR_ID, 39) + bytes(56)
    with pytest.raises(UnknownToFirmware, match="39"):
        m.match(err)
    m.request(Status())
    assert m.match(err) is None  # names another id: stale
