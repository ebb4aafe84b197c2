"""Dynamixel Protocol 2.0 codec, sans-IO: CRC-16, byte stuffing, packets, an incremental parser.

Wire format (ROBOTIS e-manual, https://emanual.robotis.com/docs/en/dxl/protocol2/):
``FF FF FD 00 | ID | LEN_L LEN_H | INST | params | CRC_L CRC_H``. LEN counts instruction,
params and CRC after stuffing; a STATUS packet (INST 0x55) carries an error byte before its
params. Multi-byte values are little-endian; negatives are two's complement.

The same functions serve the driver (builders, `Parser` on replies) and the simulator
(`Parser` on instructions, decoders of instruction params, `encode_status`). Nothing here
reads a port or awaits (ARCHITECTURE rule 1).
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from enum import IntEnum

HEADER = b"\xff\xff\xfd\x00"
BROADCAST_ID = 0xFE
MAX_ID = 0xFC
#: bytes before the instruction: header, id, LEN_L, LEN_H
PREFIX_LEN = 7
#: the parser's receive-buffer limit, bytes; also the largest frame it will wait for
BUFFER_LIMIT = 64 * 1024
CLEAR_MULTI_TURN = b"\x01\x44\x58\x4c\x22"


class Instruction(IntEnum):
    PING = 0x01
    READ = 0x02
    WRITE = 0x03
    REG_WRITE = 0x04
    ACTION = 0x05
    FACTORY_RESET = 0x06
    REBOOT = 0x08
    CLEAR = 0x10
    STATUS = 0x55
    SYNC_READ = 0x82
    SYNC_WRITE = 0x83
    BULK_READ = 0x92
    BULK_WRITE = 0x93


class ErrorCode(IntEnum):
    """Bits 0-6 of a status packet's error byte (a number, not a bit mask)."""

    RESULT_FAIL = 1
    INSTRUCTION = 2
    CRC = 3
    DATA_RANGE = 4
    DATA_LENGTH = 5
    DATA_LIMIT = 6
    ACCESS = 7


#: bit 7 of the error byte: the device has a hardware error (read Hardware Error Status, 70)
ALERT_BIT = 0x80

_ERROR_TEXT = {
    ErrorCode.RESULT_FAIL: "result fail (instruction could not be processed)",
    ErrorCode.INSTRUCTION: "instruction error (undefined, or ACTION without REG_WRITE)",
    ErrorCode.CRC: "CRC error",
    ErrorCode.DATA_RANGE: "data range error (value outside the item's range)",
    ErrorCode.DATA_LENGTH: "data length error (shorter than the item)",
    ErrorCode.DATA_LIMIT: "data limit error (value beyond a limit item)",
    ErrorCode.ACCESS: "access error (EEPROM write with torque on?)",
}


class ProtocolError(ValueError):
    """Local misuse: a bad id, params too long, or instruction params of the wrong length."""


@dataclass(frozen=True)
class Packet:
    """One decoded packet. `params` are unstuffed; for STATUS, `error` is the byte after
    0x55 and `params` exclude it; for instructions `error` is None."""

    id: int
    instruction: int
    params: bytes
    error: int | None = None


@dataclass(frozen=True)
class ParseError:
    """A framing problem seen by `Parser`: an event, never raised.

    kind: "garbage" (bytes before a header), "length" (absurd LEN), "crc" (bad checksum),
    "overflow" (fed past the buffer limit without draining). `dropped` counts bytes discarded;
    `id` is the frame's id byte where one was read (kind "crc"), else None.
    """

    kind: str
    detail: str
    dropped: int
    id: int | None = None


def describe_error(error: int) -> str:
    """Human text for a status error byte, e.g. 'access error (...); hardware alert'."""
    parts: list[str] = []
    code = error & 0x7F
    if code:
        try:
            parts.append(_ERROR_TEXT[ErrorCode(code)])
        except ValueError:
            parts.append(f"unknown error {code}")
    if error & ALERT_BIT:
        parts.append("hardware alert")
    return "; ".join(parts) if parts else "ok"


def _make_table() -> tuple[int, ...]:
    table: list[int] = []
    for i in range(256):
        crc = i << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x8005) if crc & 0x8000 else (crc << 1)
        table.append(crc & 0xFFFF)
    return tuple(table)


#: the e-manual's CRC table (polynomial 0x8005, MSB first)
CRC_TABLE = _make_table()


def crc16(data: bytes, crc: int = 0) -> int:
    """CRC-16 of the e-manual (poly 0x8005, init 0, not reflected, no final xor)."""
    table = CRC_TABLE
    for b in data:
        crc = ((crc & 0xFF) << 8) ^ table[(crc >> 8) ^ b]
    return crc


def stuff(body: bytes) -> bytes:
    """Stuff instruction + params: after each FF FF FD insert an extra FD."""
    out = bytearray()
    for i, b in enumerate(body):
        out.append(b)
        if b == 0xFD and i >= 2 and body[i - 2] == 0xFF and body[i - 1] == 0xFF:
            out.append(0xFD)
    return bytes(out)


def unstuff(body: bytes) -> bytes:
    """Undo `stuff`: FF FF FD FD becomes FF FF FD. Unstuffed input passes through unchanged
    unless it contains FF FF FD FD."""
    out = bytearray()
    i, n = 0, len(body)
    while i < n:
        out.append(body[i])
        if (body[i] == 0xFD and i >= 2 and body[i - 2] == 0xFF and body[i - 1] == 0xFF
                and i + 1 < n and body[i + 1] == 0xFD):
            i += 1
        i += 1
    return bytes(out)


def _frame(id_: int, body: bytes) -> bytes:
    stuffed = stuff(body)
    length = len(stuffed) + 2
    if PREFIX_LEN + length > BUFFER_LIMIT:
        raise ProtocolError(f"packet of {PREFIX_LEN + length} bytes exceeds {BUFFER_LIMIT}")
    head = HEADER + bytes((id_,)) + length.to_bytes(2, "little") + stuffed
    return head + crc16(head).to_bytes(2, "little")


def _check_id(id_: int, broadcast: bool = True) -> None:
    if not (0 <= id_ <= MAX_ID or (broadcast and id_ == BROADCAST_ID)):
        raise ProtocolError(f"id {id_} outside 0..252" + (" or 254" if broadcast else ""))


def encode_instruction(id: int, instruction: int, params: bytes = b"") -> bytes:
    """A whole instruction packet: stuffed, LEN and CRC over the stuffed bytes."""
    _check_id(id)
    if not 0 <= instruction <= 0xFF:
        raise ProtocolError(f"instruction {instruction} is not a byte")
    return _frame(id, bytes((instruction,)) + params)


def encode_status(id: int, error: int, params: bytes = b"") -> bytes:
    """A whole status packet (INST 0x55, then the error byte, then params)."""
    _check_id(id, broadcast=False)
    if not 0 <= error <= 0xFF:
        raise ProtocolError(f"error {error} is not a byte")
    return _frame(id, bytes((Instruction.STATUS, error)) + params)


def to_bytes(value: int, size: int) -> bytes:
    """`value` as `size` little-endian bytes; negatives in two's complement."""
    if not -(1 << (8 * size - 1)) <= value < (1 << (8 * size)):
        raise ProtocolError(f"{value} does not fit in {size} bytes")
    return (value & ((1 << (8 * size)) - 1)).to_bytes(size, "little")


def from_bytes(data: bytes, signed: bool) -> int:
    """Little-endian integer; two's complement when `signed`."""
    return int.from_bytes(data, "little", signed=signed)


def _u16(value: int, what: str) -> bytes:
    if not 0 <= value <= 0xFFFF:
        raise ProtocolError(f"{what} {value} outside 0..65535")
    return value.to_bytes(2, "little")


def ping(id: int) -> bytes:
    return encode_instruction(id, Instruction.PING)


def read(id: int, address: int, length: int) -> bytes:
    params = _u16(address, "address") + _u16(length, "length")
    return encode_instruction(id, Instruction.READ, params)


def write(id: int, address: int, data: bytes) -> bytes:
    return encode_instruction(id, Instruction.WRITE, _u16(address, "address") + data)


def status_params(packet: bytes) -> int:
    """The parameter bytes of the status that answers instruction `packet` (each servo's, for
    a SYNC_READ): a PING's 3 (Model Number LSB, MSB, Version of Firmware), a READ's or
    SYNC_READ's the length asked, a WRITE's and the others' none (e-manual, Protocol 2.0:
    "Ping", "Read" and "Sync Read"'s status parameters, "Write"'s status, Length 4). A status
    names no instruction ("Instruction of the Status Packet is designated to 0x55"): its size
    is what tells a late answer to an earlier instruction from this one's."""
    instruction = packet[PREFIX_LEN] if len(packet) >= 10 else None
    if instruction == Instruction.PING:
        return 3
    if instruction in (Instruction.READ, Instruction.SYNC_READ):
        return int.from_bytes(packet[10:12], "little")
    return 0


def reg_write(id: int, address: int, data: bytes) -> bytes:
    return encode_instruction(id, Instruction.REG_WRITE, _u16(address, "address") + data)


def action(id: int) -> bytes:
    return encode_instruction(id, Instruction.ACTION)


def factory_reset(id: int, mode: int = 0xFF) -> bytes:
    """mode 0xFF: reset all; 0x01: all but ID; 0x02: all but ID and baud rate."""
    if mode not in (0xFF, 0x01, 0x02):
        raise ProtocolError(f"factory reset mode {mode:#x} not 0xFF, 0x01 or 0x02")
    return encode_instruction(id, Instruction.FACTORY_RESET, bytes((mode,)))


def reboot(id: int) -> bytes:
    return encode_instruction(id, Instruction.REBOOT)


def clear(id: int) -> bytes:
    """CLEAR multi-turn: present position back into one turn (params 01 44 58 4C 22)."""
    return encode_instruction(id, Instruction.CLEAR, CLEAR_MULTI_TURN)


def sync_read(address: int, length: int, ids: Sequence[int]) -> bytes:
    for i in ids:
        _check_id(i, broadcast=False)
    params = _u16(address, "address") + _u16(length, "length") + bytes(ids)
    return encode_instruction(BROADCAST_ID, Instruction.SYNC_READ, params)


def sync_write(address: int, length: int, items: Mapping[int, bytes]) -> bytes:
    """Each value must be exactly `length` bytes (use `to_bytes`)."""
    params = bytearray(_u16(address, "address") + _u16(length, "length"))
    for i, data in items.items():
        _check_id(i, broadcast=False)
        if len(data) != length:
            raise ProtocolError(f"id {i}: {len(data)} bytes of data, expected {length}")
        params += bytes((i,)) + data
    return encode_instruction(BROADCAST_ID, Instruction.SYNC_WRITE, bytes(params))


def bulk_read(items: Sequence[tuple[int, int, int]]) -> bytes:
    """items: (id, address, length) each; one id at most once."""
    params = bytearray()
    for i, address, length in items:
        _check_id(i, broadcast=False)
        params += bytes((i,)) + _u16(address, "address") + _u16(length, "length")
    return encode_instruction(BROADCAST_ID, Instruction.BULK_READ, bytes(params))


def bulk_write(items: Sequence[tuple[int, int, bytes]]) -> bytes:
    """items: (id, address, data) each."""
    params = bytearray()
    for i, address, data in items:
        _check_id(i, broadcast=False)
        params += bytes((i,)) + _u16(address, "address") + _u16(len(data), "length") + data
    return encode_instruction(BROADCAST_ID, Instruction.BULK_WRITE, bytes(params))


def _need(params: bytes, n: int, what: str, exact: bool = True) -> None:
    if len(params) < n or (exact and len(params) != n):
        raise ProtocolError(f"{what}: {len(params)} param bytes, expected {n}")


def decode_read(params: bytes) -> tuple[int, int]:
    """READ params -> (address, length)."""
    _need(params, 4, "READ")
    return from_bytes(params[:2], False), from_bytes(params[2:], False)


def decode_write(params: bytes) -> tuple[int, bytes]:
    """WRITE / REG_WRITE params -> (address, data); data may not be empty."""
    _need(params, 3, "WRITE", exact=False)
    return from_bytes(params[:2], False), params[2:]


def decode_sync_read(params: bytes) -> tuple[int, int, tuple[int, ...]]:
    """SYNC_READ params -> (address, length, ids in the order listed)."""
    _need(params, 5, "SYNC_READ", exact=False)
    return from_bytes(params[:2], False), from_bytes(params[2:4], False), tuple(params[4:])


def decode_sync_write(params: bytes) -> tuple[int, int, dict[int, bytes]]:
    """SYNC_WRITE params -> (address, length, {id: data})."""
    _need(params, 4, "SYNC_WRITE", exact=False)
    address, length = from_bytes(params[:2], False), from_bytes(params[2:4], False)
    body = params[4:]
    if length == 0 or not body or len(body) % (length + 1):
        raise ProtocolError(f"SYNC_WRITE: {len(body)} bytes is not a whole number of {length + 1}")
    items = {body[k]: body[k + 1:k + 1 + length] for k in range(0, len(body), length + 1)}
    return address, length, items


def decode_bulk_read(params: bytes) -> list[tuple[int, int, int]]:
    """BULK_READ params -> [(id, address, length)] in the order listed."""
    if not params or len(params) % 5:
        raise ProtocolError(f"BULK_READ: {len(params)} bytes is not a whole number of 5")
    return [(params[k], from_bytes(params[k + 1:k + 3], False),
             from_bytes(params[k + 3:k + 5], False)) for k in range(0, len(params), 5)]


def decode_bulk_write(params: bytes) -> list[tuple[int, int, bytes]]:
    """BULK_WRITE params -> [(id, address, data)] in the order listed."""
    out: list[tuple[int, int, bytes]] = []
    k = 0
    while k < len(params):
        _need(params[k:], 5, "BULK_WRITE item", exact=False)
        length = from_bytes(params[k + 3:k + 5], False)
        data = params[k + 5:k + 5 + length]
        if len(data) != length:
            raise ProtocolError(f"BULK_WRITE: id {params[k]}: {len(data)} of {length} bytes")
        out.append((params[k], from_bytes(params[k + 1:k + 3], False), data))
        k += 5 + length
    if not out:
        raise ProtocolError("BULK_WRITE: no items")
    return out


#: Decoded frames a `Parser` remembers (a few polls' worth of status packets).
FRAME_CACHE = 64


class Parser:
    """Incremental Protocol 2.0 deframer, h11-style: `feed(bytes)`, then `next_event()`
    until None. Works for both directions (instructions and status packets).

    A frame is a header, then exactly LEN bytes: no header found inside those bytes is ever
    a resync point. This matters because DynamixelSDK does not stuff what it sends (its
    txPacket drops addStuffing's result), so an unstuffed payload may hold FF FF FD; we
    check the CRC on the raw bytes, then unstuff (a no-op on unstuffed payloads without
    FF FF FD FD). On a bad CRC or an absurd LEN (< 3, or a frame beyond the buffer limit)
    we report a ParseError and resume the search one byte after the bad header's start, so
    a good packet inside the bad frame's span is still found. Bytes before a header are
    reported as ParseError(kind="garbage") when dropped (possibly split over several events
    when fed in pieces). Memory is bounded by `limit`: bytes fed past it are dropped from
    the front and reported as kind="overflow". Nothing here raises on input.
    """

    def __init__(self, limit: int = BUFFER_LIMIT) -> None:
        self._buf = bytearray()
        self._limit = limit
        self._overflow = 0
        #: Frames already checked and decoded, by their raw bytes: a poll reads the same
        #: status packets again and again while the arm rests, and the same bytes make the
        #: same packet (no CRC, unstuffing or decoding again). Bounded by FRAME_CACHE.
        self._known: dict[bytes, Packet] = {}

    @property
    def buffered(self) -> int:
        """Bytes held waiting for the rest of a frame."""
        return len(self._buf)

    def feed(self, data: bytes) -> None:
        self._buf += data
        excess = len(self._buf) - self._limit
        if excess > 0:
            del self._buf[:excess]
            self._overflow += excess

    def clear(self) -> int:
        """Drop everything buffered (e.g. after a reply timeout); returns the count dropped."""
        n = len(self._buf)
        self._buf.clear()
        return n

    def __iter__(self) -> Iterator[Packet | ParseError]:
        while (event := self.next_event()) is not None:
            yield event

    def next_event(self) -> Packet | ParseError | None:
        """The next packet or framing error, or None when more bytes are needed."""
        if self._overflow:
            n, self._overflow = self._overflow, 0
            return ParseError("overflow", f"receive buffer over {self._limit} bytes", n)
        buf = self._buf
        start = buf.find(HEADER)
        if start < 0:
            keep = next((k for k in (3, 2, 1) if buf.endswith(HEADER[:k])), 0)
            start = len(buf) - keep
        if start > 0:
            del buf[:start]
            return ParseError("garbage", "bytes before a header", start)
        if len(buf) < PREFIX_LEN:
            return None
        length = buf[5] | buf[6] << 8
        if length < 3 or PREFIX_LEN + length > self._limit:
            del buf[:1]
            return ParseError("length", f"LEN {length} outside 3..{self._limit - PREFIX_LEN}", 1)
        end = PREFIX_LEN + length
        if len(buf) < end:
            return None
        raw = bytes(buf[:end])
        known = self._known.get(raw)
        if known is not None:
            del buf[:end]
            return known
        if crc16(raw[:-2]) != from_bytes(raw[-2:], False):
            del buf[:1]
            return ParseError("crc", f"CRC mismatch in a {end}-byte frame", 1, raw[4])
        del buf[:end]
        body = unstuff(raw[PREFIX_LEN:-2])
        if body[0] == Instruction.STATUS:
            if len(body) < 2:
                return ParseError("length", "status packet without an error byte", end)
            packet = Packet(raw[4], body[0], body[2:], body[1])
        else:
            packet = Packet(raw[4], body[0], body[1:])
        if len(self._known) >= FRAME_CACHE:
            self._known.clear()
        self._known[raw] = packet
        return packet
