"""A chain of Dynamixel servos on one Protocol 2.0 bus (protocol/dynamixel.py): the driver every
arm of Dynamixel servos shares (MX-28 (2.0) or X series: the items used have one layout); an
arm's own driver adds only what is its own (the effort unit, a gripper servo, ...).

Polling is one SYNC_READ of Moving, Moving Status, Present PWM, Present Load (MX-28) or
Present Current (X series), Velocity and Position (addresses 122-135, the same layout on both
tables) for every servo: the joints' and the extra ones (`aux_ids`, e.g. a gripper); motion
setpoints are one SYNC_WRITE of Goal Position. Before a request that follows a failed one the
input is drained, and replies are accepted only from the ids asked, in order, as status
packets; a CRC failure fails the request as corrupt.

Faults (e-manual, Protocol 2.0 "Status Packet" and "Hardware Error Status"): a status whose
error byte has only the Alert bit (0x80) set is a valid reply, its data good. The driver reads
Hardware Error Status (70) when a servo's Alert bit appears (and once a second while it
stays), reports the decoded bits in `faults`, and keeps serving the healthy servos. Only
REBOOT clears a hardware error; `reboot` sets the servo up again as at connect. Error bits 0-6
(instruction, CRC, data range, ...) still fail a request.
"""

from __future__ import annotations

import asyncio
import logging
import math
import struct
import time
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from app.arms.dynamixel.bus_rate import OTHER_RATES, found_message, poll_rate
from app.arms.dynamixel.exchange import DxlRequest, DynamixelBusDriver, check_len
from app.arms.dynamixel.faults import decode_faults, fault_advice
from app.config import JointConfig
from app.device.driver import SettleState
from app.errors import ArmError, CorruptReply, DeviceError, DeviceTimeout
from protocol import dynamixel as dxl
from protocol import mx28
from protocol.mx28 import ControlItem

log = logging.getLogger(__name__)

#: Tries at reading Present Position before torque goes on again (`set_torque`): a reply that
#: came late for a timed-out poll fails a read as corrupt; after these, the last poll's.
TORQUE_ON_READS = 3

#: Moving (1) + Moving Status (1) + Present PWM (2) + Load/Current (2) + Velocity (4) + Position.
_POLL_ADDR = mx28.TABLE["moving"].address
_POLL_LEN = 14
#: The poll's 14 bytes, little-endian: Moving, Moving Status (1 each), Present PWM, Present
#: Load (2 each, signed), Present Velocity, Present Position (4 each, signed).
_POLL_STRUCT = struct.Struct("<BBhhii")
#: Torque Enable (64) .. Hardware Error Status (70): one READ when the Alert bit appears.
_FAULT_ADDR = mx28.TABLE["torque_enable"].address
_FAULT_LEN = mx28.TABLE["hardware_error_status"].address - _FAULT_ADDR + 1
#: 0.229 rpm per Present Velocity unit (e-manual MX-28 (2.0) and XM430-W350, address 128).
_RPM_PER_UNIT = 0.229
#: Ticks of motion after a goal before the poll that follows it reads the bus (`_effect_delay`).
TICKS_TO_SHOW = 1.5
#: How often a standing fault's Hardware Error Status is read again, s.
FAULT_REFRESH_S = 1.0
#: How long a rebooted servo may take to answer a PING again, s.
BOOT_WAIT_S = 3.0
#: How often Profile Velocity is read back to notice a servo that lost power, s: at power-up
#: it is 0 (a RAM default), where set-up wrote a non-zero value.
POWER_CHECK_S = 0.5


@dataclass(frozen=True)
class _Reboot:
    """REBOOT one servo, then (for one of the arm's) set it up again, in the owner task."""

    dxl_id: int


class DynamixelChainDriver(DynamixelBusDriver):
    """Joints on Dynamixel servos, one servo a joint (`motor_id`), plus `aux_ids`."""

    #: Fraction of the stall torque per unit of the item at 126: Present Load is 0.1 % of it
    #: (MX-28); an X-series driver gives Present Current's unit over the stall current.
    effort_per_unit: ClassVar[float] = 0.001

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.ids = tuple(int(j.motor_id or 0) for j in self.profile.joints)
        #: Servos on the arm that are not joints (a gripper): set up, polled, faults reported.
        self.aux_ids: tuple[int, ...] = ()
        #: Operating mode and Profile Velocity (raw, 0: none) of each aux servo.
        self.aux_modes: dict[int, int] = {}
        self.aux_profile_velocity: dict[int, int] = {}
        #: Present Position (raw ticks) of each aux servo, from the last poll.
        self.aux_ticks: dict[int, int] = {}
        self._ticks_per_rev = np.array([j.ticks_per_rev for j in self.profile.joints], float)
        # Load/current unit -> joint effort: N m at the motor, N on a lead.
        stall = np.array([j.stall_torque_nm or 0.0 for j in self.profile.joints], float)
        per_rev = np.array([j.lead_m if j.lead_m else 2 * math.pi for j in self.profile.joints])
        self._effort_per_load = stall * self.effort_per_unit * (2 * math.pi / per_rev)
        self._sensed = bool(np.any(stall > 0))
        #: Hardware Error Status by servo, and when it was last read (monotonic s).
        self._hw_errors: dict[int, tuple[int, float]] = {}
        #: Per joint, from the last poll: the servo says it is still on its way.
        self._moving = np.zeros(len(self.ids), dtype=bool)
        #: Profile Velocity written at set-up, per servo (raw), after the Velocity Limit cap.
        self.profile_velocity: dict[int, int] = {}
        self._power_checked = 0.0
        self._poll_request: DxlRequest | None = None

    @property
    def servo_ids(self) -> tuple[int, ...]:
        """Every servo of the arm: the joints' in joint order, then the aux ones."""
        return self.ids + self.aux_ids

    def servo_name(self, dxl_id: int) -> str:
        if dxl_id in self.ids:
            return self.profile.joints[self.ids.index(dxl_id)].name
        return "gripper" if dxl_id in self.aux_ids else f"servo {dxl_id}"

    def _note_written(self, item: ControlItem, values: dict[int, int]) -> None:
        """A pass-through Profile Velocity is what the power check expects back; a joint whose
        torque came on (its status answered) may be commanded again (`torque_off`)."""
        if item.name == "profile_velocity":
            for i, raw in values.items():
                if i in self.servo_ids:
                    self.profile_velocity[i] = raw
        elif item.name == "torque_enable":
            self.note_torque([self.ids.index(i) for i, raw in values.items()
                              if raw != 0 and i in self.ids], True)

    def _note_sent(self, item: ControlItem, values: dict[int, int]) -> None:
        """Goal Position of the arm's joints is the arm's commanded state. A joint whose torque
        goes off is told nothing any more (as `set_torque`'s off: a hand may move it), and no
        command may move it until its torque is on again (`torque_off`): noted as the write
        goes out, not once its status is in, so that a status the bus loses does not leave a
        limp joint taken for one that holds."""
        if item.name == "torque_enable":
            off = [self.ids.index(i) for i, raw in values.items() if raw == 0 and i in self.ids]
            if off:
                self.forget_commanded(off)
                self.note_torque(off, False)
            return
        if item.name != "goal_position":
            return
        joints = [self.ids.index(i) for i in values if i in self.ids]
        if joints:
            self.note_commanded([values[self.ids[k]] for k in joints], joints)

    def _effect_delay(self, item: ControlItem, values: dict[int, int]) -> float:
        """A Goal Position write to joint servos shows in Present Position once a servo has
        turned one encoder tick at its Profile Velocity (e-manual MX-28 (2.0), Profile
        Velocity (112); Profile Acceleration only makes it later): `TICKS_TO_SHOW` ticks' time
        at the fastest written joint (the owner task times it from the write, `written_at`;
        Present Position rounds, so a half tick more), at most one poll period; 0 where no
        written joint has a profile (its servo steps at once). At 2 rad/s (the angler's
        theta3) a tick takes 0.77 ms, and a status reply comes back in about 0.3 ms at 1
        Mbps."""
        pace = self.pace()
        if item.name != "goal_position" or pace is None:
            return 0.0
        tpu = np.abs(self.model.transmission.ticks_per_unit)
        rates = [float(pace[k] * tpu[k]) for k in (self.ids.index(i) for i in values
                                                   if i in self.ids)
                 if np.isfinite(pace[k]) and pace[k] > 0]
        if not rates:
            return 0.0
        return min(TICKS_TO_SHOW / max(rates), 1.0 / self.profile.link.poll_hz)

    def pace(self) -> np.ndarray | None:
        """Each joint's Profile Velocity as set (0.229 rpm units) in joint units: the servo
        moves to a new goal at that speed at most (e-manual, Profile Velocity (112)). NaN
        where none is set (0: the servo goes as fast as it can)."""
        out = np.full(len(self.ids), np.nan)
        for k, (i, j) in enumerate(zip(self.ids, self.profile.joints, strict=True)):
            raw = self.profile_velocity.get(i, 0)
            if raw > 0:
                per_rev = j.lead_m if j.lead_m else 2 * math.pi
                out[k] = raw * _RPM_PER_UNIT / 60.0 * per_rev
        return out

    async def reboot(self, dxl_id: int) -> None:
        """One REBOOT (never a factory reset); one of the arm's servos is then set up again as
        at connect and, if its joint needs homing, is no longer homed."""
        await self.submit(_Reboot(dxl_id), timeout=BOOT_WAIT_S + 4 * self.timeout)

    # --------------------------------------------------------- motion interface

    async def command_joints(self, q: np.ndarray, *, hold: bool = False) -> None:
        """Goal Position of every joint servo (SYNC_WRITE). An estop's hold (`hold`) leaves out
        the joints whose torque is off (`torque_off`): it would move nothing there, and noted
        as their commanded state it would say the arm is headed for the hold point while a
        hand moves them (`told`: a recording's action, a check's start). Nothing else is sent
        to such a joint (the guard's `require_torque`)."""
        ticks = self.model.transmission.to_ticks(np.asarray(q, dtype=float))
        goals = {i: int(round(t)) for k, (i, t) in enumerate(zip(self.ids, ticks, strict=True))
                 if not (hold and k in self.torque_off)}
        if goals:
            await self.sync_write(mx28.TABLE["goal_position"], goals, gated=not hold)

    async def set_torque(self, on: bool) -> None:
        """Torque Enable (64) of every joint servo. Off: the arm moves freely by hand, its
        positions still polled (the e-manual's Torque Enable: 0 turns the motor's torque off).
        On again: Goal Position first written as each servo's Present Position, so that it
        holds where the hand left it instead of going back to an older goal (the position
        modes drive to Goal Position as soon as torque is on), and noted as the commanded
        state. Off, no joint is told anything any more: the write forgets the commanded state
        (`_note_written`, as for a pass-through torque off), so that what the arm is said to
        be headed for (`told`: a recording's action, a check's start) is where the hand has
        it, not the goal it held before. Neither write is gated by the estop latch: torque off
        is the safe write, and a goal at the present position moves nothing."""
        enable = mx28.TABLE["torque_enable"]
        if not on:
            await self.sync_write(enable, {i: 0 for i in self.ids}, gated=False)
            return
        await self.goal_at_present(list(self.ids), gated=False)
        await self.sync_write(enable, {i: 1 for i in self.ids}, gated=False)

    async def goal_at_present(self, ids: list[int], *, gated: bool = True) -> None:
        """Goal Position of the joint servos `ids` written as their Present Position, read now
        (the last polled positions if the bus fails the read TORQUE_ON_READS times), and noted
        as the commanded state: what a servo whose torque comes on holds, instead of driving
        to an older goal (`set_torque`; a pass-through Torque Enable 1 with raw access)."""
        here: dict[int, int] | None = None
        for _ in range(TORQUE_ON_READS):  # a late reply to a timed-out poll fails one read
            try:
                here = await self.sync_read(mx28.TABLE["present_position"], ids)
                break
            except (CorruptReply, DeviceTimeout):
                continue
        if here is None:  # the bus is struggling: the last polled positions, if any
            q = self.positions
            if q is None:
                raise DeviceTimeout(f"{self.name}: no present position to hold at: torque "
                                    "stays off")
            ticks = self.model.transmission.to_ticks(np.asarray(q, dtype=float))
            polled = {i: int(round(t)) for i, t in zip(self.ids, ticks, strict=True)}
            here = {i: polled[i] for i in ids}
        await self.sync_write(mx28.TABLE["goal_position"], {i: here[i] for i in ids},
                              gated=gated)

    async def settle_state(self) -> SettleState:
        """Torque Enable read now from every servo; Moving / Moving Status from the last poll
        (a servo is on its way while Moving is 1 or Moving Status says the profile runs)."""
        torque = await self.sync_read(mx28.TABLE["torque_enable"], list(self.ids))
        off = tuple(k for k, i in enumerate(self.ids) if not torque.get(i, 0))
        return SettleState(torque_off=off, moving=tuple(int(k) for k in
                                                        np.flatnonzero(self._moving)))

    # --------------------------------------------------------- owner task

    def _profile_velocity(self, joint: JointConfig, velocity_limit: int) -> int:
        """Profile Velocity (0.229 rpm units) for a joint's velocity limit, rounded down: the
        servo never turns faster than the limit, even catching up on a plan (moves are planned
        at `tracking_margin` of the limit, which leaves it the headroom to catch up); never
        above the servo's Velocity Limit (44), the ceiling of Profile Velocity (e-manual)."""
        per_rev = joint.lead_m if joint.lead_m else 2 * math.pi
        rpm = joint.max_velocity / per_rev * 60.0
        raw = max(1, math.floor(rpm / _RPM_PER_UNIT))
        return min(raw, velocity_limit) if velocity_limit > 0 else int(raw)

    async def _on_connected(self) -> None:
        garbage = self.garbage_seen
        try:
            for i in self.servo_ids:
                await self._setup_servo(i)
        except DeviceTimeout:
            await self._why_silent(self.garbage_seen > garbage)
            raise
        self._follow_the_bus()

    def _follow_the_bus(self) -> None:
        """Poll no faster than the bus carries (bus_rate.py): at a low baud rate the driver's
        copy of the profile takes the rate that fits, and the log names it."""
        link = self.profile.link
        hz, warning = poll_rate(link.poll_hz, len(self.servo_ids), link.baudrate,
                                link.return_delay_us)
        if warning is None:
            return
        log.warning("%s: %s", self.name, warning)
        self.profile = self.profile.model_copy(
            update={"link": link.model_copy(update={"poll_hz": hz})})

    async def _why_silent(self, garbled: bool = False) -> None:
        """The first servo did not answer its set-up (`garbled`: bytes came that were no
        packet, as a UART reads a servo at another rate): if no servo answers a broadcast PING
        at the profile's rate, try the other standard rates (a serial port whose rate can be
        set) and raise what was found (the arm's detail shows it as the link's last error)."""
        ping = DxlRequest(dxl.ping(dxl.BROADCAST_ID), (), True, "broadcast PING")
        garbage = self.garbage_seen
        if await self._exchange(ping, self.timeout):
            return  # some servo answers here: the set-up error stands as it is
        rate = self.profile.link.baudrate
        garbled_at = [rate] if garbled or self.garbage_seen > garbage else []
        found: dict[int, list[int]] = {}
        settable = hasattr(self.link, "baudrate") and not str(self.link.address).startswith(
            ("socket://", "loop://"))
        if settable:
            try:
                for other in (r for r in OTHER_RATES if r != rate):
                    await self._reopen_at(other)
                    garbage = self.garbage_seen
                    got = await self._exchange(ping, self.timeout)
                    if got:
                        found[other] = sorted({p.id for p in got})
                    elif self.garbage_seen > garbage:
                        garbled_at.append(other)
            finally:
                await self._reopen_at(rate)
        raise DeviceTimeout(f"{self.name}: {found_message(found, rate, garbled_at)}")

    async def _reopen_at(self, baudrate: int) -> None:
        await self.link.close()
        self.link.baudrate = baudrate  # type: ignore[attr-defined]
        await self.link.open()
        self._reset_reader()

    async def _setup_servo(self, i: int) -> None:
        """Operating mode from the profile, Profile Velocity from the joint's velocity limit
        (so the servo itself caps speed), goal = present, torque on: the servo holds where it
        is instead of jumping to a stale goal. A servo that refuses (a hardware error keeps
        torque off until a reboot) is reported, not retried: the link stays up for the
        others. A servo that does not answer at all fails the set-up (DeviceTimeout)."""
        t = mx28.TABLE
        k = self.ids.index(i) if i in self.ids else None
        joint = self.profile.joints[k] if k is not None else None
        mode = joint.operating_mode if joint is not None else self.aux_modes.get(i)
        await self._setup_exchange(DxlRequest(dxl.ping(i), (i,), what=f"PING {i}"), self.timeout)
        try:
            # Written only when it differs: a change of mode re-initialises Present Position
            # within one turn (e-manual), so a multi-turn joint is then no longer homed; and
            # only then is torque switched off (an EEPROM write needs it off), so a reconnect
            # never lets the z winch drop its load.
            if mode is not None and await self._read(i, t["operating_mode"]) != mode:
                await self._write(i, t["torque_enable"], 0)
                await self._write(i, t["operating_mode"], mode)
                if k is not None and joint is not None and joint.needs_homing \
                        and i in self.profile_velocity:
                    self.homed[k] = False
            await self._set_return_delay(i)
            # after the mode: changing Operating Mode resets Profile Velocity (e-manual)
            limit = await self._read(i, t["velocity_limit"])
            pv = (self._profile_velocity(joint, limit) if joint is not None
                  else min(self.aux_profile_velocity.get(i, 0), limit))
            if pv:
                self.profile_velocity[i] = pv
                await self._write(i, t["profile_velocity"], pv)
            await self._write(i, t["goal_position"], await self._read(i, t["present_position"]))
            if k is not None:
                self.forget_commanded([k])  # it holds where it is
            await self._write(i, t["torque_enable"], 1)
            if k is not None:
                self.note_torque([k], True)
        except DeviceError as exc:
            if isinstance(exc, CorruptReply):
                raise
            name = self.servo_name(i)
            log.warning("%s: servo %d (%s) not set up: %s", self.name, i, name, exc.detail)
            self.last_error = f"servo {i} ({name}) not set up: {exc.detail}"
        if i in self._alerts:
            await self._read_fault(i)
            self._publish_faults()

    async def _set_return_delay(self, i: int) -> None:
        """The profile's `return_delay_us` as Return Delay Time (9), where it differs and the
        torque is off. Every status packet waits that long (e-manual: "Return Delay Time");
        at the default 500 us a SYNC_READ of four servos kept the bus busy about 3 ms of each
        5 ms poll period, and a request waited for the poll in progress. EEPROM: written only
        with torque off, which a servo has after power-on; a servo holding torque (a server
        restart under a hanging winch load) keeps its value until the next power cycle."""
        us = self.profile.link.return_delay_us
        if us is None:
            return
        t = mx28.TABLE
        want = round(us / 2.0)
        if await self._read(i, t["return_delay_time"]) == want:
            return
        if await self._read(i, t["torque_enable"]):
            log.info("%s: servo %d keeps its Return Delay Time: its torque is on (an EEPROM "
                     "write needs it off)", self.name, i)
            return
        await self._write(i, t["return_delay_time"], want)

    async def _read(self, i: int, item: ControlItem) -> int:
        [p] = await self._setup_exchange(
            DxlRequest(dxl.read(i, item.address, item.size), (i,), what=f"READ {item.name}"),
            self.timeout)
        check_len(p, item.size)
        return dxl.from_bytes(p.params, item.signed)

    async def _write(self, i: int, item: ControlItem, raw: int) -> None:
        """A set-up write (idempotent: retried on a lost or corrupt reply)."""
        await self._setup_exchange(
            DxlRequest(dxl.write(i, item.address, dxl.to_bytes(raw, item.size)), (i,),
                       what=f"WRITE {item.name} to {i}"), self.timeout)

    async def _reboot(self, dxl_id: int) -> list[dxl.Packet]:
        got: list[dxl.Packet] = await self._exchange(
            DxlRequest(dxl.reboot(dxl_id), (dxl_id,), what=f"REBOOT {dxl_id}"), self.timeout)
        if dxl_id not in self.servo_ids:
            return got
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
        if dxl_id in self.ids:
            k = self.ids.index(dxl_id)
            if self.profile.joints[k].needs_homing:
                self.homed[k] = False  # a multi-turn position restarts within one turn
        await self._setup_servo(dxl_id)
        self._publish_faults()
        return got

    async def _poll(self) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        ids = self.servo_ids
        req = self._poll_request
        if req is None or req.expect != ids:  # the same bytes at every poll: built once
            req = self._poll_request = DxlRequest(
                dxl.sync_read(_POLL_ADDR, _POLL_LEN, list(ids)), ids,
                what="SYNC_READ present state")
        packets = await self._exchange(req, self.timeout)
        n = len(self.ids)
        load, vel, pos = [0] * n, [0] * n, [0] * n
        for k, p in enumerate(packets):
            check_len(p, _POLL_LEN)
            # Moving, Moving Status, Present PWM, Load, Velocity, Position (122..135)
            moving, status, _pwm, ld, v, x = _POLL_STRUCT.unpack(p.params)
            if k >= n:
                self.aux_ticks[p.id] = x
                continue
            # Moving (122) or Moving Status bit 1, "profile ongoing" (123)
            self._moving[k] = bool(moving) or bool(status & 0x02)
            load[k], vel[k], pos[k] = ld, v, x
        self._on_aux_polled()
        await self._check_faults()
        await self._check_power()
        raw = (pos, vel, load)
        known = self.converted(raw)
        if known is not None:
            return known  # the same readings (at rest): converted already
        tr = self.model.transmission
        q = tr.from_ticks(pos)
        rpm = np.array(vel, dtype=float) * _RPM_PER_UNIT
        qd = tr.velocity_from_ticks(rpm / 60.0 * self._ticks_per_rev)
        tau = np.array(load, dtype=float) * self._effort_per_load if self._sensed else None
        return self.remember_converted(raw, (q, qd, tau))

    def _repeat_ok(self) -> bool:
        """The same SYNC_READ statuses again give the same readings, moving flags and aux
        positions, while no input is held, no servo raises its Alert bit (its fault is read
        again every FAULT_REFRESH_S) and the power check is not due."""
        return not (self._dirty or self._parser.buffered or self._alerts or self._hw_errors
                    or (self.profile_velocity
                        and time.monotonic() - self._power_checked >= POWER_CHECK_S))

    def _on_aux_polled(self) -> None:  # noqa: B027 - an optional hook
        """The aux servos' `aux_ticks` were just read (a gripper publishes its opening)."""

    async def _check_power(self) -> None:
        """A servo whose Profile Velocity reads 0 where set-up wrote more has been power
        cycled (a brown-out, a loose supply): torque is off and a multi-turn joint has lost its
        count. Say so and un-home the joint; its reboot route sets it up again."""
        now = time.monotonic()
        if now - self._power_checked < POWER_CHECK_S or not self.profile_velocity:
            return
        self._power_checked = now
        ids = [i for i in self.servo_ids if self.profile_velocity.get(i)]
        pv = await self._exchange(
            DxlRequest(dxl.sync_read(mx28.TABLE["profile_velocity"].address, 4, ids),
                       tuple(ids), what="SYNC_READ profile_velocity"), self.timeout)
        for p in pv:
            if len(p.params) == 4 and dxl.from_bytes(p.params, False) == 0:
                name = self.servo_name(p.id)
                k = self.ids.index(p.id) if p.id in self.ids else None
                homing = k is not None and self.profile.joints[k].needs_homing
                del self.profile_velocity[p.id]
                if k is not None and homing:
                    self.homed[k] = False
                log.warning("%s: servo %d (%s) lost power (its RAM is back to defaults: torque "
                            "off)", self.name, p.id, name)
                self.last_error = (f"servo {p.id} ({name}) was power cycled: torque off"
                                   f"{', not homed' if homing else ''}; reboot it to "
                                   "set it up again")
                self.hub.event("power_cycled", joint=name, servo=p.id, homed=list(self.homed))

    # --------------------------------------------------------- faults

    async def _check_faults(self) -> None:
        """Read Hardware Error Status of servos whose Alert bit appeared (or stands for
        FAULT_REFRESH_S); forget the fault of a servo whose statuses no longer carry it."""
        now = time.monotonic()
        changed = False
        for i in self.servo_ids:
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
            check_len(p, _FAULT_LEN)
        except ArmError as exc:
            log.warning("%s: cannot read servo %d's hardware error: %s", self.name, i,
                        exc.detail)
            return
        self._hw_errors[i] = (p.params[-1], time.monotonic())

    def _publish_faults(self) -> None:
        faults: list[dict[str, Any]] = []
        for i in self.servo_ids:
            if i in self._hw_errors:
                raw = self._hw_errors[i][0]
                faults.append({"joint": self.servo_name(i), "servo": i,
                               "bits": decode_faults(raw), "raw": raw,
                               "advice": fault_advice(i, raw, self.name,
                                                      self.profile.falls_on(i))})
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

    async def _dispatch(self, message: Any, timeout: float) -> Any:
        if isinstance(message, _Reboot):
            return await self._reboot(message.dxl_id)
        return await self._exchange_once(message, timeout)
