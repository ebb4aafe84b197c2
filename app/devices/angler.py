"""Angler driver: four Dynamixel MX-28 servos on Protocol 2.0 (protocol/dynamixel.py).

Polling is one SYNC_READ of Present Load, Velocity and Position (addresses 126-135) for every
servo; motion setpoints are one SYNC_WRITE of Goal Position. Before each request the input is
drained (as DynamixelSDK flushes), and replies are accepted only from the ids asked, in order,
as status packets; a CRC failure fails the request as corrupt, a non-zero error byte fails it as
a device error with the e-manual's meaning.
"""

from __future__ import annotations

import asyncio
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from app.devices.base import Driver
from app.errors import CorruptReply, DeviceError, DeviceTimeout, NoGripper
from protocol import dynamixel as dxl
from protocol import mx28

#: Present Load (2) + Present Velocity (4) + Present Position (4), e-manual MX-28 (2.0).
_POLL_ADDR = mx28.TABLE["present_load"].address
_POLL_LEN = 10
#: 0.229 rpm per Present Velocity unit (e-manual MX-28 (2.0), address 128).
_RPM_PER_UNIT = 0.229


@dataclass(frozen=True)
class DxlRequest:
    packet: bytes
    expect: tuple[int, ...]  # ids expected to answer, in order; () for none
    broadcast_ping: bool = False
    what: str = ""


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

    # --------------------------------------------------------- pass-through

    async def ping(self, dxl_id: int | None) -> list[tuple[int, int, int]]:
        if dxl_id is None:
            req = DxlRequest(dxl.ping(dxl.BROADCAST_ID), (), True, "broadcast PING")
        else:
            req = DxlRequest(dxl.ping(dxl_id), (dxl_id,), False, f"PING {dxl_id}")
        packets = await self.submit(req)
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

    async def reboot(self, dxl_id: int) -> None:
        await self.submit(DxlRequest(dxl.reboot(dxl_id), (dxl_id,), what=f"REBOOT {dxl_id}"))

    # --------------------------------------------------------- motion interface

    async def command_joints(self, q: np.ndarray) -> None:
        ticks = self.model.transmission.to_ticks(np.asarray(q, dtype=float))
        await self.sync_write(mx28.TABLE["goal_position"],
                              {i: int(round(t)) for i, t in zip(self.ids, ticks, strict=True)})

    async def set_gripper(self, value: float) -> None:
        raise NoGripper(f"{self.name} has a passive magnet, not an actuated gripper")

    # --------------------------------------------------------- owner task

    def _reset_reader(self) -> None:
        self._parser = dxl.Parser()
        self._dirty = True

    def _profile_velocity(self, joint: Any) -> int:
        """Profile Velocity (0.229 rpm units) for a joint's velocity limit, with 20 % headroom
        so the servo follows the planned trajectory but never runs away from it."""
        per_rev = joint.lead_m if joint.lead_m else 2 * math.pi
        rpm = joint.max_velocity / per_rev * 60.0 * 1.2
        return max(1, math.ceil(rpm / _RPM_PER_UNIT))

    async def _on_connected(self) -> None:
        """Torque off, operating mode from the profile, Profile Velocity from the joint's
        velocity limit (so the servo itself caps speed), goal = present, torque on: the arm
        holds where it is instead of jumping to a stale goal."""
        t = mx28.TABLE
        for joint, i in zip(self.profile.joints, self.ids, strict=True):
            await self._setup_exchange(DxlRequest(dxl.ping(i), (i,), what=f"PING {i}"),
                                       self.timeout)
            await self._write(i, t["torque_enable"], 0)
            if joint.operating_mode is not None:
                await self._write(i, t["operating_mode"], joint.operating_mode)
            # after the mode: changing Operating Mode resets Profile Velocity (e-manual)
            await self._write(i, t["profile_velocity"], self._profile_velocity(joint))
            [p] = await self._setup_exchange(
                DxlRequest(dxl.read(i, t["present_position"].address, 4), (i,),
                           what="READ present_position"), self.timeout)
            await self._write(i, t["goal_position"], dxl.from_bytes(p.params, True))
            await self._write(i, t["torque_enable"], 1)

    async def _write(self, i: int, item: mx28.ControlItem, raw: int) -> None:
        """A set-up write (idempotent: retried on a lost or corrupt reply)."""
        await self._setup_exchange(
            DxlRequest(dxl.write(i, item.address, dxl.to_bytes(raw, item.size)), (i,),
                       what=f"WRITE {item.name}"), self.timeout)

    async def _poll(self) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        packets = await self._exchange(
            DxlRequest(dxl.sync_read(_POLL_ADDR, _POLL_LEN, list(self.ids)), self.ids,
                       what="SYNC_READ present state"), self.timeout)
        load = np.empty(len(self.ids))
        vel = np.empty(len(self.ids))
        pos = np.empty(len(self.ids))
        for k, p in enumerate(packets):
            _check_len(p, _POLL_LEN)
            load[k] = dxl.from_bytes(p.params[0:2], True)
            vel[k] = dxl.from_bytes(p.params[2:6], True)
            pos[k] = dxl.from_bytes(p.params[6:10], True)
        tr = self.model.transmission
        q = tr.from_ticks(pos)
        qd = tr.velocity_from_ticks(vel * _RPM_PER_UNIT / 60.0 * self._ticks_per_rev)
        tau = load * self._effort_per_load if self._sensed else None
        return q, qd, tau

    async def _exchange(self, message: Any, timeout: float) -> Any:
        try:
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
                if ev.error:
                    raise DeviceError(f"{self.name}: {req.what}: servo {ev.id}: "
                                      f"{dxl.describe_error(ev.error)}")
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
