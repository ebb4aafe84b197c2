"""Servo set-up from the factory state (`armserver setup-servos`): scan a bus at the standard
baud rates, find the servos, and give one of them a joint's ID, baud rate, operating mode and
limits as the profile wants, then verify. Blocking pyserial, one port, no server: a set-up
step done before the arm is served (the port is opened exclusively, so a server holding it
is told about, never disturbed).

What the hardware does, from the ROBOTIS e-manual (MX-28(2.0)
https://emanual.robotis.com/docs/en/dxl/mx/mx-28-2/ and XM430-W350
https://emanual.robotis.com/docs/en/dxl/x/xm430-w350/, "Control Table of EEPROM Area";
Protocol 2.0 https://emanual.robotis.com/docs/en/dxl/protocol2/):

- A servo ships as ID 1 at Baud Rate 1 (57,600 bps), Operating Mode 3 (position).
- ID (7), Baud Rate (8), Return Delay Time (9), Operating Mode (11), Homing Offset (20) and
  the position limits (48, 52) are EEPROM: written only while Torque Enable (64) is 0. This
  tool never switches torque off itself (a servo holding a load would drop it): a servo with
  torque on is refused, to be power-cycled (torque is off at power-up).
- Broadcast PING (ID 254) is answered by every servo on the bus, each with its model number
  and firmware version (DynamixelSDK `broadcastPing` scans this way); two servos on one ID
  answer at once and their replies collide (garbled bytes, a CRC failure): refused, with
  "connect one servo at a time".
- A new ID is in force at once (the status of that WRITE may come from either ID, so it is
  not relied on: the servo is PINGed at the new ID); a new Baud Rate too, so it is written
  last and the servo verified at the new rate.

A `socket://` URL (the project's simulator, `armserver sim dynamixel --factory N --listen`)
carries no baud rate: one broadcast PING there, and each servo's rate is read from its Baud
Rate item. A serial device (a U2D2 at /dev/ttyUSB0, or the simulator's pty) is scanned at
each rate.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from app.links.serial import port_fileno
from app.runtime.control_thread import terminal_hold
from protocol import dynamixel as dxl
from protocol import mx28
from protocol.mx28 import ControlItem

if TYPE_CHECKING:
    from app.config import ArmProfile, JointConfig

#: Baud Rate (8) codes of the MX-28(2.0) and X series (e-manual, "Baud Rate(8)").
BAUD_RATES = {0: 9_600, 1: 57_600, 2: 115_200, 3: 1_000_000, 4: 2_000_000, 5: 3_000_000,
              6: 4_000_000, 7: 4_500_000}
#: The rate a servo ships at (e-manual: Baud Rate (8) initial value 1).
FACTORY_RATE = 57_600
#: The order a scan tries them: the factory rate first, then the project's, then the rest.
SCAN_ORDER = (57_600, 1_000_000, 115_200, 9_600, 2_000_000, 3_000_000, 4_000_000, 4_500_000)
#: Replies a broadcast PING waits for, at most (a bus of more: raise --timeout).
SCAN_SERVOS = 20
#: How long a servo already heard may take to answer, s, at least: spent only when one does
#: not. A real servo answers within a millisecond or two; a simulated bus on a loaded machine
#: answered after the 0.1 s broadcast window three times in one `make test-loaded` (session
#: 15), and the set-up reported "no reply". Longer is only a slower failure.
REPLY_TIMEOUT_S = 1.0
#: Model numbers (Model Number (0)) this tool knows by name.
MODELS = {30: "MX-28(2.0)", 1020: "XM430-W350", 1030: "XM430-W210"}
#: The exit codes of `armserver setup-servos`.
EXIT_OK, EXIT_NONE, EXIT_SEVERAL, EXIT_REFUSED, EXIT_VERIFY = 0, 3, 4, 5, 6

_T = mx28.TABLE


#: What a SetupError is, for a caller that answers it (the dashboard's routes map each to an
#: error code of app/errors.py), by exit code unless the raise site says otherwise.
KIND_BY_EXIT = {EXIT_NONE: "no_servo", EXIT_SEVERAL: "several_servos", EXIT_REFUSED: "invalid",
                EXIT_VERIFY: "device"}


class SetupError(Exception):
    """Set-up refused or failed: `reason` for the user, `exit_code` for the shell, `kind` for a
    program: no_servo, several_servos, id_in_use, torque_on, invalid (the profile or the
    request), device (an error status or a value that does not read back), no_reply."""

    def __init__(self, reason: str, exit_code: int, kind: str | None = None) -> None:
        super().__init__(reason)
        self.reason = reason
        self.exit_code = exit_code
        self.kind = kind or KIND_BY_EXIT.get(exit_code, "device")


@dataclass(frozen=True)
class Found:
    """One servo that answered: its ID, the rate it was heard at (its Baud Rate item's), its
    model and firmware, Torque Enable and Operating Mode."""

    id: int
    baudrate: int
    model: int
    firmware: int
    torque: bool
    mode: int

    def describe(self) -> str:
        name = MODELS.get(self.model, f"model {self.model}")
        return (f"ID {self.id} at {self.baudrate:,} bps: {name}, firmware {self.firmware}, "
                f"operating mode {self.mode}, torque {'on' if self.torque else 'off'}")


@dataclass
class Scan:
    """What a scan heard: the servos, and the rates where replies collided."""

    found: list[Found] = field(default_factory=list)
    collisions: list[str] = field(default_factory=list)
    #: Rates where only bytes that were no packet came: a UART at another rate than a
    #: servo's reads its replies so (app/sim/uart.py); told, not refused.
    garbled: list[str] = field(default_factory=list)
    #: Times the standard rates were tried: 2 when the first pass heard nothing at all (`scan`).
    passes: int = 1


def carries_baud(url: str) -> bool:
    """Whether the port's baud rate reaches the bus (not over a socket)."""
    return not url.startswith(("socket://", "loop://"))


class Bus:
    """A blocking Protocol 2.0 exchange on one pyserial port."""

    def __init__(self, url: str, baudrate: int = 57_600, timeout: float = 0.1,
                 opener: Callable[..., Any] | None = None) -> None:
        """`timeout`: how long a broadcast waits for answers; a servo already heard may take
        that long to answer, REPLY_TIMEOUT_S at least (`reply_timeout`: only spent on a
        failure)."""
        if opener is None:
            import serial

            opener = serial.serial_for_url
        self.url = url
        self.timeout = timeout
        self.reply_timeout = max(timeout, REPLY_TIMEOUT_S)
        #: Bytes skipped as no packet's, counted (garbled answers, told apart from silence).
        self.garbage = 0
        self.port = opener(url, baudrate=baudrate, timeout=0.005, exclusive=True) \
            if carries_baud(url) else opener(url, baudrate=baudrate, timeout=0.005)
        # (a terminal: the server's raised threads at 0 meanwhile, app/runtime/control_thread.py)
        self._terminal = terminal_hold(port_fileno(self.port))

    def close(self) -> None:
        try:
            self.port.close()
        finally:
            if self._terminal is not None:
                self._terminal.release()

    def set_rate(self, baudrate: int) -> None:
        self.port.baudrate = baudrate
        self.drain()

    def drain(self) -> None:
        self.port.reset_input_buffer()
        end = time.monotonic() + 0.01
        while time.monotonic() < end:
            if not self.port.read(4096):
                break

    def _events(self, end: float) -> Iterator[dxl.Packet | dxl.ParseError]:
        """The packets and framing errors the port gives until `end` (garbage counted in
        `garbage`, not given). One read begins after `end`: what came before it is read even
        where this thread was held up past it (a busy machine), not dropped with the buffer."""
        parser = dxl.Parser()
        past = False
        while not past:
            past = time.monotonic() >= end
            data = self.port.read(4096)
            if data:
                parser.feed(data)
            while (ev := parser.next_event()) is not None:
                if isinstance(ev, dxl.ParseError) and ev.kind == "garbage":
                    self.garbage += 1
                else:
                    yield ev

    def exchange(self, packet: bytes, window: float | None = None
                 ) -> tuple[list[dxl.Packet], list[dxl.ParseError]]:
        """Send `packet`; every status packet and framing error seen within `window`."""
        self.port.reset_input_buffer()
        self.port.write(packet)
        got: list[dxl.Packet] = []
        errors: list[dxl.ParseError] = []
        end = time.monotonic() + (self.timeout if window is None else window)
        for ev in self._events(end):
            if isinstance(ev, dxl.ParseError):
                errors.append(ev)
            elif ev.instruction == dxl.Instruction.STATUS:
                got.append(ev)
        return got, errors

    def one(self, packet: bytes, dxl_id: int, what: str) -> dxl.Packet:
        """The status of servo `dxl_id` to `packet`; SetupError if none, garbled or an error.
        A status of another size than `packet`'s (`dxl.status_params`: a READ's item, 0 for a
        WRITE, 3 for a PING) without an error is a late answer to an earlier request
        (Protocol 2.0's status names no instruction), skipped, not taken for this one's."""
        size = dxl.status_params(packet)
        deadline = time.monotonic() + self.reply_timeout
        got: list[dxl.Packet] = []
        errors: list[dxl.ParseError] = []
        self.port.reset_input_buffer()
        self.port.write(packet)
        garbage = self.garbage
        for ev in self._events(deadline):
            if isinstance(ev, dxl.ParseError):
                errors.append(ev)
            elif (ev.instruction == dxl.Instruction.STATUS and ev.id == dxl_id
                  and (len(ev.params) == size or ev.error)):
                got.append(ev)
                break
        if not got:
            why = (f"garbled replies ({errors[0].kind}): two servos on ID {dxl_id}?"
                   if errors else f"garbled answers at {self.port.baudrate:,} bps: a servo at "
                   "another rate?" if self.garbage > garbage else "no reply")
            raise SetupError(f"{what}: servo {dxl_id}: {why}", EXIT_VERIFY,
                             "device" if errors else "no_reply")
        p = got[0]
        if (p.error or 0) & ~dxl.ALERT_BIT:
            raise SetupError(f"{what}: servo {dxl_id}: {dxl.describe_error(p.error or 0)}",
                             EXIT_REFUSED, "device")
        return p

    def read(self, dxl_id: int, item: ControlItem) -> int:
        p = self.one(dxl.read(dxl_id, item.address, item.size), dxl_id, f"READ {item.name}")
        if len(p.params) != item.size:
            raise SetupError(f"READ {item.name}: servo {dxl_id} answered {len(p.params)} "
                             f"bytes, expected {item.size}", EXIT_VERIFY)
        return dxl.from_bytes(p.params, item.signed)

    def write(self, dxl_id: int, item: ControlItem, value: int) -> None:
        self.one(dxl.write(dxl_id, item.address, dxl.to_bytes(value, item.size)), dxl_id,
                 f"WRITE {item.name} = {value}")


def scan(bus: Bus, rates: Iterable[int] = SCAN_ORDER) -> Scan:
    """Broadcast PING at each rate (once over a socket); each servo heard is read (Baud Rate,
    Torque Enable, Operating Mode). Collisions are noted, not raised. Where a pass heard
    nothing at all, a second one: a busy PC's kernel can hand a serial adapter's (or a pty's)
    bytes over later than the window (its worker held off the CPU: docs/performance.md
    "Session 24"), and a servo that is there should not read as absent for it; an empty bus
    costs twice the time."""
    tried = _tried(bus, rates)
    out = Scan()
    _scan_pass(bus, tried, out)
    if not (out.found or out.collisions or out.garbled):
        out.passes = 2
        _scan_pass(bus, tried, out)
    return out


def scan_again(bus: Bus, rates: Iterable[int], first: Scan) -> Scan:
    """A second pass over the rates after a `first` one that heard something: what both
    heard (a servo heard twice once)."""
    out = Scan(list(first.found), list(first.collisions), list(first.garbled), passes=2)
    _scan_pass(bus, _tried(bus, rates), out)
    out.collisions = list(dict.fromkeys(out.collisions))  # (a note heard twice, once)
    out.garbled = list(dict.fromkeys(out.garbled))
    return out


def _tried(bus: Bus, rates: Iterable[int]) -> list[int | None]:
    """The rates a pass tries: each of `rates`, or once over a socket (no baud rate)."""
    return list(rates) if carries_baud(bus.url) else [None]


def _scan_pass(bus: Bus, rates: list[int | None], out: Scan) -> None:
    """One broadcast PING at each of `rates`; what it hears is added to `out` (a servo
    `out` holds already, at its rate, once)."""
    seen = {(f.id, f.baudrate) for f in out.found}
    for rate in rates:
        if rate is not None:
            bus.set_rate(rate)
        where = f"{rate:,} bps" if rate is not None else "the socket"
        # every reply of up to SCAN_SERVOS servos, 14 bytes of 10 bits each, after the timeout
        window = bus.timeout + SCAN_SERVOS * 14 * 10 / (rate or 1_000_000)
        garbage = bus.garbage
        packets, errors = bus.exchange(dxl.ping(dxl.BROADCAST_ID), window)
        if not packets and not errors and bus.garbage > garbage:
            out.garbled.append(f"garbled answers at {where}: a UART at another rate than a "
                               "servo's reads its replies as garbage (the scan tries the others)")
        if errors:
            out.collisions.append(f"garbled replies at {where} ({errors[0].kind}): two servos "
                                  "on one ID answer at once")
        for p in sorted(packets, key=lambda p: p.id):
            if len(p.params) != 3:
                continue
            try:
                code = bus.read(p.id, _T["baud_rate"])
                torque = bus.read(p.id, _T["torque_enable"])
                mode = bus.read(p.id, _T["operating_mode"])
            except SetupError as exc:
                out.collisions.append(f"at {where}: {exc.reason}")
                continue
            heard = BAUD_RATES.get(code, rate or 0)
            if (p.id, heard) in seen:
                continue
            seen.add((p.id, heard))
            out.found.append(Found(p.id, heard, dxl.from_bytes(p.params[0:2], False),
                                   p.params[2], bool(torque), mode))


def _joint(profile: ArmProfile, name: str) -> tuple[int, JointConfig]:
    for k, j in enumerate(profile.joints):
        if j.name == name:
            return k, j
    names = ", ".join(j.name for j in profile.joints)
    raise SetupError(f"profile {profile.name} has no joint {name!r} (its joints: {names})",
                     EXIT_REFUSED)


def wanted(profile: ArmProfile, name: str) -> dict[str, int]:
    """The EEPROM items joint `name`'s servo gets, by control-table name: ID, Baud Rate, Return
    Delay Time (the link's), Operating Mode, and in position mode (3) Min/Max Position Limit
    from the joint's limits (the servo refuses goals outside them; extended position mode
    ignores them, e-manual "Min/Max Position Limit(52, 48)")."""
    k, j = _joint(profile, name)
    if j.motor_id is None:
        raise SetupError(f"joint {name} has no motor_id in profile {profile.name}", EXIT_REFUSED)
    shared = [o.name for o in profile.joints if o.name != name and o.motor_id == j.motor_id]
    if shared:
        raise SetupError(f"ID {j.motor_id} is in use by joint {shared[0]} in profile "
                         f"{profile.name}: two servos on one ID would collide; give joint "
                         f"{name} its own motor_id", EXIT_REFUSED, "id_in_use")
    codes = [c for c, r in BAUD_RATES.items() if r == profile.link.baudrate]
    if not codes:
        raise SetupError(f"profile {profile.name}: link.baudrate {profile.link.baudrate} is "
                         f"not a Dynamixel rate {sorted(BAUD_RATES.values())}", EXIT_REFUSED)
    out = {"id": int(j.motor_id), "baud_rate": codes[0]}
    if profile.link.return_delay_us is not None:
        out["return_delay_time"] = round(profile.link.return_delay_us / 2.0)
    mode = j.operating_mode if j.operating_mode is not None else 3
    out["operating_mode"] = mode
    if mode == 3:
        from app.arms import model_for

        tr = model_for(profile).transmission
        lo = [0.0] * len(profile.joints)
        hi = [0.0] * len(profile.joints)
        lo[k], hi[k] = j.min, j.max
        a, b = float(tr.to_ticks(lo)[k]), float(tr.to_ticks(hi)[k])
        low, high = math.floor(min(a, b)), math.ceil(max(a, b))
        if low < 0 or high > mx28.TICKS_PER_REV - 1:
            raise SetupError(f"joint {name}: its limits are ticks {low}..{high}, outside one "
                             "turn (0..4095): position mode (3) cannot take them; use extended "
                             "position mode (4)", EXIT_REFUSED)
        out["min_position_limit"], out["max_position_limit"] = low, high
    return out


def others_in_place(profile: ArmProfile, joint: str, found: list[Found]) -> dict[int, str]:
    """Found servos that already are another joint's (its ID at the profile's rate)."""
    ids = {int(j.motor_id): j.name for j in profile.joints
           if j.motor_id is not None and j.name != joint}
    return {f.id: ids[f.id] for f in found
            if f.id in ids and f.baudrate == profile.link.baudrate}


def _to_set_up(profile: ArmProfile, joint: str, result: Scan) -> tuple[dict[int, str],
                                                                       list[Found]]:
    """The found servos that are other joints' (in place), and those left to set up."""
    placed = others_in_place(profile, joint, result.found)
    return placed, [f for f in result.found
                    if f.id not in placed or f.baudrate != profile.link.baudrate]


def set_up_joint(url: str, profile: ArmProfile, joint: str, *, timeout: float = 0.1,
                 rates: Iterable[int] = SCAN_ORDER, say: Callable[[str], None] = print,
                 opener: Callable[..., Any] | None = None) -> Found:
    """Find the one servo on the bus that is not another joint's (its ID at the profile's
    rate: never touched), give it `joint`'s ID, baud rate, operating mode and limits (EEPROM,
    torque off) and verify them. SetupError with the reason and exit code when there is no
    such servo, several (two on the joint's ID among them), a collision (two on one ID at one
    rate), a servo with torque on, or a value that does not read back."""
    want = wanted(profile, joint)
    bus = Bus(url, timeout=timeout, opener=opener)
    try:
        rates = list(rates)
        result = scan(bus, rates)
        placed, todo = _to_set_up(profile, joint, result)
        if not todo and result.found and not result.collisions and result.passes == 1:
            # Only servos already set up answered. A busy PC's port can hand a new servo's
            # replies over after its rate's window (`scan` passes again only where it heard
            # nothing at all): once more before saying there is none to set up.
            result = scan_again(bus, rates, result)
            placed, todo = _to_set_up(profile, joint, result)
        for f in result.found:
            say(f"found {f.describe()}")
        if result.collisions:
            raise SetupError("; ".join(result.collisions) + ": connect one servo at a time "
                             "(each new one alone with the ones already set up)", EXIT_SEVERAL)
        if not todo:
            what = ", ".join(f"ID {i} ({n})" for i, n in sorted(placed.items()))
            raise SetupError("no servo to set up" + (f": only {what}, already set up"
                             if what else ": nothing answered at any standard rate (check "
                             "power, the cable and the adapter)"), EXIT_NONE)
        if len(todo) > 1:
            listed = "; ".join(f.describe() for f in todo)
            raise SetupError(f"{len(todo)} servos to set up ({listed}): connect only the one "
                             f"for joint {joint}", EXIT_SEVERAL)
        # Another servo on the joint's ID at the profile's rate would be a second candidate
        # (refused above as several); another joint's servo is never a candidate.
        servo = todo[0]
        if servo.torque:
            raise SetupError(f"servo ID {servo.id} has torque on: EEPROM items are written "
                             "only with torque off; power-cycle it (torque is off at power-up)",
                             EXIT_REFUSED, "torque_on")
        if carries_baud(url):
            bus.set_rate(servo.baudrate)
        for name in ("operating_mode", "return_delay_time", "min_position_limit",
                     "max_position_limit"):
            if name in want and bus.read(servo.id, _T[name]) != want[name]:
                bus.write(servo.id, _T[name], want[name])
        dxl_id = servo.id
        if dxl_id != want["id"]:
            bus.exchange(dxl.write(dxl_id, _T["id"].address, bytes((want["id"],))))
            dxl_id = want["id"]
            bus.one(dxl.ping(dxl_id), dxl_id, f"PING at the new ID {dxl_id}")
        rate = BAUD_RATES[want["baud_rate"]]
        if servo.baudrate != rate:
            # The port moves to the new rate only once the servo has read this WRITE: its
            # status, at the rate the servo read the WRITE at, or the reply timeout (as
            # ROBOTIS's Dynamixel2Arduino, whose `setBaudrate` is a WRITE that waits for its
            # status before `begin(new_rate)`). A broadcast's window was too short for a
            # bus that read the WRITE late: it read it at the new rate, as noise.
            code = want["baud_rate"]
            try:
                bus.one(dxl.write(dxl_id, _T["baud_rate"].address, bytes((code,))), dxl_id,
                        f"WRITE baud_rate = {code}")
            except SetupError as exc:
                if exc.kind != "no_reply":  # (silence: verified at the new rate below)
                    raise
            if carries_baud(url):
                bus.set_rate(rate)
        for name, value in want.items():
            got = bus.read(dxl_id, _T[name])
            if got != value:
                raise SetupError(f"verify: servo {dxl_id} {name} reads {got}, wanted {value}",
                                 EXIT_VERIFY)
        done = Found(dxl_id, rate, servo.model, servo.firmware, False, want["operating_mode"])
        say(f"joint {joint}: set up and verified: {done.describe()}")
        return done
    finally:
        bus.close()


def scan_port(url: str, *, timeout: float = 0.1, rates: Iterable[int] = SCAN_ORDER,
              opener: Callable[..., Any] | None = None) -> Scan:
    """Open `url`, scan it (`scan`) and close it. A listing is scanned twice in any case (a
    pass that heard one servo can have missed another whose replies a busy PC's port handed
    over late: `scan_again`); the listing is what a student sets up from, and a second
    scan is a second or so more."""
    bus = Bus(url, timeout=timeout, opener=opener)
    try:
        rates = list(rates)
        result = scan(bus, rates)
        return result if result.passes > 1 else scan_again(bus, rates, result)
    finally:
        bus.close()


def placement(profile: ArmProfile | None, f: Found) -> tuple[str | None, str]:
    """Whose a found servo is against the profile: (the joint whose ID and rate it has, or
    None; a note for the user: "= joint y", "joint y's ID, but not the profile's ...",
    "[factory state]")."""
    joints = {} if profile is None else {int(j.motor_id): j.name for j in profile.joints
                                         if j.motor_id is not None}
    joint, note = None, ""
    if profile is not None and f.id in joints:
        if f.baudrate == profile.link.baudrate:
            joint, note = joints[f.id], f"= joint {joints[f.id]}"
        else:
            note = (f"(joint {joints[f.id]}'s ID, but not the profile's "
                    f"{profile.link.baudrate:,} bps)")
    if f.id == 1 and f.baudrate == FACTORY_RATE:
        note = f"{note} [factory state]".strip()
    return joint, note


def report(url: str, profile: ArmProfile | None, *, timeout: float = 0.1,
           rates: Iterable[int] = SCAN_ORDER, say: Callable[[str], None] = print,
           opener: Callable[..., Any] | None = None) -> Scan:
    """Scan and print what answered, and against the profile, whose each servo is."""
    result = scan_port(url, timeout=timeout, rates=rates, opener=opener)
    for f in result.found:
        note = placement(profile, f)[1]
        say(f"found {f.describe()}{' ' + note if note else ''}")
    for c in [*result.garbled, *result.collisions]:
        say(c)
    return result
