"""Angler driver: four Dynamixel MX-28 servos on Protocol 2.0 (protocol/dynamixel.py).

Polling is one SYNC_READ of Moving, Moving Status, Present PWM, Load, Velocity and Position
(addresses 122-135) for every servo; motion setpoints are one SYNC_WRITE of Goal Position.
Before a request that follows a failed one the input is drained, and replies are accepted only
from the ids asked, in order, as status packets; a CRC failure fails the request as corrupt.

Faults (e-manual, Protocol 2.0 "Status Packet" and MX-28 (2.0) "Hardware Error Status"): a
status whose error byte has only the Alert bit (0x80) set is a valid reply, its data good; the
Alert bit says "read Hardware Error Status (70)". The driver does so when a servo's Alert bit
appears (and once a second while it stays), reports the decoded bits in `faults`, and keeps
serving the healthy servos. Only REBOOT clears a hardware error; `reboot` sets the servo up
again as at connect. Error bits 0-6 (instruction, CRC, data range, ...) still fail a request.
"""

from __future__ import annotations

import asyncio
import logging
import math
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from app.devices.base import Driver, SettleState
from app.errors import ArmError, CorruptReply, DeviceError, DeviceTimeout, NoGripper
from protocol import dynamixel as dxl
from protocol import mx28

log = logging.getLogger(__name__)

#: Moving (1) + Moving Status (1) + Present PWM (2) + Load (2) + Velocity (4) + Position (4).
_POLL_ADDR = mx28.TABLE["moving"].address
_POLL_LEN = 14
#: Torque Enable (64) .. Hardware Error Status (70): one READ when the Alert bit appears.
_FAULT_ADDR = mx28.TABLE["torque_enable"].address
_FAULT_LEN = mx28.TABLE["hardware_error_status"].address - _FAULT_ADDR + 1
#: 0.229 rpm per Present Velocity unit (e-manual MX-28 (2.0), address 128).
_RPM_PER_UNIT = 0.229
#: How often a standing fault's Hardware Error Status is read again, s.
FAULT_REFRESH_S = 1.0
#: How long a rebooted servo may take to answer a PING again, s.
BOOT_WAIT_S = 3.0
#: How often Profile Velocity is read back to notice a servo that lost power, s: at power-up
#: it is 0 (a RAM default), where set-up wrote a non-zero value.
POWER_CHECK_S = 0.5

#: Hardware Error Status bits (e-manual MX-28 (2.0), address 70) and what a lab should do.
FAULT_BITS: dict[int, tuple[str, str]] = {
    0: ("input_voltage", "check the supply: the input voltage left the servo's limits"),
    2: ("overheating", "let the servo cool down and reduce its load"),
    3: ("motor_encoder", "the servo's encoder failed: check the servo, it may need replacing"),
    4: ("electrical_shock", "check the wiring and the supply for shorts"),
    5: ("overload", "remove the load or obstruction (a jammed screw, an end stop)"),
}


def decode_faults(raw: int) -> list[str]:
    """Names of the Hardware Error Status bits set in `raw` (unknown bits as `bitN`)."""
    known = mx28.hardware_error_names(raw)
    return known + [f"bit{b}" for b in range(8) if raw >> b & 1 and b not in FAULT_BITS]


def fault_advice(dxl_id: int, raw: int, arm: str) -> str:
    hints = [FAULT_BITS[b][1] for b in FAULT_BITS if raw >> b & 1]
    return ("; ".join(hints) + "; " if hints else "") + (
        f"then clear it with POST /api/v1/arms/{arm}/dynamixel/{dxl_id}/reboot (only a reboot "
        "clears a hardware error; multi-turn joints then need homing again)")


@dataclass(frozen=True)
class DxlRequest:
    packet: bytes
    expect: tuple[int, ...]  # ids expected to answer, in order; () for none
    broadcast_ping: bool = False
    what: str = ""


@dataclass(frozen=True)
class _Reboot:
    """REBOOT one servo, then (for one of the arm's) set it up again, in the owner task."""

    dxl_id: int


class AnglerDriver(Driver):
    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._parser = dxl.Parser()
        self._dirty = False
        self.ids = tuple(int(j.motor_id) for j in self.profile.joints)  # type: ignore[arg-type]
        self._ticks_per_rev = np.array([j.ticks_per_rev for j in self.profile.joints], float)
        # Load (0.1 % of stall torque) -> joint effort: N m at the motor, N on a lead.
        stall = np.array([j.stall_torque_nm or 0.0 for j in self.profile.joints], float)
        per_rev = np.array([j.lead_m if j.lead_m else 2 * math.pi for j in self.profile.joints])
        self._effort_per_load = stall / 1000.0 * (2 * math.pi / per_rev)
        self._sensed = bool(np.any(stall > 0))
        #: Servos whose last status carried the Alert bit.
        self._alerts: set[int] = set()
        #: Hardware Error Status by servo, and when it was last read (monotonic s).
        self._hw_errors: dict[int, tuple[int, float]] = {}
        #: Per joint, from the last poll: the servo says it is still on its way.
        self._moving = np.zeros(len(self.ids), dtype=bool)
        #: Profile Velocity written at set-up, per servo (raw), after the Velocity Limit cap.
        self.profile_velocity: dict[int, int] = {}
        self._power_checked = 0.0

    # --------------------------------------------------------- pass-through

    async def ping(self, dxl_id: int | None) -> list[tuple[int, int, int]]:
        if dxl_id is None:
            req = DxlRequest(dxl.ping(dxl.BROADCAST_ID), (), True, "broadcast PING")
        else:
            req = DxlRequest(dxl.ping(dxl_id), (dxl_id,), False, f"PING {dxl_id}")
        try:
            packets = await self.submit(req)
        except DeviceTimeout:
            if dxl_id is not None and dxl_id in self.ids:
                # One of this arm's own servos: silence is a lost reply or a fault of the
                # link, not an absent servo; saying "absent" would be a wrong answer.
                raise
            return []  # no servo with that id on this arm: an answer, not a failure (API.md)
        return [(p.id, dxl.from_bytes(p.params[0:2], False), p.params[2]) for p in packets]

    async def read_register(self, dxl_id: int, item: mx28.ControlItem) -> int:
        [p] = await self.submit(DxlRequest(dxl.read(dxl_id, item.address, item.size), (dxl_id,),
                                           what=f"READ {item.name} from {dxl_id}"))
        _check_len(p, item.size)
        return dxl.from_bytes(p.params, item.signed)

    async def write_register(self, dxl_id: int, item: mx28.ControlItem, raw: int) -> None:
        data = dxl.to_bytes(raw, item.size)
        expect = () if dxl_id == dxl.BROADCAST_ID else (dxl_id,)
        await self.submit(DxlRequest(dxl.write(dxl_id, item.address, data), expect,
                                     what=f"WRITE {item.name} to {dxl_id}"))
        self._note_written(item, {dxl_id: raw})

    async def sync_read(self, item: mx28.ControlItem, ids: list[int]) -> dict[int, int]:
        packets = await self.submit(DxlRequest(dxl.sync_read(item.address, item.size, ids),
                                               tuple(ids), what=f"SYNC_READ {item.name}"))
        out = {}
        for p in packets:
            _check_len(p, item.size)
            out[p.id] = dxl.from_bytes(p.params, item.signed)
        return out

    async def sync_write(self, item: mx28.ControlItem, values: dict[int, int]) -> None:
        data = {i: dxl.to_bytes(v, item.size) for i, v in values.items()}
        await self.submit(DxlRequest(dxl.sync_write(item.address, item.size, data), (),
                                     what=f"SYNC_WRITE {item.name}"))
        self._note_written(item, values)

    def _note_written(self, item: mx28.ControlItem, values: dict[int, int]) -> None:
        """A pass-through Profile Velocity is what the power check expects back."""
        if item.name == "profile_velocity":
            for i, raw in values.items():
                if i in self.ids:
                    self.profile_velocity[i] = raw

    async def reboot(self, dxl_id: int) -> None:
        """One REBOOT (never a factory reset); one of the arm's servos is then set up again as
        at connect and, if its joint needs homing, is no longer homed."""
        await self.submit(_Reboot(dxl_id), timeout=BOOT_WAIT_S + 4 * self.timeout)

    # --------------------------------------------------------- motion interface

    async def command_joints(self, q: np.ndarray) -> None:
        ticks = self.model.transmission.to_ticks(np.asarray(q, dtype=float))
        await self.sync_write(mx28.TABLE["goal_position"],
                              {i: int(round(t)) for i, t in zip(self.ids, ticks, strict=True)})

    async def set_gripper(self, value: float) -> None:
        raise NoGripper(f"{self.name} has a passive magnet, not an actuated gripper")

    async def settle_state(self) -> SettleState:
        """Torque Enable read now from every servo; Moving / Moving Status from the last poll
        (a servo is on its way while Moving is 1 or Moving Status says the profile runs)."""
        torque = await self.sync_read(mx28.TABLE["torque_enable"], list(self.ids))
        off = tuple(k for k, i in enumerate(self.ids) if not torque.get(i, 0))
        return SettleState(torque_off=off, moving=tuple(int(k) for k in
                                                        np.flatnonzero(self._moving)))

    # --------------------------------------------------------- owner task

    def _reset_reader(self) -> None:
        self._parser = dxl.Parser()
        self._dirty = True

    def _profile_velocity(self, joint: Any, velocity_limit: int) -> int:
        """Profile Velocity (0.229 rpm units) for a joint's velocity limit, rounded down: the
        servo never turns faster than the limit, even catching up on a plan (moves are planned
        at `tracking_margin` of the limit, which leaves it the headroom to catch up); never
        above the servo's Velocity Limit (44), the ceiling of Profile Velocity (e-manual)."""
        per_rev = joint.lead_m if joint.lead_m else 2 * math.pi
        rpm = joint.max_velocity / per_rev * 60.0
        raw = max(1, math.floor(rpm / _RPM_PER_UNIT))
        return min(raw, velocity_limit) if velocity_limit > 0 else raw

    async def _on_connected(self) -> None:
        for k in range(len(self.ids)):
            await self._setup_servo(k)

    async def _setup_servo(self, k: int) -> None:
        """Operating mode from the profile, Profile Velocity from the joint's
        velocity limit (so the servo itself caps speed), goal = present, torque on: the servo
        holds where it is instead of jumping to a stale goal. A servo that refuses (a hardware
        error keeps torque off until a reboot) is reported, not retried: the link stays up for
        the others. A servo that does not answer at all fails the set-up (DeviceTimeout)."""
        t = mx28.TABLE
        joint, i = self.profile.joints[k], self.ids[k]
        await self._setup_exchange(DxlRequest(dxl.ping(i), (i,), what=f"PING {i}"), self.timeout)
        try:
            # Written only when it differs: a change of mode re-initialises Present Position
            # within one turn (e-manual), so a multi-turn joint is then no longer homed; and
            # only then is torque switched off (an EEPROM write needs it off), so a reconnect
            # never lets the z winch drop its load.
            if (joint.operating_mode is not None
                    and await self._read(i, t["operating_mode"]) != joint.operating_mode):
                await self._write(i, t["torque_enable"], 0)
                await self._write(i, t["operating_mode"], joint.operating_mode)
                if joint.needs_homing and not self._first_setup(k):
                    self.homed[k] = False
            # after the mode: changing Operating Mode resets Profile Velocity (e-manual)
            limit = await self._read(i, t["velocity_limit"])
            self.profile_velocity[i] = self._profile_velocity(joint, limit)
            await self._write(i, t["profile_velocity"], self.profile_velocity[i])
            await self._write(i, t["goal_position"], await self._read(i, t["present_position"]))
            await self._write(i, t["torque_enable"], 1)
        except DeviceError as exc:
            if isinstance(exc, CorruptReply):
                raise
            log.warning("%s: servo %d (%s) not set up: %s", self.name, i, joint.name, exc.detail)
            self.last_error = f"servo {i} ({joint.name}) not set up: {exc.detail}"
        if i in self._alerts:
            await self._read_fault(i)
            self._publish_faults()

    def _first_setup(self, k: int) -> bool:
        """Joint `k` has never been set up by this driver (the start of its first connect):
        `homed` then still says what the profile's link says (homed_at_start)."""
        return self.ids[k] not in self.profile_velocity

    async def _read(self, i: int, item: mx28.ControlItem) -> int:
        [p] = await self._setup_exchange(
            DxlRequest(dxl.read(i, item.address, item.size), (i,), what=f"READ {item.name}"),
            self.timeout)
        _check_len(p, item.size)
        return dxl.from_bytes(p.params, item.signed)

    async def _write(self, i: int, item: mx28.ControlItem, raw: int) -> None:
        """A set-up write (idempotent: retried on a lost or corrupt reply)."""
        await self._setup_exchange(
            DxlRequest(dxl.write(i, item.address, dxl.to_bytes(raw, item.size)), (i,),
                       what=f"WRITE {item.name} to {i}"), self.timeout)

    async def _reboot(self, dxl_id: int) -> list[dxl.Packet]:
        got: list[dxl.Packet] = await self._exchange(
            DxlRequest(dxl.reboot(dxl_id), (dxl_id,), what=f"REBOOT {dxl_id}"), self.timeout)
        if dxl_id not in self.ids:
            return got
        k = self.ids.index(dxl_id)
        loop = asyncio.get_running_loop()
        deadline = loop.time() + BOOT_WAIT_S
        while True:  # the status comes before the restart: wait until it answers again
            try:
                await self._exchange(DxlRequest(dxl.ping(dxl_id), (dxl_id,),
                                                what=f"PING {dxl_id} after REBOOT"), self.timeout)
                break
            except (DeviceTimeout, CorruptReply):
                if loop.time() > deadline:
                    raise
        self._hw_errors.pop(dxl_id, None)
        if self.profile.joints[k].needs_homing:
            self.homed[k] = False  # a multi-turn position restarts within one turn
        await self._setup_servo(k)
        self._publish_faults()
        return got

    async def _poll(self) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        packets = await self._exchange(
            DxlRequest(dxl.sync_read(_POLL_ADDR, _POLL_LEN, list(self.ids)), self.ids,
                       what="SYNC_READ present state"), self.timeout)
        load = np.empty(len(self.ids))
        vel = np.empty(len(self.ids))
        pos = np.empty(len(self.ids))
        for k, p in enumerate(packets):
            _check_len(p, _POLL_LEN)
            # Moving (122) or Moving Status bit 1, "profile ongoing" (123)
            self._moving[k] = bool(p.params[0]) or bool(p.params[1] & 0x02)
            load[k] = dxl.from_bytes(p.params[4:6], True)
            vel[k] = dxl.from_bytes(p.params[6:10], True)
            pos[k] = dxl.from_bytes(p.params[10:14], True)
        await self._check_faults()
        await self._check_power()
        tr = self.model.transmission
        q = tr.from_ticks(pos)
        qd = tr.velocity_from_ticks(vel * _RPM_PER_UNIT / 60.0 * self._ticks_per_rev)
        tau = load * self._effort_per_load if self._sensed else None
        return q, qd, tau

    async def _check_power(self) -> None:
        """A servo whose Profile Velocity reads 0 where set-up wrote more has been power
        cycled (a brown-out, a loose supply): torque is off and a multi-turn joint has lost its
        count. Say so and un-home the joint; its reboot route sets it up again."""
        now = time.monotonic()
        if now - self._power_checked < POWER_CHECK_S or not self.profile_velocity:
            return
        self._power_checked = now
        ids = [i for i in self.ids if self.profile_velocity.get(i)]
        pv = await self._exchange(
            DxlRequest(dxl.sync_read(mx28.TABLE["profile_velocity"].address, 4, ids),
                       tuple(ids), what="SYNC_READ profile_velocity"), self.timeout)
        for p in pv:
            if len(p.params) == 4 and dxl.from_bytes(p.params, False) == 0:
                k = self.ids.index(p.id)
                joint = self.profile.joints[k]
                del self.profile_velocity[p.id]
                if joint.needs_homing:
                    self.homed[k] = False
                log.warning("%s: servo %d (%s) lost power (its RAM is back to defaults: torque "
                            "off)", self.name, p.id, joint.name)
                self.last_error = (f"servo {p.id} ({joint.name}) was power cycled: torque off"
                                   f"{', not homed' if joint.needs_homing else ''}; reboot it to "
                                   "set it up again")
                self.hub.event("power_cycled", joint=joint.name, servo=p.id,
                               homed=list(self.homed))

    # --------------------------------------------------------- faults

    async def _check_faults(self) -> None:
        """Read Hardware Error Status of servos whose Alert bit appeared (or stands for
        FAULT_REFRESH_S); forget the fault of a servo whose statuses no longer carry it."""
        now = time.monotonic()
        changed = False
        for i in self.ids:
            if i in self._alerts:
                seen = self._hw_errors.get(i)
                if seen is None or now - seen[1] >= FAULT_REFRESH_S:
                    before = seen[0] if seen else None
                    await self._read_fault(i)
                    changed |= self._hw_errors.get(i, (None,))[0] != before
            elif i in self._hw_errors:
                del self._hw_errors[i]
                changed = True
        if changed:
            self._publish_faults()

    async def _read_fault(self, i: int) -> None:
        """Torque Enable .. Hardware Error Status in one READ; a failed read keeps the old."""
        try:
            [p] = await self._exchange(DxlRequest(dxl.read(i, _FAULT_ADDR, _FAULT_LEN), (i,),
                                                  what="READ hardware_error_status"),
                                       self.timeout)
            _check_len(p, _FAULT_LEN)
        except ArmError as exc:
            log.warning("%s: cannot read servo %d's hardware error: %s", self.name, i,
                        exc.detail)
            return
        self._hw_errors[i] = (p.params[-1], time.monotonic())

    def _publish_faults(self) -> None:
        faults = []
        for k, i in enumerate(self.ids):
            if i in self._hw_errors:
                raw = self._hw_errors[i][0]
                faults.append({"joint": self.profile.joints[k].name, "servo": i,
                               "bits": decode_faults(raw), "raw": raw,
                               "advice": fault_advice(i, raw, self.name)})
        if faults == self.faults:
            return
        old = {f["servo"]: f for f in self.faults}
        new = {f["servo"]: f for f in faults}
        self.faults = faults
        for i in sorted(old.keys() | new.keys()):
            if old.get(i) != new.get(i):
                f = new.get(i) or old[i]
                cleared = i not in new
                (log.info if cleared else log.warning)(
                    "%s: servo %d (%s) %s: %s", self.name, i, f["joint"],
                    "fault cleared" if cleared else "fault", ", ".join(f["bits"]) or "alert")
                self.hub.event("fault", joint=f["joint"], servo=i, bits=f["bits"], raw=f["raw"],
                               advice=f["advice"], cleared=cleared, faults=faults)

    # --------------------------------------------------------- exchanges

    async def _exchange(self, message: Any, timeout: float) -> Any:
        try:
            if isinstance(message, _Reboot):
                return await self._reboot(message.dxl_id)
            return await self._exchange_once(message, timeout)
        except BaseException:
            self._dirty = True  # whatever failed may have left bytes behind
            raise

    async def _exchange_once(self, message: Any, timeout: float) -> Any:
        req: DxlRequest = message
        if self._dirty:
            await self._drain()
        await self.link.write(req.packet)
        if not req.expect and not req.broadcast_ping:
            return []
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout
        got: list[dxl.Packet] = []
        while True:
            for ev in iter(self._parser.next_event, None):
                if isinstance(ev, dxl.ParseError):
                    if ev.kind == "garbage":
                        continue
                    self.stats["corrupt"] += 1
                    raise CorruptReply(f"{self.name}: {req.what}: {ev.kind}: {ev.detail}")
                if ev.instruction != dxl.Instruction.STATUS:
                    continue  # our own echo on a half-duplex adapter, or noise
                if req.broadcast_ping:
                    got.append(ev)
                    continue
                if len(got) >= len(req.expect) or ev.id != req.expect[len(got)]:
                    self.stats["stale_replies"] += 1
                    continue
                error = ev.error or 0
                if error & dxl.ALERT_BIT:  # a valid reply; the servo has a hardware error
                    self._alerts.add(ev.id)
                else:
                    self._alerts.discard(ev.id)
                if error & ~dxl.ALERT_BIT:
                    raise DeviceError(f"{self.name}: {req.what}: servo {ev.id}: "
                                      f"{dxl.describe_error(error)}")
                got.append(ev)
                if len(got) == len(req.expect):
                    return got
            left = deadline - loop.time()
            if left <= 0:
                if req.broadcast_ping:
                    return sorted(got, key=lambda p: p.id)
                missing = req.expect[len(got):]
                raise DeviceTimeout(f"{self.name}: {req.what}: no status from id "
                                    f"{', '.join(map(str, missing))} within "
                                    f"{timeout * 1000:.0f} ms")
            data = await self.link.read(left)
            if data:
                self._parser.feed(data)

    async def _drain(self) -> None:
        """After a failed exchange, discard input until the bus has been quiet for one timeout
        (DynamixelSDK flushes before every send instead): status packets carry no request tag,
        so this is what keeps a late reply from answering the next request. After a clean
        exchange every expected byte was consumed, and nothing is waited for."""
        while await self.link.read(self.timeout):
            pass
        self._parser = dxl.Parser()
        self._dirty = False


def _check_len(p: dxl.Packet, size: int) -> None:
    if len(p.params) != size:
        raise CorruptReply(f"servo {p.id} answered {len(p.params)} bytes, expected {size}")
