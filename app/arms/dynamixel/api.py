"""Dynamixel Protocol 2.0 pass-through: ping, registers by control-table name, SYNC read and
write, reboot. Raw register values (`raw`), named by the arm's control table (its arm type's
`control_table`, e.g. protocol/mx28.py for the MX-28; the XM430's has the same layout). One
router for every Dynamixel arm type: it names none.

Every check happens before anything is sent: the name must be in the table (422
`unknown_register`), a write must be to a writable item (422 `read_only`) and within the item's
raw range (422 `out_of_range`), and a `goal_position` must be for one of the arm's motors; goal
positions, one or several, are then checked like a planned move from where the arm is, on the
control thread (`ArmService.command_passthrough`). Writes and reboots are refused while the
estop is latched, except the safe ones: torque off and the LED. Reads may name any id
(the bus may carry other servos).
"""

from __future__ import annotations

from collections.abc import Awaitable, Callable
from typing import Annotated, Any, NoReturn

from fastapi import APIRouter, Body, FastAPI, Path
from pydantic import ValidationError
from starlette.responses import Response
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from app import schemas as s
from app.arms import arm_type
from app.arms.dynamixel.exchange import DynamixelBusDriver
from app.arms.dynamixel.servos import DynamixelChainDriver
from app.errors import ArmError, InUse, OutOfRange, ReadOnly, UnknownId, UnknownRegister
from app.service import ArmService
from app.web.deps import ControlArm, bearer_credentials, check_control
from app.web.error_responses import arm_error_response
from app.web.routes.common import DEVICE, errors
from protocol import mx28

router = APIRouter(prefix="/arms/{arm}/dynamixel", tags=["dynamixel"])

DxlId = Annotated[int, Path(ge=0, le=252, description="Dynamixel id")]
RegName = Annotated[str, Path(max_length=64, description="control-table item, e.g. goal_position")]

_NOT_SUPPORTED = "409 `not_supported` on an arm that does not speak Dynamixel."


def _driver(svc: ArmService) -> DynamixelBusDriver:
    bus: type[DynamixelBusDriver] = DynamixelBusDriver  # type: ignore[type-abstract]  # isinstance
    return svc.protocol_driver("dynamixel", bus)


def _table(svc: ArmService) -> Any:
    """The arm's control table module (protocol/mx28.py's shape); the MX-28's by default."""
    return arm_type(svc.profile.model).control_table or mx28


def _item(svc: ArmService, name: str) -> mx28.ControlItem:
    try:
        item: mx28.ControlItem = _table(svc).item(name)
    except KeyError as exc:
        raise UnknownRegister(str(exc.args[0])) from None
    return item


def _joint_of(svc: ArmService, dxl_id: int) -> int:
    for k, j in enumerate(svc.profile.joints):
        if j.motor_id == dxl_id:
            return k
    ids = ", ".join(str(j.motor_id) for j in svc.profile.joints)
    raise UnknownId(f"id {dxl_id} is not a motor of {svc.name} (its ids: {ids}); "
                    "goal_position writes go only to the arm's own motors")


_PROFILE = "the arm profile's {what} (then restart the server)"
_REBOOT = "POST /api/v1/arms/{arm}/dynamixel/{id}/reboot, which sets the servo up again"
_RAW = "an arm profile with raw_access = true, its owner's choice (then restart the server)"
#: Goal PWM (and an X-series servo's Goal Current) in a position mode: the e-manual's Goal
#: PWM(100), "in other control modes, this value is used to limit PWM value". Set to 0 during
#: a planned move of the angler's z and back to 885, the simulated winch caught up at 0.127 m/s
#: against its 0.05 m/s limit (tests/test_api_passthrough.py).
_FORCE = ("it limits the force the servo drives and holds with: lowered, the joint lags its "
          "planned path (a joint under gravity falls), and raised again it catches up faster "
          "than any plan", "none: the driver leaves it at the servo's limit; " + _RAW)
_FORCE_LIMIT = ("it caps Goal PWM or Goal Current, the force the servo drives and holds with",
                "none: the driver leaves it at the servo's default; " + _RAW)
_GAIN = ("it sets how closely the joint follows the planned path: lowered, the joint lags it (a "
         "joint under gravity sags) and catches up faster than any plan once raised; raised, "
         "it overshoots", _RAW)
#: Items the driver relies on for the arm's own servos, each with why and with the route (or
#: the profile setting) that changes it properly: how the driver addresses the servos, at what
#: speed and protocol they answer, how a goal is read, and every limit and profile it sets so
#: that a servo cannot outrun the planned trajectory (`profile_velocity` 32767 removed the
#: speed cap). Writing one through pass-through is 409 `in_use` unless the profile allows raw
#: access.
DRIVER_SETTINGS: dict[str, tuple[str, str]] = {
    "id": ("the driver addresses the servo by it", _PROFILE.format(what="joints.motor_id")),
    "secondary_id": ("a shared id would answer for several servos",
                     _PROFILE.format(what="joints.motor_id")),
    "baud_rate": ("the link runs at one rate", _PROFILE.format(what="link.baudrate")),
    "protocol_version": ("the driver speaks Protocol 2.0", "none: the driver needs 2.0"),
    "status_return_level": ("the driver needs a reply to every instruction",
                            "none: the driver needs level 2"),
    "return_delay_time": ("replies must come within the link timeout",
                          _PROFILE.format(what="link.timeout_s")),
    "operating_mode": ("the driver commands positions in the profile's mode", _REBOOT),
    "drive_mode": ("direction and profile type are the driver's",
                   _PROFILE.format(what="joints.sign")),
    "homing_offset": ("joint positions are read through it", "POST /api/v1/arms/{arm}/home"),
    "velocity_limit": ("it bounds the joint's speed",
                       _PROFILE.format(what="joints.max_velocity")),
    "acceleration_limit": ("it bounds the joint's acceleration",
                           _PROFILE.format(what="joints.max_acceleration")),
    "max_position_limit": ("it keeps the joint within its range",
                           _PROFILE.format(what="joints.max")),
    "min_position_limit": ("it keeps the joint within its range",
                           _PROFILE.format(what="joints.min")),
    "profile_velocity": ("it caps the servo's speed at the joint's velocity limit",
                         "the move routes' `speed` and `duration` (POST /api/v1/arms/{arm}/"
                         "move/joints)"),
    "profile_acceleration": ("it caps the servo's acceleration",
                             "the move routes' `speed` and `duration` (POST /api/v1/arms/"
                             "{arm}/move/joints)"),
    "shutdown": ("it says which faults turn the torque off to protect the servo", _REBOOT),
    **dict.fromkeys(("goal_pwm", "goal_current"), _FORCE),
    **dict.fromkeys(("pwm_limit", "current_limit"), _FORCE_LIMIT),
    **dict.fromkeys(("position_p_gain", "position_i_gain", "position_d_gain",
                     "velocity_p_gain", "velocity_i_gain", "feedforward_1st_gain",
                     "feedforward_2nd_gain"), _GAIN),
}


#: Why torque on is not a pass-through write to the arm's own servos (torque off is: the
#: README's homing by hand): a servo in a position mode may drive to its Goal Position as its
#: torque comes on (the e-manual does not say it does not; `DynamixelChainDriver.set_torque`
#: writes the present position there first), and after a hand or gravity moved the joint that
#: goal is an older one. With raw access the write goes through, after that same goal
#: (`ArmService.torque_on_holding`). The server's
#: record of what the arm was told (its last command) would not know of that move nor of the
#: position the joint comes to hold: the next planned move started from that last command and
#: drove the arm back towards it first, a path no check had seen (tests/test_api_passthrough.py).
#: The torque route (`PUT /arms/{arm}/torque`, `ArmService.set_torque`) and a servo's reboot
#: set the servos up to hold where they are and note it. As a DRIVER_SETTINGS entry, for
#: `torque_enable` 1 only.
TORQUE_ON = ("it goes off through pass-through, on again only as the driver sets the servo up: "
             "as torque comes on, a servo in a position mode may drive to its Goal Position, an "
             "older goal than where a hand or gravity left the joint, and the server's record "
             "of what the arm was told would not know of either",
             'PUT /api/v1/arms/{arm}/torque {{"on": true}}, which holds every joint where it '
             "is, or " + _REBOOT)


def _check_write(svc: ArmService, item: mx28.ControlItem, dxl_id: int, raw: int) -> None:
    """Everything a write must pass before it is queued."""
    if not item.writable:
        raise ReadOnly(f"{item.name} is read-only")
    if not item.min_raw <= raw <= item.max_raw:
        raise OutOfRange(f"{item.name} takes raw values {item.min_raw}..{item.max_raw}, "
                         f"got {raw}")
    # (the arm's own ids are looked up once, and only for the items that need them: a goal,
    # the pass-through's hot write, needs none of these)
    guarded = not svc.profile.raw_access
    ids = (_own_ids(svc) if guarded and (item.name in DRIVER_SETTINGS
                                         or item.name == "torque_enable") else {})
    if item.name in DRIVER_SETTINGS and dxl_id in ids:
        _in_use(svc, item, dxl_id, DRIVER_SETTINGS[item.name])  # (a gripper's servo too)
    if item.name in ("id", "secondary_id") and raw in ids:
        raise InUse(f"{item.name} {raw} of servo {dxl_id}: {raw} is the id of {svc.name}'s "
                    f"servo for {ids[raw]}; a second servo answering to it would take the arm's "
                    "commands (and, as its id, collide with its replies). Pass-through may not "
                    "give it: the profile does not allow raw access")
    if item.name == "goal_position":
        _joint_of(svc, dxl_id)  # checked with the others' goals: `_send`
    elif not _safe(item, raw):
        svc.require_motion_allowed()  # (first: torque on while latched is `estop_latched`)
    if guarded and item.name == "torque_enable":
        if raw != 0 and dxl_id in ids:
            _in_use(svc, item, dxl_id, TORQUE_ON)
        falls = svc.profile.falls_on(dxl_id)
        if raw == 0 and falls is not None:
            raise InUse(f"torque off of servo {dxl_id} would let {falls} fall (the profile's "
                        "joints.falls_without_torque): gravity would move it where no planned "
                        "move may go, at no speed the server set. Move it with POST "
                        f"/api/v1/arms/{svc.name}/move/joints. Pass-through may not switch it "
                        "off: the profile does not allow raw access")


def _own_ids(svc: ArmService) -> dict[int, str]:
    """The arm's own servo ids (its joints' and its gripper's), each with what it drives."""
    ids = {j.motor_id: j.name for j in svc.profile.joints if j.motor_id is not None}
    if svc.profile.gripper.motor_id is not None:
        ids[svc.profile.gripper.motor_id] = "gripper"
    return ids


def _in_use(svc: ArmService, item: mx28.ControlItem, dxl_id: int,
            setting: tuple[str, str]) -> NoReturn:
    """409 `in_use`: `item` of the arm's servo `dxl_id` is the driver's (`setting`: why, and
    the route or profile key that changes it)."""
    why, route = setting
    raise InUse(f"{item.name} of servo {dxl_id} is set by the {svc.name} driver ({why}); "
                f"change it with {route.format(arm=svc.name, id=dxl_id)}. Pass-through "
                "may not write it: the profile does not allow raw access")


def _safe(item: mx28.ControlItem, raw: int) -> bool:
    """Writes that cannot move the arm, allowed while the estop is latched: torque off, LED
    (torque off of a joint that falls without it is refused apart: `_check_write`)."""
    return item.name == "led" or (item.name == "torque_enable" and raw == 0)


async def _send(svc: ArmService, item: mx28.ControlItem, values: dict[int, int],
                send: Callable[[bool], Awaitable[None]]) -> None:
    """Send checked writes; goal positions of the arm's joints, one or several, go through
    the arm's pass-through gate together (checked like a planned move from where the arm is,
    on the control thread). `send(gated)`: gated unless every write is a safe one."""
    if item.name == "goal_position":
        goals = {_joint_of(svc, i): float(raw) for i, raw in values.items()}
        await svc.command_passthrough(goals, lambda: send(True))
        return
    chain = _driver(svc)
    if item.name == "torque_enable" and isinstance(chain, DynamixelChainDriver):
        joints = [i for i, raw in values.items() if raw and i in chain.ids]
        if joints:  # (raw access: `_check_write` refuses it otherwise)
            hold = chain.goal_at_present
            await svc.torque_on_holding(lambda: hold(joints), lambda: send(True))
        else:
            await send(not all(_safe(item, raw) for raw in values.values()))
        _torque_event(svc, values)
        return
    await send(not all(_safe(item, raw) for raw in values.values()))


def _torque_event(svc: ArmService, values: dict[int, int]) -> None:
    """A Torque Enable written to the arm's joint servos: the `torque` event the torque route
    sends too, with the joints switched (a dashboard reads which from the arm's detail)."""
    names = {j.motor_id: j.name for j in svc.profile.joints}
    for on in (False, True):
        joints = [names[i] for i, raw in values.items() if i in names and bool(raw) == on]
        if joints:
            svc.event("torque", on=on, joints=joints)


def _value(svc: ArmService, dxl_id: int, item: mx28.ControlItem, raw: int) -> s.RegisterValue:
    return s.RegisterValue(id=dxl_id, name=item.name, address=item.address, size=item.size,
                           raw=raw, unit=item.unit, value=_table(svc).to_unit(item, raw))


@router.post(
    "/ping",
    response_model=s.PingResult,
    summary="PING one id, or every id on the bus",
    description="With `id`: that servo's model number and firmware version, or an empty list "
    "if no servo answers (an absent servo is an answer). Without (or with no body): a "
    "broadcast ping, answering every servo that replied. " + _NOT_SUPPORTED,
    responses=errors(*DEVICE),
)
async def ping(svc: ControlArm,
               req: Annotated[s.PingRequest | None, Body()] = None) -> s.PingResult:
    found = await _driver(svc).ping(req.id if req is not None else None)
    return s.PingResult(devices=[s.PingDevice(id=i, model_number=m, firmware_version=f)
                                 for i, m, f in found])


@router.get(
    "/{dxl_id}/registers/{name}",
    response_model=s.RegisterValue,
    summary="READ one control-table item",
    description="The raw value and, where the item has a unit, the value in it (e.g. deg). "
    "422 `unknown_register` for a name not in the arm's control table. Operator token (it uses the "
    "bus). " + _NOT_SUPPORTED,
    responses=errors(*DEVICE),
)
async def read_register(svc: ControlArm, dxl_id: DxlId, name: RegName) -> s.RegisterValue:
    drv = _driver(svc)
    item = _item(svc, name)
    return _value(svc, dxl_id, item, await drv.read_register(dxl_id, item))


@router.put(
    "/{dxl_id}/registers/{name}",
    response_model=s.RegisterValue,
    summary="WRITE one control-table item",
    description="Writes `raw`. 422 `unknown_register`, `read_only`, `out_of_range`; "
    "`goal_position` only to the arm's motors (422 `unknown_id`) and within the joint limits "
    "(422 `joint_limit`); 409 `in_use`, naming the route that changes it, for the settings the "
    "driver relies on (" + ", ".join(DRIVER_SETTINGS) + ") of the arm's own servos unless the "
    "profile allows raw access; 409 `estop_latched` for anything but torque "
    "off and the LED while the estop is latched; 409 `in_use` for `torque_enable` 1 to the arm's "
    "own servos unless the profile allows raw access (as torque comes on a servo drives to its "
    "Goal Position, perhaps older than where the joint is: switch it on with PUT "
    "/api/v1/arms/{arm}/torque, every joint holding where it is, or the servo's reboot); a "
    "joint whose torque goes off is told nothing any more (its commanded state forgotten); "
    "409 `in_use` for `torque_enable` 0 to the servo of a joint that falls without "
    "torque (the profile's `falls_without_torque`: gravity would move it where no planned "
    "move may go) unless the profile allows raw access; 409 `in_use` for `id` or `secondary_id` "
    "of any servo set to one of the arm's own ids (it would take the arm's commands) unless "
    "the profile allows raw access. Answers the value written. "
    + _NOT_SUPPORTED,
    responses=errors(*DEVICE),
)
async def write_register(svc: ControlArm, dxl_id: DxlId, name: RegName,
                         req: s.RegisterWrite) -> s.RegisterValue:
    return await write_one(svc, dxl_id, name, req.raw)


async def write_one(svc: ArmService, dxl_id: int, name: str, raw: int) -> s.RegisterValue:
    """The register write's checks and its send, after the access, the arm and its lease:
    the route above and `RegisterWriteFastPath` below run this one."""
    drv = _driver(svc)
    item = _item(svc, name)
    _check_write(svc, item, dxl_id, raw)
    await _send(svc, item, {dxl_id: raw},
                lambda gated: drv.write_register(dxl_id, item, raw, gated=gated))
    return _value(svc, dxl_id, item, raw)


@router.post(
    "/sync-read",
    response_model=s.SyncReadResult,
    summary="SYNC_READ one item from several ids",
    description="One instruction, one status packet per id (ids answered in the order asked, "
    "duplicates removed). " + _NOT_SUPPORTED,
    responses=errors(*DEVICE),
)
async def sync_read(svc: ControlArm, req: s.SyncReadRequest) -> s.SyncReadResult:
    drv = _driver(svc)
    item = _item(svc, req.name)
    ids = list(dict.fromkeys(req.ids))
    return s.SyncReadResult(name=item.name, values=await drv.sync_read(item, ids))


@router.post(
    "/sync-write",
    response_model=s.Ack,
    summary="SYNC_WRITE one item to several ids",
    description="Every value is checked as for a single write before the one instruction is "
    "sent (all or nothing); goal positions of the arm's joints are checked together, as one "
    "command from where the arm is (joint limits, keep-out zones and floor along the path "
    "each servo takes at its Profile Velocity, raw access too). " + _NOT_SUPPORTED,
    responses=errors(*DEVICE),
)
async def sync_write(svc: ControlArm, req: s.SyncWriteRequest) -> s.Ack:
    drv = _driver(svc)
    item = _item(svc, req.name)
    values = dict(req.values)
    for dxl_id, raw in values.items():
        _check_write(svc, item, dxl_id, raw)
    await _send(svc, item, values, lambda gated: drv.sync_write(item, values, gated=gated))
    return s.Ack(command=f"SYNC_WRITE {item.name}")


@router.post(
    "/{dxl_id}/reboot",
    response_model=s.Ack,
    summary="REBOOT one servo (clears a hardware fault)",
    description="One REBOOT (never a factory reset): the servo restarts with its RAM defaults, "
    "which clears a hardware error. One of the arm's servos is then set up again as at "
    "connect (operating mode, profile velocity, goal = present position, torque on); a joint "
    "that needs homing comes back not homed. Works while the arm has a fault; refused while "
    "the estop is latched (409 `estop_latched`) or a motion runs or is queued (409 `busy`). "
    "The servo's torque is off from the REBOOT until it is set up again: for a joint that "
    "falls without torque (the profile's `falls_without_torque`: the angler's z winch) whose "
    "servo holds torque, 409 `in_use` unless the body says `{\"load_supported\": true}` (its "
    "load rests or is held) or the profile allows raw access. " + _NOT_SUPPORTED,
    responses=errors(*DEVICE),
)
async def reboot(svc: ControlArm, dxl_id: DxlId,
                 req: Annotated[s.RebootRequest | None, Body()] = None) -> s.Ack:
    drv = _driver(svc)
    falls = None if svc.profile.raw_access else svc.profile.falls_on(dxl_id)
    if falls is not None and not (req is not None and req.load_supported):
        svc.require_motion_allowed()  # (first: latched is `estop_latched`, as before)
        if await drv.read_register(dxl_id, _item(svc, "torque_enable")):
            raise InUse(f"a reboot switches servo {dxl_id}'s torque off until it is set up "
                        f"again, and {falls} falls without torque (the profile's "
                        "joints.falls_without_torque). Rest or hold its load first, then say "
                        'so: {"load_supported": true}')
    await svc.reboot(dxl_id)
    return s.Ack(command=f"REBOOT {dxl_id}")


class RegisterWriteFastPath:
    """`PUT {prefix}/arms/{arm}/dynamixel/{id}/registers/{name}` (`write_register`) answered
    by the same code without FastAPI's router and dependency solving: an ASGI layer inside
    every other one (installed innermost, `FAST_PATHS`), so the audit log, the last-resort
    errors, CORS, the Host and Origin guard, the token gate and the body limit have all run
    on it as on any request.

    A pass-through goal is the command whose latency is measured (issue 23: a goal's
    `PUT` ends with the first sample that shows the move); the router walks every included
    router's routes twice and FastAPI solves the dependencies: profiled, about 60 % of the
    HTTP thread's CPU for a goal (`bench/goal_trace.py`, docs/performance.md). Here:
    `check_control` (`ControlArm`'s token, role, arm and lease checks, the same function),
    the body validated by `RegisterWrite` from its raw bytes, and `write_one` (the route's
    checks and send, the same function). An `ArmError` is answered as the app's handler
    answers it (`arm_error_response`), the value as FastAPI serialises the route's
    `response_model`.

    Only a request whose every part the route would take as it is comes here: a query
    string, a `root_path`, a content type other than `application/json`, an id that is not
    0-252 in plain digits, an arm or register name over 64 characters, an `X-Arm-Lease` over
    128, or a body `RegisterWrite` refuses go down to the router exactly as before (its 422
    answers, its order of checks), with the body replayed; so do all other requests."""

    def __init__(self, app: ASGIApp, app_ref: FastAPI) -> None:
        self.app = app
        self.state = app_ref.state
        self.head = s.API_PREFIX + "/arms/"

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        target = self._target(scope)
        if target is None:
            await self.app(scope, receive, send)
            return
        chunks: list[bytes] = []
        while True:  # the body limit (outside) has bounded it
            message = await receive()
            if message["type"] != "http.request":  # a disconnect: the router sees it
                await self.app(scope, _replay(message, receive), send)
                return
            chunks.append(message.get("body", b""))
            if not message.get("more_body", False):
                break
        body = b"".join(chunks)
        try:
            req = s.RegisterWrite.model_validate_json(body)
        except ValidationError:  # the router's 422, as it words it
            await self.app(scope, _replay({"type": "http.request", "body": body,
                                           "more_body": False}, receive), send)
            return
        arm, dxl_id, name, token, lease = target
        response: Response
        try:
            svc = await check_control(self.state.access, self.state.services,
                                      self.state.leases, token, arm, lease)
            value = await write_one(svc, dxl_id, name, req.raw)
        except ArmError as exc:
            response = arm_error_response(exc)
        else:
            response = Response(value.model_dump_json(by_alias=True),
                                media_type="application/json")
        await response(scope, receive, send)

    def _target(self, scope: Scope) -> tuple[str, int, str, str | None, str | None] | None:
        """(arm, id, register name, token, lease id) of a register write this layer takes,
        else None."""
        if scope["type"] != "http" or scope.get("method") != "PUT" or scope.get("query_string") \
                or scope.get("root_path"):
            return None
        path: str = scope["path"]
        if not path.startswith(self.head):
            return None
        parts = path[len(self.head):].split("/")
        if len(parts) != 5 or parts[1] != "dynamixel" or parts[3] != "registers":
            return None
        arm, dxl, name = parts[0], parts[2], parts[4]
        if not (0 < len(arm) <= 64 and 0 < len(name) <= 64 and 0 < len(dxl) <= 3
                and dxl.isascii() and dxl.isdigit() and int(dxl) <= 252):
            return None
        auth = lease = kind = None
        for key, value in scope.get("headers", ()):
            if key == b"content-type" and kind is None:
                kind = value
            elif key == b"authorization" and auth is None:
                auth = value.decode("latin-1")
            elif key == b"x-arm-lease" and lease is None:
                lease = value.decode("latin-1")
        if kind is None or kind.lower() != b"application/json" or (
                lease is not None and len(lease) > 128):
            return None
        return arm, int(dxl), name, bearer_credentials(auth), lease


def _replay(first: Message, receive: Receive) -> Receive:
    """A `receive` that gives `first` once, then `receive`'s messages."""
    given = False

    async def again() -> Message:
        nonlocal given
        if not given:
            given = True
            return first
        return await receive()
    return again


#: The ASGI layers of this router's module, innermost (app/arms `arm_fast_paths`).
FAST_PATHS = [RegisterWriteFastPath]
