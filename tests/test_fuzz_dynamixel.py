"""Fuzz the Dynamixel parser: noise never raises, valid packets survive noise and mutation."""

from __future__ import annotations

import os

from hypothesis import given, settings
from hypothesis import strategies as st

from protocol import dynamixel as dxl
from protocol.dynamixel import Packet, ParseError

CASES = int(os.environ.get("ARMSERVER_FUZZ_CASES", "150"))
# bytes rich in the header's values, so random input often looks like a frame
NOISY = st.lists(st.sampled_from([0xFF, 0xFD, 0x00, 0x55, 0x01, 0x03, 0x07]) | st.integers(0, 255),
                 max_size=120).map(bytes)
IDS = st.integers(0, 252) | st.just(dxl.BROADCAST_ID)
PARAMS = st.lists(st.sampled_from([0xFF, 0xFD, 0x00]) | st.integers(0, 255), max_size=40).map(bytes)
INSTRUCTIONS = st.sampled_from([i for i in dxl.Instruction if i != dxl.Instruction.STATUS])


def _drain(parser: dxl.Parser, data: bytes, chunk: int) -> list[Packet | ParseError]:
    events: list[Packet | ParseError] = []
    for k in range(0, len(data), chunk):
        parser.feed(data[k:k + chunk])
        events.extend(parser)
    return events


@settings(max_examples=CASES, deadline=None)
@given(NOISY, st.integers(1, 16))
def test_noise_never_raises(noise: bytes, chunk: int) -> None:
    events = _drain(dxl.Parser(limit=256), noise, chunk)
    assert all(isinstance(e, Packet | ParseError) for e in events)


@settings(max_examples=CASES, deadline=None)
@given(IDS, INSTRUCTIONS, PARAMS, st.integers(1, 9))
def test_round_trip(id_: int, inst: int, params: bytes, chunk: int) -> None:
    events = _drain(dxl.Parser(), dxl.encode_instruction(id_, inst, params), chunk)
    assert events == [Packet(id_, inst, params)]


@settings(max_examples=CASES, deadline=None)
@given(st.integers(0, 252), st.integers(0, 255), PARAMS)
def test_status_round_trip(id_: int, error: int, params: bytes) -> None:
    events = _drain(dxl.Parser(), dxl.encode_status(id_, error, params), 5)
    assert events == [Packet(id_, 0x55, params, error)]


@settings(max_examples=CASES, deadline=None)
@given(NOISY, IDS, INSTRUCTIONS, PARAMS, st.integers(1, 9))
def test_packet_after_noise_is_found(noise: bytes, id_: int, inst: int, params: bytes,
                                     chunk: int) -> None:
    """Noise, then silence long enough for any frame the noise began to complete (as a
    driver's timeout would give), then a packet: the packet is always found."""
    parser = dxl.Parser(limit=512)
    _drain(parser, noise, chunk)
    parser.clear()  # a reply timeout: the driver drops what it holds
    wire = dxl.encode_instruction(id_, inst, params)
    assert _drain(parser, wire, chunk) == [Packet(id_, inst, params)]


@settings(max_examples=CASES, deadline=None)
@given(NOISY, IDS, INSTRUCTIONS, PARAMS)
def test_packet_after_headerless_noise_without_clear(noise: bytes, id_: int, inst: int,
                                                     params: bytes) -> None:
    """Without a clear: noise holding no header is skipped (reported as garbage) and the
    packet is found, even when the noise ends in a header's first bytes."""
    while dxl.HEADER[:3] in noise:
        noise = noise.replace(dxl.HEADER[:3], b"")
    wire = dxl.encode_instruction(id_, inst, params)
    events = _drain(dxl.Parser(), noise + wire, 7)
    assert [e for e in events if isinstance(e, Packet)] == [Packet(id_, inst, params)]
    assert sum(e.dropped for e in events if isinstance(e, ParseError)) == len(noise)


@settings(max_examples=CASES, deadline=None)
@given(st.lists(st.tuples(IDS, INSTRUCTIONS, PARAMS), min_size=1, max_size=4),
       st.data())
def test_mutated_streams_never_raise_and_keep_later_packets(packets: list[tuple[int, int, bytes]],
                                                            data: st.DataObject) -> None:
    wires = [dxl.encode_instruction(*p) for p in packets]
    stream = bytearray(b"".join(wires))
    for _ in range(data.draw(st.integers(1, 4))):
        op = data.draw(st.sampled_from(["flip", "drop", "insert"]))
        k = data.draw(st.integers(0, len(stream) - 1))
        if op == "flip":
            stream[k] ^= data.draw(st.integers(1, 255))
        elif op == "drop":
            del stream[k]
        else:
            stream.insert(k, data.draw(st.integers(0, 255)))
    good = dxl.encode_instruction(7, dxl.Instruction.PING)
    parser = dxl.Parser(limit=1024)
    events = _drain(parser, bytes(stream), 3)
    parser.clear()
    events += _drain(parser, good, 3)
    assert events[-1] == Packet(7, dxl.Instruction.PING, b"")
    assert parser.buffered == 0
