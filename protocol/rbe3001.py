"""RBE3001 (Gen A) 64-byte HID packet codec: framing and the SET_PID/STATUS/SET_GAIN/SET_CLAW set.

Wire facts (WPIRoboticsEngineering/RBE3001_nucleo_firmware, SimplePacketComs framing):
a packet is 64 bytes, little-endian: bytes 0-3 a uint32 command id, bytes 4-63 fifteen
float32. The firmware looks the id up, lets the matching server rewrite the float buffer in
place and sends the same 64 bytes back, so a reply carries the request's id; an unknown id
gets no reply (later SimplePacketComs builds answer it with error id 99, the unknown id in
bytes 4-7). The hidapi report-id byte (0) is the HID link's business, not this codec's.

What a reply's floats hold depends on the build. PidServer.cpp zeroes the whole float area
("re-initialize the packet to all zeros") before writing its nine readings, and the STATUS,
GAIN and CLAW servers of the design were written like it, so their replies carry nothing of
the request: no tag can be echoed. Other builds echo what their server does not overwrite.
`ReplyMatcher` accepts both: it matches on the command id and on order (one request
outstanding per link), never on an echoed value.

Sans-IO: bytes in, dataclasses out; no I/O, no awaits. Positions and velocities are encoder
ticks and ticks/s (AS5050, 4096 a turn); strain gauges are raw ADC fractions 0..1.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Sequence
from dataclasses import dataclass
from enum import IntEnum
from typing import ClassVar

PACKET_SIZE = 64
N_FLOATS = 15
_PACKET = struct.Struct("<I15f")
_MAX_ID = 0xFFFF_FFFF
#: SimplePacketComs (madhephaestus/SimplePacketComs, src/SimplePacketComs.cpp, later builds)
#: answers an id no server handles with this id and the unknown id in bytes 4-7.
ERROR_ID = 99


class CommandId(IntEnum):
    SET_PID = 37
    STATUS = 38
    SET_GAIN = 39
    SET_CLAW = 40


class DecodeError(ValueError):
    """The bytes are not a valid packet or reply (a remote protocol error)."""


class UnknownCommand(DecodeError):
    """A well-framed packet whose id no server handles; the firmware stays silent."""

    def __init__(self, command_id: int) -> None:
        super().__init__(f"unknown command id {command_id}")
        self.command_id = command_id


@dataclass(frozen=True)
class RawPacket:
    command_id: int
    values: tuple[float, ...]  # always N_FLOATS long


def encode_packet(command_id: int, values: Sequence[float] = ()) -> bytes:
    """One 64-byte packet: uint32 id then up to 15 float32, the rest zero."""
    if not 0 <= command_id <= _MAX_ID:
        raise ValueError(f"command id {command_id} is outside uint32")
    if len(values) > N_FLOATS:
        raise ValueError(f"a packet holds {N_FLOATS} floats, got {len(values)}")
    padded = [float(v) for v in values] + [0.0] * (N_FLOATS - len(values))
    try:
        return _PACKET.pack(command_id, *padded)
    except OverflowError as exc:  # a finite double too large for float32
        raise ValueError(f"value does not fit a float32: {exc}") from exc


def decode_packet(data: bytes | bytearray | memoryview) -> RawPacket:
    """Split a 64-byte packet into its id and 15 floats; DecodeError on any other length."""
    if len(data) != PACKET_SIZE:
        kind = "short" if len(data) < PACKET_SIZE else "long"
        raise DecodeError(f"{kind} packet: {len(data)} bytes, expected {PACKET_SIZE}")
    command_id, *values = _PACKET.unpack(bytes(data))
    return RawPacket(command_id, tuple(values))


# --- commands (host -> firmware) -------------------------------------------------------


@dataclass(frozen=True)
class JointSetpoint:
    """One joint's SET_PID slot; the firmware uses only the position (velocity and force are
    carried but 'currently unused' in PidServer.cpp)."""

    position_ticks: float
    velocity_ticks_s: float = 0.0
    force: float = 0.0


@dataclass(frozen=True)
class SetPid:
    """Position setpoints for the three joints, joint i at floats 3i, 3i+1, 3i+2."""

    setpoints: tuple[JointSetpoint, JointSetpoint, JointSetpoint]
    command_id: ClassVar[int] = CommandId.SET_PID


@dataclass(frozen=True)
class Status:
    """Read positions, velocities and strain gauges without moving."""

    command_id: ClassVar[int] = CommandId.STATUS


@dataclass(frozen=True)
class SetGain:
    """PID gains of one joint (axis 0-2), firmware units: kp in output fraction per tick."""

    axis: int
    kp: float
    ki: float
    kd: float
    command_id: ClassVar[int] = CommandId.SET_GAIN


@dataclass(frozen=True)
class SetClaw:
    """Claw setpoint, 0.0 open .. 1.0 closed."""

    value: float
    command_id: ClassVar[int] = CommandId.SET_CLAW


Command = SetPid | Status | SetGain | SetClaw


# --- replies (firmware -> host) --------------------------------------------------------

Triple = tuple[float, float, float]
Triple3 = tuple[Triple, Triple, Triple]


@dataclass(frozen=True)
class SetPidReply:
    """PidServer rewrites joint i's floats as position [3i], velocity [3i+1], load cell [3i+2]."""

    position_ticks: Triple
    velocity_ticks_s: Triple
    strain_adc: Triple


@dataclass(frozen=True)
class StatusReply:
    """Positions at floats 0-2, velocities (ticks/s) at 3-5, strain ADC at 6-8."""

    position_ticks: Triple
    velocity_ticks_s: Triple
    strain_adc: Triple


@dataclass(frozen=True)
class Ack:
    """SET_GAIN and SET_CLAW: the reply's floats carry nothing (zeroed or echoed by build).
    The design document says they "do not provide any return values": a build may answer
    other bytes (`other`), or nothing at all (the driver's business: it waits a short quiet
    time and reports the command sent)."""

    command_id: int
    other: bool = False


Reply = SetPidReply | StatusReply | Ack


def _finite(name: str, values: Sequence[float]) -> None:
    for i, v in enumerate(values):
        if not math.isfinite(v):
            raise ValueError(f"{name}[{i}] must be finite, got {v}")


def _validate(cmd: Command) -> None:
    if isinstance(cmd, SetPid):
        if len(cmd.setpoints) != 3:
            raise ValueError(f"SET_PID needs 3 setpoints, got {len(cmd.setpoints)}")
        for i, sp in enumerate(cmd.setpoints):
            _finite(f"setpoints[{i}]", (sp.position_ticks, sp.velocity_ticks_s, sp.force))
    elif isinstance(cmd, SetGain):
        if isinstance(cmd.axis, bool) or cmd.axis not in (0, 1, 2):
            raise ValueError(f"SET_GAIN axis must be 0, 1 or 2, got {cmd.axis!r}")
        _finite("gains", (cmd.kp, cmd.ki, cmd.kd))
    elif isinstance(cmd, SetClaw):
        _finite("claw", (cmd.value,))
        if not 0.0 <= cmd.value <= 1.0:
            raise ValueError(f"SET_CLAW value must be within 0..1, got {cmd.value}")


def _floats(cmd: Command) -> list[float]:
    if isinstance(cmd, SetPid):
        return [
            x for sp in cmd.setpoints for x in (sp.position_ticks, sp.velocity_ticks_s, sp.force)
        ]
    if isinstance(cmd, SetGain):
        return [float(cmd.axis), cmd.kp, cmd.ki, cmd.kd]
    if isinstance(cmd, SetClaw):
        return [cmd.value]
    return []


def encode_command(cmd: Command) -> bytes:
    """The 64-byte packet for a command; ValueError if a field is out of range or not finite."""
    _validate(cmd)
    return encode_packet(cmd.command_id, _floats(cmd))


def _triple(raw: RawPacket, name: str, indices: Sequence[int]) -> Triple:
    out: list[float] = []
    for k, idx in enumerate(indices):
        v = raw.values[idx]
        if not math.isfinite(v):
            raise DecodeError(f"{name}[{k}] is {v} (float {idx}), expected a finite number")
        out.append(v)
    return (out[0], out[1], out[2])


def _sensors(raw: RawPacket, pos: Sequence[int], vel: Sequence[int], adc: Sequence[int]) -> Triple3:
    return (
        _triple(raw, "position_ticks", pos),
        _triple(raw, "velocity_ticks_s", vel),
        _triple(raw, "strain_adc", adc),
    )


def decode_reply(request: Command | int, data: bytes | bytearray | memoryview) -> Reply:
    """Decode the firmware's answer to `request` (a command or its id).

    DecodeError if the packet is malformed, carries another id, or has a NaN/inf where a
    reading is required. An id outside CommandId decodes as an Ack (its floats stay raw)."""
    expected = request if isinstance(request, int) else request.command_id
    raw = decode_packet(data)
    if raw.command_id != expected:
        raise DecodeError(f"reply id {raw.command_id} does not match request {expected}")
    if expected == CommandId.SET_PID:
        return SetPidReply(*_sensors(raw, (0, 3, 6), (1, 4, 7), (2, 5, 8)))
    if expected == CommandId.STATUS:
        return StatusReply(*_sensors(raw, (0, 1, 2), (3, 4, 5), (6, 7, 8)))
    return Ack(raw.command_id)


# --- the simulator's side --------------------------------------------------------------


def decode_command(data: bytes | bytearray | memoryview) -> Command:
    """Parse a host packet as the firmware would; UnknownCommand for an id no server has,
    DecodeError for a malformed packet or out-of-range field."""
    raw = decode_packet(data)
    v = raw.values
    cid = raw.command_id
    cmd: Command
    if cid == CommandId.SET_PID:
        cmd = SetPid(
            (
                JointSetpoint(v[0], v[1], v[2]),
                JointSetpoint(v[3], v[4], v[5]),
                JointSetpoint(v[6], v[7], v[8]),
            )
        )
    elif cid == CommandId.STATUS:
        cmd = Status()
    elif cid == CommandId.SET_GAIN:
        if v[0] not in (0.0, 1.0, 2.0):
            raise DecodeError(f"SET_GAIN axis {v[0]} is not 0, 1 or 2")
        cmd = SetGain(int(v[0]), v[1], v[2], v[3])
    elif cid == CommandId.SET_CLAW:
        cmd = SetClaw(v[0])
    else:
        raise UnknownCommand(cid)
    try:
        _validate(cmd)
    except ValueError as exc:
        raise DecodeError(str(exc)) from exc
    return cmd


def encode_reply(reply: Reply, request: bytes | None = None, *, echo: bool = False) -> bytes:
    """The firmware's answer to the received packet `request` (zeros when None).

    By default as PidServer.cpp: the float area is zeroed, then the server writes its values
    (nine readings for SET_PID and STATUS, none for SET_GAIN and SET_CLAW). With `echo`, as
    builds whose servers leave what they do not overwrite: STATUS writes floats 0-8 over the
    request, SET_GAIN and SET_CLAW send the request back unchanged (SET_PID still zeroes)."""
    base = [0.0] * N_FLOATS
    if echo and request is not None and not isinstance(reply, SetPidReply):
        base = list(decode_packet(request).values)
    if isinstance(reply, SetPidReply):
        for i in range(3):
            base[3 * i : 3 * i + 3] = [
                reply.position_ticks[i],
                reply.velocity_ticks_s[i],
                reply.strain_adc[i],
            ]
        return encode_packet(CommandId.SET_PID, base)
    if isinstance(reply, StatusReply):
        base[0:9] = [*reply.position_ticks, *reply.velocity_ticks_s, *reply.strain_adc]
        return encode_packet(CommandId.STATUS, base)
    return encode_packet(reply.command_id, base)


# --- the host's side: framing and request matching (sans-IO) ----------------------------


class UnknownToFirmware(DecodeError):
    """The firmware answered with SimplePacketComs' error packet: it has no server for the id."""

    def __init__(self, command_id: int) -> None:
        super().__init__(f"the firmware has no server for command id {command_id}")
        self.command_id = command_id


class FrameParser:
    """Cut a byte stream (a serial or socket link) into 64-byte packets.

    There is no sync byte and no checksum, so a frame starts only where the first four bytes
    are a known command id (CommandId or ERROR_ID); anything else is dropped one byte at a
    time until such an id lines up (`skipped` counts the bytes). A packetised link (HID: one
    report a read) feeds one report at a time and gets it back whole, or nothing for a
    report of another length."""

    def __init__(self, known_ids: frozenset[int] | None = None) -> None:
        self.known_ids = known_ids if known_ids is not None else KNOWN_IDS
        self._buf = bytearray()
        self.skipped = 0

    def clear(self) -> None:
        self._buf.clear()

    @property
    def pending(self) -> int:
        return len(self._buf)

    def feed(self, data: bytes | bytearray | memoryview) -> list[bytes]:
        self._buf.extend(data)
        out: list[bytes] = []
        while len(self._buf) >= PACKET_SIZE:
            rid = int.from_bytes(self._buf[0:4], "little")
            if rid in self.known_ids:
                out.append(bytes(self._buf[:PACKET_SIZE]))
                del self._buf[:PACKET_SIZE]
            else:
                del self._buf[0]
                self.skipped += 1
        return out

    def feed_report(self, data: bytes | bytearray | memoryview) -> bytes | None:
        """One HID report: the packet, or None for a report that is not 64 bytes."""
        return bytes(data) if len(data) == PACKET_SIZE else None


KNOWN_IDS = frozenset({int(c) for c in CommandId} | {ERROR_ID})
_TAIL = slice(4 + 9 * 4, PACKET_SIZE)  # floats 9-14: sent as zeros, never written by a server


#: Decoded reading replies a `ReplyMatcher` remembers.
KNOWN_REPLIES = 64
_STATUS = Status()
_STATUS_PACKET = encode_command(_STATUS)  # STATUS has no fields: the same packet every poll


class ReplyMatcher:
    """Match firmware replies to the one outstanding request, by id and order alone.

    `request(cmd)` encodes the command (floats 9-14 zero) and makes it the outstanding one.
    `match(frame)` answers the decoded reply, or None for a frame that belongs to no request
    now outstanding (another id: a late answer to an earlier request; `stale` counts them).
    It raises UnknownToFirmware for an error packet naming the outstanding id and DecodeError
    for a frame with the right id that cannot be a true answer:
    - a reading reply (SET_PID, STATUS) whose floats 9-14 are not zero: every build either
      zeroes them or echoes the zeros we sent;
    - (a SET_GAIN / SET_CLAW reply whose floats are neither all zero (PidServer-style
      builds) nor the request's floats (echoing builds) is taken, marked `Ack.other`: those
      commands "do not provide any return values" (design document), so what a build writes
      there says nothing of whether it acted);
    - a NaN or infinity where a reading belongs.
    What it cannot tell apart is a late reply with the same id as the outstanding request:
    the caller must not send after a timeout until the link has been quiet (see the driver).
    """

    def __init__(self) -> None:
        self.outstanding: Command | None = None
        self._packet = b""
        self.stale = 0
        #: Reading replies already checked and decoded, by their bytes: an arm at rest
        #: answers each STATUS with the same 64 bytes (bounded by KNOWN_REPLIES).
        self._known: dict[bytes, Reply] = {}

    def request(self, cmd: Command) -> bytes:
        packet = _STATUS_PACKET if cmd == _STATUS else encode_command(cmd)
        self.outstanding = cmd
        self._packet = packet
        return packet

    def cancel(self) -> None:
        self.outstanding = None

    def match(self, frame: bytes) -> Reply | None:
        cmd = self.outstanding
        if len(frame) != PACKET_SIZE:
            raise DecodeError(f"a reply is {PACKET_SIZE} bytes, got {len(frame)}")
        rid = int.from_bytes(frame[0:4], "little")
        if cmd is None:
            self.stale += 1
            return None
        if rid == ERROR_ID:
            missing = int.from_bytes(frame[4:8], "little")
            if missing == cmd.command_id:
                self.outstanding = None
                raise UnknownToFirmware(missing)
            self.stale += 1
            return None
        if rid != cmd.command_id:
            self.stale += 1
            return None
        reading = isinstance(cmd, SetPid | Status)
        if reading:
            key = bytes(frame)
            known = self._known.get(key)
            if known is not None:  # the same bytes: the same checks passed, the same reply
                self.outstanding = None
                return known
            if frame[_TAIL] != bytes(PACKET_SIZE - _TAIL.start):
                raise DecodeError(f"reply to id {cmd.command_id}: floats 9-14 changed "
                                  "(no build writes them): corrupted")
        elif frame[4:] != bytes(PACKET_SIZE - 4) and frame[4:] != self._packet[4:]:
            self.outstanding = None
            return Ack(cmd.command_id, other=True)
        reply = decode_reply(cmd, frame)
        if reading:
            if len(self._known) >= KNOWN_REPLIES:
                self._known.clear()
            self._known[key] = reply
        self.outstanding = None
        return reply
