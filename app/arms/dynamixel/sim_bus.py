"""A simulated Dynamixel Protocol 2.0 bus of MX-28 servos: a SimDevice (app/sim/base.py).

Bytes written by the host go through `protocol.dynamixel.Parser`; every instruction is
answered as the e-manual (https://emanual.robotis.com/docs/en/dxl/protocol2/) describes:

- Unicast instructions are answered by the addressed servo, subject to its Status Return
  Level (0: PING only, 1: PING and READ/SYNC_READ/BULK_READ, 2: all). Broadcast instructions
  other than PING, SYNC_READ and BULK_READ are executed by every servo without a reply.
- Broadcast PING: every servo answers, in id order. SYNC_READ / BULK_READ: the listed servos
  answer in the order listed; absent ids are skipped (the host times out, as on hardware).
- A frame with a bad CRC is answered with the CRC error status when its id byte names a
  servo at Status Return Level 2 (the e-manual lists CRC error 0x03 as a status error);
  otherwise it is ignored. Unknown instructions get the instruction error, malformed
  params the data length error. Status packets on the bus (another device's) are ignored.
- The bus baud rate is the host's: served on a pseudo-terminal it follows the termios rate
  the host set (`set_host_baudrate`, app/sim/servers.py); None (`baudrate=None`, a TCP
  socket, which carries no baud rate) lets every servo hear. Servos start configured for the
  bus baud rate (code 3 at 1 Mbps); a factory reset puts them back at 57,600 as real ones.
  A servo whose Baud Rate item is another rate than the host's reads the host's bytes as its
  UART does (app/sim/uart.py `resample`: sampled at its own bit times, wrong values, more or
  fewer bytes, framing errors) and acts on what that decodes to; its replies go back at its
  rate and the host's UART reads them the same way. Between the standard rates nothing
  decodes (the header FF FF FD 00 does not survive), so such a servo is silent, as real ones
  are at the wrong rate ("no status packet"); where a header survives with a bad CRC (a 4 Mbps
  host, a 4.5 Mbps servo: 12.5 % apart) a unicast instruction draws the servo's CRC error
  status, which the host reads as garbled bytes.
- Factory state (`DynamixelBus.factory`): every servo ID 1 at 57,600 bps, as the MX-28(2.0)
  and XM430 ship (e-manual, "Control Table of EEPROM Area": ID 1, Baud Rate 1 = 57,600).
  Two listening servos on one ID both act on an instruction and both answer at once: their
  status packets collide on the half-duplex line (`_collide`: garbled bytes that fail the
  CRC; counted in `collisions`).

Reply timing: replies are serialised on the half-duplex bus. Each starts after the
instruction's wire time, the servo's Return Delay Time (2 us units) and the wire time of
the replies before it; wire time is 10 bits a byte at `baudrate`.
"""

from __future__ import annotations

import functools
from collections.abc import Iterable, Mapping
from typing import Any

from app.arms.dynamixel.sim_mx28 import BAUD_CODES, Mx28Servo
from app.sim.uart import resample
from protocol import dynamixel as dxl
from protocol.dynamixel import BROADCAST_ID, ErrorCode, Instruction, Packet, ParseError

_READS = (Instruction.READ, Instruction.SYNC_READ, Instruction.BULK_READ)
#: The rate a servo ships at (e-manual MX-28(2.0) and XM430-W350: Baud Rate (8) initial 1).
FACTORY_BAUDRATE = 57_600


def baud_code(baudrate: int) -> int:
    """The Baud Rate (8) code of a rate; ValueError naming the valid rates otherwise."""
    codes = [c for c, b in BAUD_CODES.items() if b == baudrate]
    if not codes:
        raise ValueError(f"baudrate {baudrate} is not an MX-28 rate {sorted(BAUD_CODES.values())}")
    return codes[0]


#: A servo at rest answers a poll with the same status packet each time: framed (stuffing,
#: CRC) once.
_encode_status = functools.lru_cache(maxsize=256)(dxl.encode_status)


class DynamixelBus:
    """Several simulated MX-28 servos on one bus."""

    packetized = False

    def __init__(self, ids: Iterable[int] = (1, 2, 3, 4), baudrate: int | None = 1_000_000,
                 operating_modes: Mapping[int, int] | None = None,
                 models: Mapping[int, type[Mx28Servo]] | None = None) -> None:
        """`models` gives a servo class per id (default MX-28), e.g. Xm430Servo for an
        OpenManipulator-X's ids; every class shares the MX-28's baud-rate codes. `baudrate`
        None: the host's rate is unknown (a socket) and every servo hears (servos at 1 Mbps)."""
        code = baud_code(1_000_000 if baudrate is None else baudrate)
        modes = dict(operating_modes or {})
        self.baudrate = baudrate
        kinds = dict(models or {})
        self.servos = [kinds.get(i, Mx28Servo)(i, modes.get(i, 3), code)
                       for i in sorted(set(ids))]
        #: Instructions whose replies collided (two servos on one ID), counted.
        self.collisions = 0
        self.parser = dxl.Parser()
        #: Parsers of the host's bytes as a servo at another rate reads them, by that rate.
        self._parsers: dict[int, dxl.Parser] = {}
        #: The rate whose servos act on the instruction being handled (`hears`).
        self._rate: int | None = baudrate
        self.errors: list[ParseError] = []  # last framing errors seen, newest last (bounded)
        self._now: float | None = None
        self._busy_until = 0.0
        #: Gravity on the falling joints of the arm these servos are (app/arms/dynamixel/
        #: sim_gravity.py; `simulated_bus` sets it from the profile), None: none modelled.
        self.gravity: Any = None

    @classmethod
    def factory(cls, count: int = 1, baudrate: int | None = FACTORY_BAUDRATE,
                model: type[Mx28Servo] = Mx28Servo) -> DynamixelBus:
        """`count` servos as they leave the factory: ID 1, 57,600 bps, position mode, on a
        bus whose host is at `baudrate` (None: a socket, every servo hears)."""
        bus = cls(ids=(), baudrate=baudrate)
        for _ in range(count):
            bus.add_servo(model)
        return bus

    def add_servo(self, model: type[Mx28Servo] = Mx28Servo, id: int = 1,
                  baudrate: int = FACTORY_BAUDRATE) -> Mx28Servo:
        """Plug one more servo into the bus (default: a factory one, ID 1 at 57,600)."""
        servo = model(id, 3, baud_code(baudrate))
        if self._now is not None:
            servo.advance(0.0, self._now)
        self.servos.append(servo)
        return servo

    def remove_servo(self, servo: Mx28Servo) -> None:
        """Unplug a servo."""
        self.servos.remove(servo)

    def set_host_baudrate(self, baudrate: int | None) -> None:
        """The rate the host's UART runs at now (the pty server calls this with the
        termios rate before each write of the host; 0: one it cannot tell): servos at another
        rate read the host's bytes re-sampled at theirs."""
        self.baudrate = baudrate
        self._rate = baudrate

    # SimDevice ----------------------------------------------------------------------------
    def advance(self, now: float) -> None:
        if self._now is None:
            self._now = now
        dt = now - self._now
        if dt < 0:
            return
        self._now = now
        for s in self.servos:
            s.advance(dt, now)
        if self.gravity is not None:
            self.gravity.step(now)

    def receive(self, data: bytes, now: float) -> list[tuple[float, bytes]]:
        self.advance(now)
        self.parser.feed(data)
        out: list[tuple[float, bytes]] = []
        t = max(now, self._busy_until)
        for event in self.parser:
            if isinstance(event, ParseError):
                self.errors = [*self.errors[-15:], event]
            t = self._act(event, t, now, out)
        host = self.baudrate
        if host:  # servos at other rates read the host's bytes as their UARTs do
            for rate in sorted({BAUD_CODES.get(s.get("baud_rate"), 0) for s in self.servos}
                               - {host, 0}):
                parser = self._parsers.setdefault(rate, dxl.Parser())
                parser.feed(resample(data, host, rate))
                self._rate = rate
                try:
                    for event in parser:
                        t = self._act(event, t, now, out)
                finally:
                    self._rate = host
        self._busy_until = t
        return out

    def _act(self, event: Packet | ParseError, t: float, now: float,
             out: list[tuple[float, bytes]]) -> float:
        """Handle one instruction (or framing error) as the servos at `self._rate` read it;
        their replies, timed at that rate and read at the host's, appended to `out`."""
        if isinstance(event, ParseError):
            replies = self._on_corrupt(event)
            frame_len = 0
        else:
            replies = self._handle(event)
            frame_len = len(event.params) + 10
        rate = self._rate
        t += self._wire(frame_len, rate)
        for servo, reply in replies:
            t += servo.get("return_delay_time") * 2e-6 + self._wire(len(reply), rate)
            if rate and self.baudrate and rate != self.baudrate:
                reply = resample(reply, rate, self.baudrate)
            if reply:
                out.append((t - now, reply))
        return t

    # helpers ------------------------------------------------------------------------------
    def hears(self, s: Mx28Servo) -> bool:
        """Whether servo `s` acts on the instruction being handled: its Baud Rate is the rate
        being decoded (the host's, outside `receive`), or the host's rate is unknown."""
        return self.baudrate is None or BAUD_CODES.get(s.get("baud_rate")) == self._rate

    def servo(self, id: int) -> Mx28Servo | None:
        """The listening servo with this id (the first, if ids collide), or None."""
        for s in self.servos:
            if s.id == id and self.hears(s):
                return s
        return None

    def _same_id(self, id: int) -> list[Mx28Servo]:
        """Every listening servo with this id (more than one: their replies collide)."""
        return [s for s in self.servos if s.id == id and self.hears(s)]

    def _listening(self) -> list[Mx28Servo]:
        return sorted((s for s in self.servos if self.servo(s.id) is s), key=lambda s: s.id)

    def _wire(self, n_bytes: int, rate: int | None = None) -> float:
        return n_bytes * 10.0 / (rate or self.baudrate or 1_000_000)

    def _collide(self, replies: list[tuple[Mx28Servo, bytes]]) -> list[tuple[Mx28Servo, bytes]]:
        """Replies of servos that share an id overlap on the line: one garbled packet. The
        second starts one byte time after the first (two servos' delays are never exactly
        equal), and the line reads the AND of both (either transmitter pulls it low), so even
        two identical replies garble past the header and fail the CRC."""
        out: list[tuple[Mx28Servo, bytes]] = []
        for servo, reply in replies:
            if out and out[-1][0].id == servo.id and len(self._same_id(servo.id)) > 1:
                first, late = out[-1][1] + b"\xff", b"\xff" + reply
                n = max(len(first), len(late))
                first, late = first.ljust(n, b"\xff"), late.ljust(n, b"\xff")
                merged = bytes(a & b for a, b in zip(first, late, strict=True))
                out[-1] = (out[-1][0], merged)
                self.collisions += 1
            else:
                out.append((servo, reply))
        return out

    @staticmethod
    def _status(servo: Mx28Servo, error: int, params: bytes = b"") -> tuple[Mx28Servo, bytes]:
        if servo.alert:
            error |= dxl.ALERT_BIT
        return servo, _encode_status(servo.id, error, bytes(params))

    def _on_corrupt(self, event: ParseError) -> list[tuple[Mx28Servo, bytes]]:
        s = self.servo(event.id) if event.kind == "crc" and event.id is not None else None
        if s is None or s.get("status_return_level") < 2:
            return []
        return [self._status(s, ErrorCode.CRC)]

    def _handle(self, p: Packet) -> list[tuple[Mx28Servo, bytes]]:
        if p.error is not None:
            return []  # a status packet: another device's reply
        if p.instruction == Instruction.PING:
            targets = (sorted((s for s in self.servos if self.hears(s)), key=lambda s: s.id)
                       if p.id == BROADCAST_ID else self._same_id(p.id))
            return self._collide([self._status(s, 0, dxl.to_bytes(s.get("model_number"), 2)
                                               + bytes((s.get("firmware_version"),)))
                                  for s in targets])
        try:
            if p.instruction == Instruction.SYNC_READ:
                address, length, ids = dxl.decode_sync_read(p.params)
                return self._reads([(i, address, length) for i in ids])
            if p.instruction == Instruction.BULK_READ:
                return self._reads(dxl.decode_bulk_read(p.params))
            if p.instruction == Instruction.SYNC_WRITE:
                address, _, items = dxl.decode_sync_write(p.params)
                for i, data in items.items():
                    if (s := self.servo(i)) is not None:
                        s.write(address, data)
                return []
            if p.instruction == Instruction.BULK_WRITE:
                for i, address, data in dxl.decode_bulk_write(p.params):
                    if (s := self.servo(i)) is not None:
                        s.write(address, data)
                return []
        except dxl.ProtocolError:
            return []  # a broadcast instruction: nobody answers
        targets = self._listening() if p.id == BROADCAST_ID else self._same_id(p.id)
        replies = []
        for s in targets:
            error, params = self._unicast(s, p)
            level = s.get("status_return_level")
            if p.id != BROADCAST_ID and (level >= 2 or (level == 1 and p.instruction in _READS)):
                replies.append(self._status(s, error, params))
        return self._collide(replies)

    def _reads(self, items: list[tuple[int, int, int]]) -> list[tuple[Mx28Servo, bytes]]:
        replies = []
        for i, address, length in items:
            for s in self._same_id(i):
                if s.get("status_return_level") >= 1:
                    error, data = s.read(address, length)
                    replies.append(self._status(s, error, data))
        return self._collide(replies)

    def _unicast(self, s: Mx28Servo, p: Packet) -> tuple[int, bytes]:
        """Run one instruction on one servo: (error code, status params)."""
        inst = p.instruction
        try:
            if inst == Instruction.READ:
                return s.read(*dxl.decode_read(p.params))
            if inst == Instruction.WRITE:
                return s.write(*dxl.decode_write(p.params)), b""
            if inst == Instruction.REG_WRITE:
                return s.reg_write(*dxl.decode_write(p.params)), b""
            if inst == Instruction.ACTION:
                return s.action(), b""
            if inst == Instruction.REBOOT:
                return s.reboot(), b""
            if inst == Instruction.FACTORY_RESET:
                if len(p.params) != 1:
                    return ErrorCode.DATA_LENGTH, b""
                return s.factory_reset(p.params[0]), b""
            if inst == Instruction.CLEAR:
                return s.clear(p.params), b""
        except dxl.ProtocolError:
            return ErrorCode.DATA_LENGTH, b""
        return ErrorCode.INSTRUCTION, b""

    # fault injection (tests and `armserver sim dynamixel --fault`) ---------------------------
    def _one(self, id: int) -> Mx28Servo:
        s = self.servo(id)
        if s is None:
            raise KeyError(f"no servo {id} on the bus")
        return s

    def _some(self, ids: Iterable[int] | None) -> list[Mx28Servo]:
        return list(self.servos) if ids is None else [self._one(i) for i in ids]

    def inject_hardware_error(self, id: int, bits: int | str | list[str] | tuple[str, ...]
                              ) -> None:
        """Raise Hardware Error Status bits on servo `id`: a mask (0x20) or names ("overload",
        ["overheating", "electrical_shock"]; see protocol.mx28.HARDWARE_ERRORS). The alert bit
        is set in its replies and, for a bit in its Shutdown item, torque goes off, both until
        REBOOT."""
        self._one(id).inject_hardware_error(bits)

    def set_supply_voltage(self, volts: float, ids: Iterable[int] | None = None) -> None:
        """The supply the servos see (V): their speed scales with it and, outside their
        voltage limits, they raise the input voltage error."""
        for s in self._some(ids):
            s.supply_v = float(volts)
            s.advance(0.0, self._now or 0.0)

    def set_temperature(self, celsius: float, ids: Iterable[int] | None = None) -> None:
        """Internal temperature (C): above Temperature Limit, the overheating error."""
        for s in self._some(ids):
            s.temperature_c = float(celsius)
            s.advance(0.0, self._now or 0.0)

    def power_cycle(self, ids: Iterable[int] | None = None) -> None:
        """Power off and on (all servos, or `ids`): RAM defaults, torque off, errors cleared,
        position re-initialised within one turn. No reply tells the host."""
        for s in self._some(ids):
            s.power_cycle()

    def brown_out(self, ids: Iterable[int] | None = None) -> None:
        """A supply dip deep enough to reset the servos' controller: a power cycle the host
        is not told about (it finds torque off and the multi-turn count lost)."""
        self.power_cycle(ids)

    def set_torque_refusal(self, error: int) -> None:
        """What a servo answers to Torque Enable = 1 after a shutdown: 0 (default: the write is
        ignored, only the Alert bit shows) or an error number such as ErrorCode.RESULT_FAIL."""
        for s in self.servos:
            s.torque_refusal = int(error)
