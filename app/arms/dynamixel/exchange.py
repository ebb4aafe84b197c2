"""One owner task on a Dynamixel Protocol 2.0 bus: requests, replies and the pass-through
(PING, READ, WRITE, SYNC_READ, SYNC_WRITE by control-table item).

Before a request that follows a failed one the input is drained, and replies are accepted
only from the ids asked, in order, as status packets of the length the request asks for (a
READ's or SYNC_READ's the length read, a PING's 3, a write's none: `dxl.status_params`):
a status of another length is an earlier exchange's, late (the drain cannot tell a bus that
is quiet from one whose bytes a busy machine hands over late), and is passed over as stale;
a CRC failure fails the request as corrupt. A status whose error byte has only the Alert bit
(0x80) set is a valid reply, its data good; the servo is noted in `_alerts` (the chain driver
reads its Hardware Error Status). Error bits 0-6 (instruction, CRC, data range, ...) fail the
request, whatever the status's length.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from app.device.driver import Driver, ReplyWait
from app.errors import CorruptReply, DeviceError, DeviceTimeout
from protocol import dynamixel as dxl
from protocol.mx28 import ControlItem


@dataclass(frozen=True)
class DxlRequest:
    packet: bytes
    expect: tuple[int, ...]  # ids expected to answer, in order; () for none
    broadcast_ping: bool = False
    what: str = ""
    #: Poll right after this request is answered (a write whose effect the samples should
    #: show without waiting for the schedule: up to one poll period, 5 ms at 200 Hz).
    poll_after: bool = False
    #: ... but no sooner than this after the write, s: when the effect can first show (a
    #: goal's first encoder tick, `_effect_delay`), else the poll reads the sample before.
    poll_delay_s: float = 0.0
    #: A WRITE of the ID item: its new ID, from which the status may come in place of the
    #: old one's. ROBOTIS's own device library answers from the new ID (Dynamixel2Arduino,
    #: `Slave::processInstWrite`: the ID item written, then `txStatusPacket(id_, ...)`); which
    #: one an MX-28's firmware uses is not in the e-manual, so either is the status.
    renamed_to: int | None = None
    #: The parameter bytes of each status it asks for (`dxl.status_params`): read off the
    #: packet once, not at every exchange (the poll's request is built once and sent 200
    #: times a second).
    status_params: int = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "status_params", dxl.status_params(self.packet))


class DynamixelBusDriver(Driver):
    """The bus side of a Dynamixel arm's driver; subclasses poll and set up the servos."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._parser = dxl.Parser()
        self._dirty = False
        #: Servos whose last status carried the Alert bit.
        self._alerts: set[int] = set()
        #: Bytes skipped as no packet's (the parser's "garbage"): what a UART at another rate
        #: than a servo's reads of its replies (app/sim/uart.py); the connect scan tells it.
        self.garbage_seen = 0

    @property
    def servo_ids(self) -> tuple[int, ...]:
        """The arm's own servos (silence from one of them is an error, not an absence)."""
        return ()

    # --------------------------------------------------------- pass-through

    async def ping(self, dxl_id: int | None) -> list[tuple[int, int, int]]:
        if dxl_id is None:
            req = DxlRequest(dxl.ping(dxl.BROADCAST_ID), (), True, "broadcast PING")
        else:
            req = DxlRequest(dxl.ping(dxl_id), (dxl_id,), False, f"PING {dxl_id}")
        try:
            packets = await self.submit(req)
        except DeviceTimeout:
            if dxl_id is not None and dxl_id in self.servo_ids:
                # One of this arm's own servos: silence is a lost reply or a fault of the
                # link, not an absent servo; saying "absent" would be a wrong answer.
                raise
            return []  # no servo with that id on this arm: an answer, not a failure (API.md)
        return [(p.id, dxl.from_bytes(p.params[0:2], False), p.params[2]) for p in packets]

    async def read_register(self, dxl_id: int, item: ControlItem) -> int:
        [p] = await self.submit(DxlRequest(dxl.read(dxl_id, item.address, item.size), (dxl_id,),
                                           what=f"READ {item.name} from {dxl_id}"))
        check_len(p, item.size)
        return dxl.from_bytes(p.params, item.signed)

    async def write_register(self, dxl_id: int, item: ControlItem, raw: int, *,
                             gated: bool = True) -> None:
        """WRITE one item; `gated` (all but the safe writes: torque off, the LED) is refused
        in the owner task while the estop is latched."""
        data = dxl.to_bytes(raw, item.size)
        expect = () if dxl_id == dxl.BROADCAST_ID else (dxl_id,)
        values = {dxl_id: raw}
        await self.submit(DxlRequest(dxl.write(dxl_id, item.address, data), expect,
                                     what=f"WRITE {item.name} to {dxl_id}", poll_after=True,
                                     poll_delay_s=self._effect_delay(item, values),
                                     renamed_to=raw if item.name == "id" else None),
                          gated=gated, on_send=lambda: self._note_sent(item, values))
        self._note_written(item, values)

    async def sync_read(self, item: ControlItem, ids: list[int]) -> dict[int, int]:
        packets = await self.submit(DxlRequest(dxl.sync_read(item.address, item.size, ids),
                                               tuple(ids), what=f"SYNC_READ {item.name}"))
        out = {}
        for p in packets:
            check_len(p, item.size)
            out[p.id] = dxl.from_bytes(p.params, item.signed)
        return out

    async def sync_write(self, item: ControlItem, values: dict[int, int], *,
                         gated: bool = True) -> None:
        """SYNC_WRITE one item; `gated` as for `write_register` (the estop's hold is not)."""
        data = {i: dxl.to_bytes(v, item.size) for i, v in values.items()}
        await self.submit(DxlRequest(dxl.sync_write(item.address, item.size, data), (),
                                     what=f"SYNC_WRITE {item.name}"),
                          gated=gated, on_send=lambda: self._note_sent(item, values))
        self._note_written(item, values)

    def _effect_delay(self, item: ControlItem, values: dict[int, int]) -> float:
        """How long after a write of `values` to `item` a poll can show its effect, s (a
        hook: the chain driver gives a goal's first tick of motion; here none)."""
        return 0.0

    def _note_written(self, item: ControlItem, values: dict[int, int]) -> None:  # noqa: B027
        """A pass-through write went out (a hook: the chain driver tracks Profile Velocity)."""

    def _note_sent(self, item: ControlItem, values: dict[int, int]) -> None:  # noqa: B027
        """A write is being sent, in the owner task (a hook: the chain driver notes the goal
        positions of its joints as the arm's commanded state)."""

    # --------------------------------------------------------- exchanges

    def _reset_reader(self) -> None:
        self._parser = dxl.Parser()
        self._dirty = True

    async def _exchange(self, message: Any, timeout: float) -> Any:
        try:
            return await self._dispatch(message, timeout)
        except BaseException:
            self._dirty = True  # whatever failed may have left bytes behind
            raise

    async def _dispatch(self, message: Any, timeout: float) -> Any:
        """One message in the owner task: a DxlRequest (subclasses add their own kinds)."""
        return await self._exchange_once(message, timeout)

    async def _exchange_once(self, req: DxlRequest, timeout: float) -> list[dxl.Packet]:
        if self._dirty:
            await self._drain()
        # one call where the link can (a link with its own thread: the statuses read with the
        # write, or read ahead on the poll schedule); else the write, and the reads below
        sent = await self.link.transact(req.packet, _status_bytes(req), timeout)
        if not req.expect and not req.broadcast_ping:
            return []
        if sent.data:
            self._parser.feed(sent.data)
        wait = ReplyWait(sent.deadline)
        got: list[dxl.Packet] = []
        size = req.status_params
        while True:
            while (ev := self._parser.next_event()) is not None:
                if isinstance(ev, dxl.ParseError):
                    if ev.kind == "garbage":
                        self.garbage_seen += 1
                        continue
                    self.stats["corrupt"] += 1
                    raise CorruptReply(f"{self.name}: {req.what}: {ev.kind}: {ev.detail}")
                if ev.instruction != dxl.Instruction.STATUS:
                    continue  # our own echo on a half-duplex adapter, or noise
                if req.broadcast_ping:
                    got.append(ev)
                    continue
                error = ev.error or 0
                if (len(got) >= len(req.expect)
                        or (ev.id != req.expect[len(got)] and ev.id != req.renamed_to)
                        or (len(ev.params) != size and not error & ~dxl.ALERT_BIT)):
                    self.stats["stale_replies"] += 1
                    continue
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
            left = wait.left()
            if left is None:
                if req.broadcast_ping:
                    return sorted(got, key=lambda p: p.id)
                missing = req.expect[len(got):]
                raise DeviceTimeout(f"{self.name}: {req.what}: no status from id "
                                    f"{', '.join(map(str, missing))} within "
                                    f"{timeout * 1000:.0f} ms")
            data = await self.link.read(left)
            if data:
                self._parser.feed(data)
            wait.found(bool(data))

    async def _drain(self) -> None:
        """After a failed exchange, discard input until the bus has been quiet for one timeout
        (DynamixelSDK flushes before every send instead): status packets carry no request tag,
        so this is what keeps a late reply from answering the next request. After a clean
        exchange every expected byte was consumed, and nothing is waited for."""
        while await self.link.read(self.timeout):
            pass
        self._parser = dxl.Parser()
        self._dirty = False


def _status_bytes(req: DxlRequest) -> int:
    """The bytes of the statuses `req` expects, unstuffed (a status packet is 11 bytes and its
    parameters, `status_params`); 0 for no status or a broadcast PING. A hint: more bytes
    (stuffing) are read on."""
    if not req.expect or req.broadcast_ping:
        return 0
    return len(req.expect) * (11 + req.status_params)


def check_len(p: dxl.Packet, size: int) -> None:
    if len(p.params) != size:
        raise CorruptReply(f"servo {p.id} answered {len(p.params)} bytes, expected {size}")
