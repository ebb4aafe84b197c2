"""protocol/dynamixel.py against the e-manual's vectors and the public DynamixelSDK's bytes.

The SDK's own packet handler builds the reference bytes; its port is replaced by a recording
double (a PortHandler subclass that keeps what `writePort` is given and serves canned
replies), never our code.
"""

from __future__ import annotations

import random

import pytest
from dynamixel_sdk import (
    GroupBulkRead,
    GroupBulkWrite,
    GroupSyncRead,
    GroupSyncWrite,
    PortHandler,
    Protocol2PacketHandler,
)
from hypothesis import given, settings
from hypothesis import strategies as st

from protocol import dynamixel as dxl
from protocol.dynamixel import Packet, ParseError

H = bytes.fromhex


class RecordingPort(PortHandler):
    """The SDK's port with the serial device swapped for a list and a canned reply buffer."""

    def __init__(self) -> None:
        super().__init__("recording")
        self.is_open = True
        self.baudrate = 1_000_000
        self.tx_time_per_byte = 0.01
        self.sent: list[bytes] = []
        self.rx = bytearray()

    def clearPort(self) -> None:  # noqa: N802 - the SDK's name
        pass

    def writePort(self, packet: list[int]) -> int:  # noqa: N802
        self.sent.append(bytes(packet))
        return len(packet)

    def readPort(self, length: int) -> bytes:  # noqa: N802
        out = bytes(self.rx[:length])
        del self.rx[:length]
        return out


SDK = tuple[Protocol2PacketHandler, RecordingPort]


@pytest.fixture()
def sdk() -> SDK:
    return Protocol2PacketHandler(), RecordingPort()


# e-manual / reference vectors ---------------------------------------------------------------

def test_reference_vectors() -> None:
    assert dxl.crc16(b"123456789") == 0xFEE8
    assert dxl.ping(1) == H("FFFFFD00 01 0300 01 194E")
    assert dxl.read(1, 132, 4) == H("FFFFFD00 01 0700 02 8400 0400 1D15")
    assert dxl.sync_read(132, 4, [1, 2, 3, 4]) == H("FFFFFD00 FE 0B00 82 8400 0400 01020304 303E")
    assert dxl.encode_status(1, 0) == H("FFFFFD00 01 0400 55 00 A10C")
    assert dxl.HEADER == H("FFFFFD00") and dxl.BROADCAST_ID == 0xFE


def test_crc_table_is_the_sdks(sdk: SDK) -> None:
    ph, _ = sdk
    assert [ph.updateCRC(0, [i], 1) for i in range(256)][1:4] == [0x8005, 0x800F, 0x000A]
    assert all(dxl.CRC_TABLE[i] == ph.updateCRC(0, [i], 1) for i in range(256))


@settings(max_examples=60, deadline=None)
@given(st.binary(max_size=300), st.integers(0, 0xFFFF))
def test_crc_matches_sdk(data: bytes, start: int) -> None:
    ph = Protocol2PacketHandler()
    assert dxl.crc16(data, start) == ph.updateCRC(start, list(data), len(data))


def test_instruction_and_error_codes() -> None:
    assert {i.name: i.value for i in dxl.Instruction} == {
        "PING": 1, "READ": 2, "WRITE": 3, "REG_WRITE": 4, "ACTION": 5, "FACTORY_RESET": 6,
        "REBOOT": 8, "CLEAR": 0x10, "STATUS": 0x55, "SYNC_READ": 0x82, "SYNC_WRITE": 0x83,
        "BULK_READ": 0x92, "BULK_WRITE": 0x93}
    assert dxl.describe_error(0) == "ok"
    assert dxl.describe_error(0x87) == "access error (EEPROM write with torque on?); hardware alert"
    assert dxl.describe_error(0x04).startswith("data range error")
    assert dxl.describe_error(0x80) == "hardware alert"


# our builders equal the SDK's bytes ---------------------------------------------------------

def _sdk_bytes(sdk: SDK, call: object, reply: bytes = b"") -> bytes:
    ph, port = sdk
    port.sent.clear()
    port.rx[:] = reply
    port.is_using = False  # a *Tx-only call (sync/bulk read) leaves the SDK port busy
    assert callable(call)
    call(ph, port)
    assert len(port.sent) == 1
    return port.sent[0]


OK1 = dxl.encode_status(1, 0)


@pytest.mark.parametrize(("call", "ours", "reply"), [
    (lambda ph, p: ph.ping(p, 1), dxl.ping(1), dxl.encode_status(1, 0, H("1E002D"))),
    (lambda ph, p: ph.action(p, 1), dxl.action(1), b""),
    (lambda ph, p: ph.action(p, 0xFE), dxl.action(0xFE), b""),
    (lambda ph, p: ph.reboot(p, 2), dxl.reboot(2), dxl.encode_status(2, 0)),
    (lambda ph, p: ph.clearMultiTurn(p, 3), dxl.clear(3), dxl.encode_status(3, 0)),
    (lambda ph, p: ph.factoryReset(p, 1, 0x02), dxl.factory_reset(1, 0x02), OK1),
    (lambda ph, p: ph.factoryReset(p, 1, 0xFF), dxl.factory_reset(1), OK1),
    (lambda ph, p: ph.read1ByteTxRx(p, 1, 64), dxl.read(1, 64, 1),
     dxl.encode_status(1, 0, b"\x01")),
    (lambda ph, p: ph.read2ByteTxRx(p, 1, 126), dxl.read(1, 126, 2),
     dxl.encode_status(1, 0, b"\1\2")),
    (lambda ph, p: ph.read4ByteTxRx(p, 1, 132), dxl.read(1, 132, 4),
     dxl.encode_status(1, 0, b"1234")),
    (lambda ph, p: ph.write1ByteTxRx(p, 1, 64, 1), dxl.write(1, 64, b"\x01"), OK1),
    (lambda ph, p: ph.write2ByteTxRx(p, 1, 100, 300), dxl.write(1, 100, dxl.to_bytes(300, 2)), OK1),
    (lambda ph, p: ph.write4ByteTxRx(p, 1, 116, 2**32 - 4000),
     dxl.write(1, 116, dxl.to_bytes(-4000, 4)), OK1),
    (lambda ph, p: ph.write4ByteTxOnly(p, 0xFE, 116, 1024),
     dxl.write(0xFE, 116, dxl.to_bytes(1024, 4)), b""),
    (lambda ph, p: ph.regWriteTxRx(p, 1, 116, 4, [0, 8, 0, 0]),
     dxl.reg_write(1, 116, H("00080000")), OK1),
    (lambda ph, p: ph.regWriteTxOnly(p, 1, 64, 1, [1]), dxl.reg_write(1, 64, b"\x01"), b""),
])
def test_builders_equal_sdk(sdk: SDK, call: object,
                            ours: bytes, reply: bytes) -> None:
    assert _sdk_bytes(sdk, call, reply) == ours


def test_group_builders_equal_sdk(sdk: SDK) -> None:
    ph, port = sdk

    def sync_read(ph: Protocol2PacketHandler, p: RecordingPort) -> None:
        g = GroupSyncRead(p, ph, 132, 4)
        for i in (3, 1, 4, 2):
            g.addParam(i)
        g.txPacket()

    assert _sdk_bytes(sdk, sync_read) == dxl.sync_read(132, 4, [3, 1, 4, 2])

    def sync_write(ph: Protocol2PacketHandler, p: RecordingPort) -> None:
        g = GroupSyncWrite(p, ph, 116, 4)
        for i, v in ((1, 1000), (2, 2000), (7, 3000)):
            g.addParam(i, list(dxl.to_bytes(v, 4)))
        g.txPacket()

    assert _sdk_bytes(sdk, sync_write) == dxl.sync_write(
        116, 4, {i: dxl.to_bytes(v, 4) for i, v in ((1, 1000), (2, 2000), (7, 3000))})

    def bulk_read(ph: Protocol2PacketHandler, p: RecordingPort) -> None:
        g = GroupBulkRead(p, ph)
        g.addParam(1, 132, 4)
        g.addParam(2, 126, 2)
        g.txPacket()

    assert _sdk_bytes(sdk, bulk_read) == dxl.bulk_read([(1, 132, 4), (2, 126, 2)])

    def bulk_write(ph: Protocol2PacketHandler, p: RecordingPort) -> None:
        g = GroupBulkWrite(p, ph)
        g.addParam(1, 116, 4, list(dxl.to_bytes(2048, 4)))
        g.addParam(3, 64, 1, [1])
        g.txPacket()

    assert _sdk_bytes(sdk, bulk_write) == dxl.bulk_write(
        [(1, 116, dxl.to_bytes(2048, 4)), (3, 64, b"\x01")])


def test_sdk_sends_unstuffed_and_parser_still_decodes(
        sdk: SDK) -> None:
    ph, _ = sdk
    goal = dxl.to_bytes(-131073, 4)
    assert goal == H("FFFFFDFF")
    sent = _sdk_bytes(sdk, lambda ph, p: ph.write4ByteTxOnly(p, 1, 116, -131073 & 0xFFFFFFFF))
    ours = dxl.write(1, 116, goal)
    assert sent == H("FFFFFD00 01 0900 03 7400 FFFFFDFF") + sent[-2:]  # LEN 9: not stuffed
    assert ours[:-2] == H("FFFFFD00 01 0A00 03 7400 FFFFFDFD FF")  # LEN 10: stuffed
    # the SDK's own addStuffing (whose result it discards) agrees with ours
    assert bytes(ph.addStuffing(list(sent)))[:-2] == ours[:-2]
    expected = Packet(1, dxl.Instruction.WRITE, H("7400") + goal)
    for wire in (sent, ours):
        parser = dxl.Parser()
        parser.feed(wire)
        assert list(parser) == [expected]


# stuffing and value helpers -----------------------------------------------------------------

@pytest.mark.parametrize(("raw", "stuffed"), [
    (H("03FFFFFD"), H("03FFFFFDFD")),
    (H("FFFFFDFD"), H("FFFFFDFDFD")),
    (H("FFFFFDFFFFFD"), H("FFFFFDFDFFFFFDFD")),
    (H("FFFD"), H("FFFD")),
    (b"", b""),
])
def test_stuffing_vectors(raw: bytes, stuffed: bytes) -> None:
    assert dxl.stuff(raw) == stuffed
    assert dxl.unstuff(stuffed) == raw


@settings(max_examples=80, deadline=None)
@given(st.lists(st.sampled_from([0xFF, 0xFD, 0x00, 0x55]), max_size=40).map(bytes))
def test_stuffing_round_trip_and_matches_sdk(body: bytes) -> None:
    assert dxl.unstuff(dxl.stuff(body)) == body
    length = (len(body) + 3).to_bytes(2, "little")
    packet = list(H("FFFFFD00 01") + length + b"\x03" + body + b"\0\0")
    sdk_stuffed = bytes(Protocol2PacketHandler().addStuffing(packet))
    assert sdk_stuffed[8:-2] == dxl.stuff(b"\x03" + body)[1:]


def test_value_helpers() -> None:
    assert dxl.to_bytes(-1, 4) == H("FFFFFFFF")
    assert dxl.to_bytes(4095, 4) == H("FF0F0000")
    assert dxl.to_bytes(-1000, 2) == H("18FC")
    assert dxl.from_bytes(H("18FC"), signed=True) == -1000
    assert dxl.from_bytes(H("18FC"), signed=False) == 0xFC18
    with pytest.raises(dxl.ProtocolError):
        dxl.to_bytes(70000, 2)


def test_local_misuse_raises() -> None:
    with pytest.raises(dxl.ProtocolError):
        dxl.ping(253)
    with pytest.raises(dxl.ProtocolError):
        dxl.encode_status(0xFE, 0)
    with pytest.raises(dxl.ProtocolError):
        dxl.sync_write(116, 4, {1: b"\x00\x01"})
    with pytest.raises(dxl.ProtocolError):
        dxl.write(1, 0, bytes(70_000))


def test_decoders_round_trip_and_reject_bad_lengths() -> None:
    def params(wire: bytes) -> bytes:
        p = dxl.Parser()
        p.feed(wire)
        ev = p.next_event()
        assert isinstance(ev, Packet)
        return ev.params

    assert dxl.decode_read(params(dxl.read(1, 132, 4))) == (132, 4)
    assert dxl.decode_write(params(dxl.write(1, 116, b"\1\2\3\4"))) == (116, b"\1\2\3\4")
    assert dxl.decode_sync_read(params(dxl.sync_read(132, 4, [4, 2]))) == (132, 4, (4, 2))
    assert dxl.decode_sync_write(params(dxl.sync_write(116, 2, {1: b"ab", 5: b"cd"}))) == (
        116, 2, {1: b"ab", 5: b"cd"})
    assert dxl.decode_bulk_read(params(dxl.bulk_read([(1, 132, 4), (9, 64, 1)]))) == [
        (1, 132, 4), (9, 64, 1)]
    assert dxl.decode_bulk_write(params(dxl.bulk_write([(1, 116, b"wxyz"), (2, 64, b"\1")]))) == [
        (1, 116, b"wxyz"), (2, 64, b"\1")]
    bad_params = [(dxl.decode_read, b"\1\2\3"), (dxl.decode_write, b"\1\2"),
                  (dxl.decode_sync_read, b"\1\2\3\4"), (dxl.decode_sync_write, b"\1\0\2\0\1a"),
                  (dxl.decode_bulk_read, b"\1\2\3\4"), (dxl.decode_bulk_write, b"\1\2\0\3\0ab")]
    for decode, bad in bad_params:
        with pytest.raises(dxl.ProtocolError):
            decode(bad)  # type: ignore[operator]


# the parser ---------------------------------------------------------------------------------

STREAM = [dxl.ping(1), dxl.encode_status(1, 0, H("1E002D")),
          dxl.write(1, 116, dxl.to_bytes(-131073, 4)),
          dxl.encode_status(3, 0x87), dxl.sync_write(116, 4, {1: H("FFFFFDFF"), 2: H("00FFFFFD")})]
PACKETS = [Packet(1, 1, b""), Packet(1, 0x55, H("1E002D"), 0), Packet(1, 3, H("7400FFFFFDFF")),
           Packet(3, 0x55, b"", 0x87),
           Packet(0xFE, 0x83, H("74000400") + H("01FFFFFDFF") + H("0200FFFFFD"))]


def _packets(events: list[Packet | ParseError]) -> list[Packet]:
    return [e for e in events if isinstance(e, Packet)]


def test_parser_whole_and_byte_by_byte() -> None:
    p = dxl.Parser()
    p.feed(b"".join(STREAM))
    assert list(p) == PACKETS
    p = dxl.Parser()
    events: list[Packet | ParseError] = []
    for b in b"".join(STREAM):
        p.feed(bytes((b,)))
        events.extend(p)
    assert events == PACKETS
    assert p.buffered == 0


def test_parser_random_splits() -> None:
    rng = random.Random(7)
    wire = b"".join(STREAM)
    for _ in range(50):
        cuts = sorted(rng.sample(range(1, len(wire)), 6))
        p = dxl.Parser()
        events: list[Packet | ParseError] = []
        for a, b in zip([0, *cuts], [*cuts, len(wire)], strict=True):
            p.feed(wire[a:b])
            events.extend(p)
        assert events == PACKETS


def test_parser_garbage_before_is_reported_and_skipped() -> None:
    p = dxl.Parser()
    p.feed(b"\x00\xff\x12\xff\xff" + STREAM[0])
    assert list(p) == [ParseError("garbage", "bytes before a header", 5), PACKETS[0]]


def test_parser_bad_crc_then_good_packet() -> None:
    bad = bytearray(STREAM[2])
    bad[-1] ^= 0x40
    p = dxl.Parser()
    p.feed(bytes(bad) + STREAM[1])
    events = list(p)
    assert events[0] == ParseError("crc", "CRC mismatch in a 17-byte frame", 1, 1)
    assert _packets(events) == [PACKETS[1]]


def test_parser_remembers_checked_frames_and_still_refuses_a_changed_byte() -> None:
    p = dxl.Parser()
    p.feed(STREAM[1] + STREAM[1])
    first, again = list(p)
    assert first == PACKETS[1] and again is first  # the same bytes: decoded once
    changed = bytearray(STREAM[1])
    changed[9] ^= 0x01  # a parameter byte, the CRC left as it was
    p.feed(bytes(changed) + STREAM[1])
    events = list(p)
    assert isinstance(events[0], ParseError) and events[0].kind == "crc"
    assert _packets(events) == [PACKETS[1]]
    for k in range(dxl.FRAME_CACHE + 10):  # distinct frames: the memory stays bounded
        p.feed(dxl.encode_status(1, 0, k.to_bytes(2, "little")))
        assert list(p) == [dxl.Packet(1, dxl.Instruction.STATUS, k.to_bytes(2, "little"), 0)]
    assert len(p._known) <= dxl.FRAME_CACHE


def test_parser_truncated_frame_does_not_hide_the_next() -> None:
    """A frame cut short: its LEN swallows the next packet's start; the CRC fails, the search
    resumes inside it and the next packet is still found."""
    p = dxl.Parser()
    p.feed(STREAM[2][:9] + STREAM[1] + STREAM[0])
    events = list(p)
    assert events[0].kind == "crc"  # type: ignore[union-attr]
    assert _packets(events) == [PACKETS[1], PACKETS[0]]


@pytest.mark.parametrize("length", [0, 2, 0xFFFF])
def test_parser_absurd_len_resyncs(length: int) -> None:
    p = dxl.Parser(limit=1024)
    p.feed(dxl.HEADER + b"\x01" + length.to_bytes(2, "little") + STREAM[0])
    events = list(p)
    assert events[0] == ParseError("length", f"LEN {length} outside 3..1017", 1)
    assert _packets(events) == [PACKETS[0]]


def test_parser_buffer_is_bounded() -> None:
    p = dxl.Parser(limit=256)
    p.feed(dxl.HEADER + b"\x01" + (240).to_bytes(2, "little"))  # waits for 240 bytes
    p.feed(bytes(300))
    assert p.buffered == 256
    assert p.next_event() == ParseError("overflow", "receive buffer over 256 bytes", 51)
    assert p.clear() == 256
