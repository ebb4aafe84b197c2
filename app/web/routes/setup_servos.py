"""Servo set-up from the factory state in the dashboard (issue 24): the same set-up as
`armserver setup-servos` (app/arms/dynamixel/setup.py: the scan, one servo at a time, the
refusals; nothing of it is repeated here), as routes, and a practice bus to try it on.

- `GET /setup-servos`: the profiles a set-up can follow, the ports the server's arms own, the
  practice bus (any viewer).
- `POST /setup-servos/scan` {port, profile, baudrates?}: what answers on the port, and whose
  each servo is against the profile (instructor: the port is opened exclusively).
- `POST /setup-servos/assign` {port, profile, joint, baudrates?}: the one servo on the port
  that is not another joint's gets the joint's ID, baud rate, operating mode and limits
  (EEPROM, torque off), read back (instructor: it writes EEPROM).
- `POST /setup-servos/practice` {servos}, `POST /setup-servos/practice/servos`,
  `DELETE /setup-servos/practice`: a factory-state simulated bus on a pseudo-terminal
  (app/arms/dynamixel/practice.py says why the server serves it, and why not on a socket), one
  more servo plugged in, and stopped (instructor).

A port an arm of this server owns is refused with 409 `port_in_use` naming the arm: the server
owns each link and nothing else touches it; a port another program holds (a link opens its
port exclusively, as the set-up does) is 409 `port_in_use` too. The set-up's refusals keep
their reasons: 409 `no_servo`, `several_servos`, `id_in_use`, `conflict` (a servo with
torque on), 422 `invalid_request` (the profile cannot be set up so, or the port cannot be
opened), 502 `device_error` / 504 `device_timeout` (a servo that answers wrongly or not at all
mid-way).
One set-up at a time (409 `busy`); each runs on a worker thread (blocking pyserial), never on
the HTTP loop. Under `--workers` this runs on the first worker, which knows its own arms' ports
by name; another worker's is refused by its exclusive lock.
"""

from __future__ import annotations

import asyncio
import os
import re
import stat
from typing import Any, cast
from urllib.parse import urlsplit

from fastapi import APIRouter, Request

from app import schemas as s
from app.arms import arm_type, builtin_profiles
from app.arms.dynamixel import practice, setup
from app.arms.loading import load_profile
from app.config import ArmProfile, ConfigError
from app.errors import (
    ArmError,
    Busy,
    Conflict,
    DeviceError,
    DeviceTimeout,
    IdInUse,
    InvalidRequest,
    NoServo,
    PortInUse,
    SeveralServos,
)
from app.service import ArmService
from app.web.deps import InstructorRole, ViewerRole
from app.web.routes.common import errors

router = APIRouter(prefix="/setup-servos", tags=["servo set-up"])

#: How long a broadcast PING waits for answers at each rate, s, unless the request says: three
#: times the CLI's default, as a server shares its cores with the arms it serves (a full scan
#: of the eight rates then takes about 3 s).
TIMEOUT_S = 0.3
_LOOPBACK = {"127.0.0.1", "localhost", "::1"}
_KIND: dict[str, type[ArmError]] = {
    "no_servo": NoServo, "several_servos": SeveralServos, "id_in_use": IdInUse,
    "torque_on": Conflict, "invalid": InvalidRequest, "device": DeviceError,
    "no_reply": DeviceTimeout,
}
#: The refusals a set-up route may answer.
_SETUP_ERRORS = errors(401, 403, 409, 422, 502, 504, extra={
    409: "`port_in_use`: an arm of this server owns the port; `no_servo`, `several_servos`, "
    "`id_in_use`: the set-up's refusals; `conflict`: a servo with torque on; `busy`: another "
    "set-up runs"})


def _services(request: Request) -> dict[str, ArmService]:
    return cast("dict[str, ArmService]", request.app.state.services)


def _practice(request: Request) -> practice.PracticeBus | None:
    return cast("practice.PracticeBus | None", getattr(request.app.state, "practice_bus", None))


def _lock(request: Request, name: str = "setup_lock") -> asyncio.Lock:
    """The app's lock of that name (one set-up at a time; one change of the practice bus)."""
    lock = getattr(request.app.state, name, None)
    if lock is None:
        lock = asyncio.Lock()
        setattr(request.app.state, name, lock)
    return cast(asyncio.Lock, lock)


#: What a serial port's device is, its symlinks followed: a USB adapter (/dev/ttyUSB0, the
#: U2D2), a board's UART (/dev/ttyS0, /dev/ttyAMA0), a pseudo-terminal (a simulator's).
_SERIAL_DEVICE = re.compile(r"^/dev/(tty[A-Za-z]+[0-9]+|pts/[0-9]+|cu\.[^/]+|rfcomm[0-9]+)$")


def _socket_address(port: str) -> tuple[str, int] | None:
    """(host, port) of a `socket://HOST:PORT` URL, or None when it is not one."""
    u = urlsplit(port)
    try:
        number = u.port
    except ValueError:
        return None
    if u.scheme != "socket" or not u.hostname or not number or u.path or u.query:
        return None
    return u.hostname, number


def _same_port(a: str, b: str) -> bool:
    """Whether two port names are one port: a device path through its symlinks
    (/dev/serial/by-id/... is /dev/ttyUSB0), a socket URL by host and port."""
    if a.startswith("/") and b.startswith("/"):
        return os.path.realpath(a) == os.path.realpath(b)
    sa, sb = _socket_address(a), _socket_address(b)
    return sa is not None and sa == sb


def _own_terminals() -> set[str]:
    out = set()
    for fd in (0, 1, 2):
        try:
            out.add(os.path.realpath(os.ttyname(fd)))
        except OSError:
            continue
    return out


def _owned(services: dict[str, ArmService]) -> dict[str, str]:
    """Port -> the arm whose link it is (serial links: a HID or simulated link has no port)."""
    return {svc.profile.link.address: name for name, svc in services.items()
            if svc.profile.link.kind == "serial" and svc.profile.link.address}


def _check_port(port: str, services: dict[str, ArmService]) -> None:
    """409 for an arm's port; 422 for a port that is neither a serial device nor loopback."""
    for link, arm in _owned(services).items():
        if _same_port(port, link):
            raise PortInUse(f"{port} is the link of arm {arm}: the server owns it and nothing "
                            "else touches it (set its servos up with the server stopped, or "
                            "on another port)")
    if port.startswith("socket://"):
        address = _socket_address(port)
        if address is None or address[0] not in _LOOPBACK:
            raise InvalidRequest(f"{port}: a socket port is socket://127.0.0.1:PORT, on this "
                                 "machine's loopback: the server opens no connection elsewhere")
        return
    try:
        mode = os.stat(port).st_mode
    except (OSError, ValueError) as exc:
        raise InvalidRequest(f"no port {port}: {getattr(exc, 'strerror', None) or exc}"
                             ) from None
    device = os.path.realpath(port)
    if not stat.S_ISCHR(mode) or not _SERIAL_DEVICE.match(device):
        raise InvalidRequest(f"{port} is not a serial device (/dev/ttyUSB0, /dev/ttyACM0, "
                             "/dev/serial/by-id/..., a pseudo-terminal)")
    if device in _own_terminals():
        raise InvalidRequest(f"{port} is the server's own terminal")


def _candidates(services: dict[str, ArmService]) -> dict[str, ArmProfile]:
    """Profiles a set-up can follow by name: the hosted arms' first, then the built-in ones;
    of Dynamixel arms only."""
    out = {svc.profile.name: svc.profile for svc in services.values()}
    for stem in builtin_profiles():
        try:
            p = load_profile(stem)
        except ConfigError:
            continue
        out.setdefault(p.name, p)
    return {n: p for n, p in out.items() if arm_type(p.model).protocol == "dynamixel"}


def _profile(name: str, services: dict[str, ArmService]) -> ArmProfile:
    candidates = _candidates(services)
    if name not in candidates:
        raise InvalidRequest(f"no profile {name!r} of an arm of Dynamixel servos: the profiles "
                             f"a set-up can follow are {', '.join(candidates) or 'none'}")
    return candidates[name]


def _checked(request: Request, req: s.ServoScanRequest) -> ArmProfile:
    """The request's profile, once its port is known to be no arm's of this server."""
    services = _services(request)
    _check_port(req.port, services)
    return _profile(req.profile, services)


def _found(profile: ArmProfile, f: setup.Found) -> s.FoundServo:
    joint, note = setup.placement(profile, f)
    return s.FoundServo(id=f.id, baudrate=f.baudrate, model=f.model,
                        model_name=setup.MODELS.get(f.model, f"model {f.model}"),
                        firmware=f.firmware, torque=f.torque, mode=f.mode, joint=joint,
                        factory=f.id == 1 and f.baudrate == setup.FACTORY_RATE, note=note)


def _rates(req: s.ServoScanRequest) -> tuple[int, ...]:
    return tuple(req.baudrates) if req.baudrates else setup.SCAN_ORDER


def _timeout(req: s.ServoScanRequest) -> float:
    """The broadcast's window (a servo heard has setup.REPLY_TIMEOUT_S at least)."""
    return req.timeout or TIMEOUT_S


async def _run_setup(request: Request, fn: Any, *args: Any, **kw: Any) -> Any:
    """One set-up at a time, on a worker thread; its SetupError as the table's error."""
    lock = _lock(request)
    if lock.locked():
        raise Busy("another servo set-up runs: try again when it ends")
    async with lock:
        try:
            return await asyncio.to_thread(fn, *args, **kw)
        except setup.SetupError as exc:
            raise _KIND.get(exc.kind, DeviceError)(exc.reason) from None
        except OSError as exc:  # pyserial's SerialException is an OSError
            if "exclusively lock" in str(exc):  # serialposix: another program holds it
                raise PortInUse(f"{args[0]} is held by another program (an arm's link on "
                                "another worker or server, a terminal): nothing else touches "
                                "a port in use") from None
            raise InvalidRequest(f"cannot open {args[0]}: {exc}") from None


def _practice_body(bus: practice.PracticeBus | None) -> s.PracticeBus:
    if bus is None:
        return s.PracticeBus(running=False, port=None, servos=[])
    return s.PracticeBus(running=True, port=bus.port,
                         servos=[s.PracticeServo(id=p.id, baudrate=p.baudrate)
                                 for p in bus.servos()])


@router.get(
    "",
    response_model=s.ServoSetupInfo,
    summary="What servo set-up can do here",
    description="The profiles of Dynamixel arms a set-up can follow, the ports this server's "
    "arms own (never scanned nor written), and the practice bus.",
    responses=errors(401, 422),
)
async def setup_info(request: Request, _: ViewerRole) -> s.ServoSetupInfo:
    services = _services(request)
    async with _lock(request, "practice_lock"):
        body = await asyncio.to_thread(_practice_body, _practice(request))
    return s.ServoSetupInfo(profiles=list(_candidates(services)),
                            ports_in_use=_owned(services), practice=body)


@router.post(
    "/scan",
    response_model=s.ServoScan,
    summary="Find the servos on a port",
    description="Broadcast PING at each rate (once over a socket), each servo's Baud Rate, "
    "Torque Enable and Operating Mode read, and whose it is against the profile; every rate a "
    "second time, each servo listed once (a busy PC can hand one rate's replies over late). Writes "
    "nothing. Instructor (the port is opened exclusively).",
    responses=_SETUP_ERRORS,
)
async def scan_servos(request: Request, req: s.ServoScanRequest,
                      _: InstructorRole) -> s.ServoScan:
    profile = _checked(request, req)
    result: setup.Scan = await _run_setup(request, setup.scan_port, req.port,
                                          rates=_rates(req), timeout=_timeout(req))
    servos = [_found(profile, f) for f in result.found]
    placed = {f.joint for f in servos if f.joint is not None}
    return s.ServoScan(port=req.port, profile=profile.name, servos=servos,
                       collisions=result.collisions, garbled=result.garbled,
                       joints={j.name: int(j.motor_id) for j in profile.joints
                               if j.motor_id is not None},
                       profile_baudrate=profile.link.baudrate,
                       todo=[j.name for j in profile.joints if j.name not in placed])


@router.post(
    "/assign",
    response_model=s.ServoAssigned,
    summary="Set up the one new servo on a port as a joint's",
    description="The one servo on the port that is not another joint's (its ID at the "
    "profile's rate: never touched) gets the joint's ID, baud rate, Return Delay Time, "
    "operating mode and, in position mode, its limits (EEPROM, torque off), then each is read "
    "back. Refused, with nothing written, when no servo or several answer, two collide on one "
    "ID, the servo's torque is on, or the profile gives the joint's ID to another. Instructor "
    "(it writes EEPROM).",
    responses=_SETUP_ERRORS,
)
async def assign_servo(request: Request, req: s.ServoAssignRequest,
                       _: InstructorRole) -> s.ServoAssigned:
    profile = _checked(request, req)
    said: list[str] = []
    done: setup.Found = await _run_setup(request, setup.set_up_joint, req.port, profile,
                                         req.joint, rates=_rates(req), say=said.append,
                                         timeout=_timeout(req))
    return s.ServoAssigned(port=req.port, profile=profile.name, joint=req.joint,
                           servo=_found(profile, done), said=said)


@router.post(
    "/practice",
    response_model=s.PracticeBus,
    summary="Start a practice bus of factory servos",
    description="A simulated Dynamixel bus in the factory state (every servo ID 1 at 57,600 "
    "bps) on a pseudo-terminal whose baud rate its servos honour, replacing any earlier one: "
    "a port to scan and set up without hardware. Instructor.",
    responses=errors(401, 403, 422),
)
async def start_practice(request: Request, req: s.PracticeBusRequest,
                         _: InstructorRole) -> s.PracticeBus:
    async with _lock(request, "practice_lock"):
        old = _practice(request)
        request.app.state.practice_bus = None
        if old is not None:
            await asyncio.to_thread(old.close)
        bus = await asyncio.to_thread(practice.PracticeBus, req.servos)
        request.app.state.practice_bus = bus
        return await asyncio.to_thread(_practice_body, bus)


@router.post(
    "/practice/servos",
    response_model=s.PracticeBus,
    summary="Plug one more factory servo into the practice bus",
    description="ID 1 at 57,600 bps, as shipped; 409 `conflict` with no practice bus running "
    f"or {practice.MAX_SERVOS} servos on it. Instructor.",
    responses=errors(401, 403, 409),
)
async def plug_practice_servo(request: Request, _: InstructorRole) -> s.PracticeBus:
    async with _lock(request, "practice_lock"):
        bus = _practice(request)
        if bus is None:
            raise Conflict("no practice bus runs: start one (POST /api/v1/setup-servos/practice)")
        try:
            await asyncio.to_thread(bus.plug)
        except ValueError as exc:
            raise Conflict(str(exc)) from None
        return await asyncio.to_thread(_practice_body, bus)


@router.delete(
    "/practice",
    response_model=s.PracticeBus,
    summary="Stop the practice bus",
    description="Its port closes; answers the bus as stopped (also when none ran). Instructor.",
    responses=errors(401, 403),
)
async def stop_practice(request: Request, _: InstructorRole) -> s.PracticeBus:
    async with _lock(request, "practice_lock"):
        bus = _practice(request)
        request.app.state.practice_bus = None
        if bus is not None:
            await asyncio.to_thread(bus.close)
    return _practice_body(None)
