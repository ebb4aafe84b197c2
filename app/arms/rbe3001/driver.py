"""RBE3001 driver: the 64-byte HID packet protocol (protocol/rbe3001.py) over any link.

Reply matching without an echo. PidServer.cpp zeroes the reply's whole float area before it
writes its readings, and the design's STATUS, GAIN and CLAW servers were written like it, so
no value we send comes back: a tag cannot be used. Other builds echo. The driver relies on
neither: one request is outstanding per link (the owner task), so a reply is the answer if
its command id is the request's (`rb.ReplyMatcher`); a frame with another id is a late
answer to an earlier request and is discarded.

What id and order cannot tell apart is a late reply with the same id as the next request.
The firmware services the HID endpoints every 1 ms (bInterval 1) and answers within one or
two intervals (design documents: round trip at most 2 ms); the timeout is 50 ms, 25 times
that. A reply that has not come by then was lost or is very late (a stalled host or
firmware). So after any timeout the link must be quiet for one timeout (`_drain`) before the
next request is written: a late reply arrives during the quiet wait and is swallowed; one
later than timeout + quiet is treated as never coming. The only way a stale reply can still
be taken is a reply delayed by more than twice the timeout (100 HID intervals): it would have
the right id and would also have to pass the checks below.

SET_GAIN and SET_CLAW "do not provide any return values" (the design document): a build may
answer zeros, the echo, other bytes or nothing. The driver waits one timeout for a reply (the
short quiet wait); none is "sent" (and the link is drained before the next request, as after
any timeout), other bytes are logged and taken: the firmware acted either way.

Stock firmware without STATUS (38). At connect the driver asks STATUS once: a board that
answers SimplePacketComs' error 99 or nothing at all has no STATUS server, and the server
cannot read the arm (a SET_PID re-sent as a poll would need a setpoint the server commanded,
and there is none at connect). The set-up fails with a reason that names the build and what to
do (`firmware_note`, in the arm's detail; the link's last error; the log, once), and is tried
again with the link's backoff.

The protocol has no checksum: a reply is refused as corrupt when floats 9-14 of a reading
changed (every build zeroes them or echoes our zeros), when an acknowledgement is neither all
zeros nor the echo, when a value is not finite or not plausible, or when a position jumped
further than the arm can move since the last reading.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections import deque
from typing import Any, Literal

import numpy as np

from app.device.driver import Driver, ReplyWait
from app.errors import CorruptReply, DeviceError, DeviceTimeout
from protocol import rbe3001 as rb

log = logging.getLogger(__name__)

#: How the firmware answered a SET_GAIN or SET_CLAW (module doc).
AckHow = Literal["acknowledged", "sent", "other"]

#: A reading may differ from the last accepted one by at most JUMP_SPEEDS x the joint's
#: velocity limit x the time since, plus JUMP_SLACK_RAD (encoder noise and averaging).
JUMP_SPEEDS = 10.0
JUMP_SLACK_RAD = 0.05
#: Longest the quiet wait after a timeout may take, in timeouts: a link that never stops
#: talking is not waited on for ever (the next request then goes out; the checks remain).
DRAIN_MAX_TIMEOUTS = 10


class Rbe3001Driver(Driver):
    """Owns an rbe3001 link; polls STATUS; sends SET_PID setpoints for motion."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._frames = rb.FrameParser()
        self._ready: deque[bytes] = deque()
        self._matcher = rb.ReplyMatcher()
        #: A request timed out: its reply may still come, so wait for quiet before the next.
        self._dirty = False
        self._last_q: np.ndarray | None = None
        #: The earliest the last accepted reading can have been taken (`time.monotonic()`):
        #: the jump check's clock (`_check_jump`).
        self._last_q_t = 0.0
        self._last_units = self.units_version  # the units `_last_q` was read in
        f = self.profile.force
        self._adc_scale = np.array(f.scale if f else [0.0] * 3)
        self._adc_offset = np.array(f.offset if f else [0.0] * 3)
        tpr = np.array([j.ticks_per_rev for j in self.profile.joints], dtype=float)
        #: Plausibility bounds for decoded values: 64 turns and 64 turns/s.
        self._max_ticks: list[float] = (64 * tpr).tolist()
        self._plausible: Any = None  # the last reply found plausible
        #: The command id the firmware last answered error 99 for (no server for it).
        self._unknown_id: int | None = None
        self.gripper = None

    # --------------------------------------------------------- pass-through

    async def status(self) -> rb.StatusReply:
        reply: rb.StatusReply = await self.submit(rb.Status())
        return reply

    async def set_pid(self, setpoints: list[tuple[float, float, float]], *,
                      hold: bool = False) -> rb.SetPidReply:
        """SET_PID: the positions are the arm's commanded state from the moment it is written
        (`note_commanded`); refused there while the estop is latched, unless it is the hold."""
        sps = tuple(rb.JointSetpoint(p, v, f) for p, v, f in setpoints)
        cmd = rb.SetPid(sps)  # type: ignore[arg-type]  # three: one per joint, from the caller
        ticks = [p for p, _v, _f in setpoints]
        reply: rb.SetPidReply = await self.submit(
            cmd, gated=not hold, on_send=lambda: self.note_commanded(ticks))
        return reply

    async def set_gain(self, axis: int, kp: float, ki: float, kd: float) -> AckHow:
        """SET_GAIN; answers how the firmware answered: `acknowledged` (zeros or the echo),
        `other` (other bytes, logged) or `sent` (no reply within the quiet wait)."""
        return _how(await self.submit(rb.SetGain(axis, kp, ki, kd), gated=True))

    async def set_claw(self, value: float) -> AckHow:
        """SET_CLAW; answers as `set_gain`."""
        how = _how(await self.submit(rb.SetClaw(value), gated=True))
        self.gripper = float(value)
        return how

    # --------------------------------------------------------- motion interface

    async def command_joints(self, q: np.ndarray, *, hold: bool = False) -> None:
        ticks = self.model.transmission.to_ticks(np.asarray(q, dtype=float))
        await self.set_pid([(float(t), 0.0, 0.0) for t in ticks], hold=hold)

    async def set_gripper(self, value: float) -> None:
        await self.set_claw(value)

    # --------------------------------------------------------- owner task

    async def _on_connected(self) -> None:
        """Ask STATUS once: a build without it is named (module doc)."""
        self._unknown_id = None
        try:
            await self._setup_exchange(_STATUS, self.timeout)
        except DeviceError as exc:
            if self._unknown_id != rb.CommandId.STATUS:
                raise
            self.firmware_note = (
                "this board's firmware has no STATUS server (38): it answered "
                f"SimplePacketComs' error {rb.ERROR_ID}. The server reads the arm with STATUS: "
                "flash the course firmware that has it (README, 'On real hardware')")
            raise DeviceError(f"{self.name}: {self.firmware_note}") from exc
        except DeviceTimeout as exc:
            self.firmware_note = (
                "the board answers nothing to STATUS (38): a firmware without the STATUS "
                "server (a build that stays silent for an unknown id), or a board that does not "
                "answer at all. Flash the course firmware that has STATUS (README, 'On real "
                "hardware') and check the USB cable")
            raise DeviceTimeout(f"{self.name}: {self.firmware_note}") from exc
        if self.firmware_note is not None:
            log.info("%s: the board answers STATUS now", self.name)
        self.firmware_note = None

    def _reset_reader(self) -> None:
        self._frames.clear()
        self._ready.clear()

    def _repeat_ok(self) -> bool:
        """The same STATUS bytes again give the same reading (the matcher's known reply, the
        converted readings kept for it) while no input is held and no quiet wait is due."""
        return not (self._dirty or self._ready or self._frames.pending
                    or self._matcher.outstanding is not None)

    def _repeated(self, at: float) -> None:
        self._last_q_t = self.read_at(at)  # as `_poll` for a known reply: the jump check's clock

    async def _drain(self) -> None:
        """After a timeout, discard input until the link has been quiet for one timeout (see
        the module doc): a reply later than that is as good as lost, one sooner is dropped
        here. Bounded by DRAIN_MAX_TIMEOUTS so a chattering link cannot stall the driver."""
        loop = asyncio.get_running_loop()
        give_up = loop.time() + DRAIN_MAX_TIMEOUTS * self.timeout
        while loop.time() < give_up:
            data = await self.link.read(min(self.timeout, max(0.0, give_up - loop.time())))
            if not data:
                break
            self.stats["stale_replies"] += 1
        self._reset_reader()
        self._dirty = False

    async def _poll(self) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        asked = time.monotonic()
        reply: rb.StatusReply = await self._exchange(_STATUS, self.timeout)
        read_at = self.read_at()
        # The reading was taken between the ask and the read (one read ahead: before its read,
        # so no later than that): a process held up between the two has the arm's motion
        # over the hold in the next reading, and the jump check counts the hold in its time.
        taken = min(asked, read_at)
        known = self.converted(reply)
        if known is not None:
            # The matcher's reply for the same bytes (an arm at rest): the same readings,
            # converted already (read-only arrays); the jump check's clock moves on.
            self._last_q_t = taken
            return known
        tr = self.model.transmission
        q = tr.from_ticks(np.array(reply.position_ticks, dtype=float))
        self._check_jump(q, read_at, taken)
        qd = tr.velocity_from_ticks(np.array(reply.velocity_ticks_s, dtype=float))
        tau = None
        if self.profile.force is not None:
            tau = self._adc_scale * (np.array(reply.strain_adc, dtype=float) - self._adc_offset)
        return self.remember_converted(reply, (q, qd, tau))

    async def _exchange(self, message: Any, timeout: float) -> Any:
        if self._dirty:
            await self._drain()
        packet = self._matcher.request(message)
        name = _command_name(message)
        # one call where the link can (a link with its own thread: the reply read with the
        # write, or read ahead on the poll schedule); else the write, and the reads below
        sent = await self.link.transact(packet, rb.PACKET_SIZE, timeout)
        self._take(sent.data)
        wait = ReplyWait(sent.deadline)
        while True:
            left = 0.0 if self._ready else wait.left()
            if left is None:
                self._matcher.cancel()
                self._dirty = True
                if isinstance(message, rb.SetGain | rb.SetClaw):  # no return values: sent
                    self.stats["unanswered"] = self.stats.get("unanswered", 0) + 1
                    return _SENT
                raise DeviceTimeout(f"{self.name}: no reply to {name} "
                                    f"within {timeout * 1000:.0f} ms")
            frame = await self._next_frame(left)
            if frame is None:
                wait.found(False)
                continue
            stale = self._matcher.stale
            try:
                reply = self._matcher.match(frame)
            except rb.UnknownToFirmware as exc:
                self._unknown_id = exc.command_id
                raise DeviceError(f"{self.name}: {exc} ({name}): this firmware build does not "
                                  "serve it") from None
            except rb.DecodeError as exc:
                self._matcher.cancel()
                self.stats["corrupt"] += 1
                raise CorruptReply(f"{self.name}: reply to {name}: {exc}") from None
            if reply is None:
                self.stats["stale_replies"] += self._matcher.stale - stale
                continue
            if isinstance(reply, rb.Ack) and reply.other:
                self.stats["other_replies"] = self.stats.get("other_replies", 0) + 1
                log.warning("%s: %s answered bytes that are neither zeros nor the echo (%s): "
                            "taken, the command carries no return value", self.name, name,
                            frame[4:40].hex())
            self._check_plausible(reply)
            return reply

    async def _next_frame(self, timeout: float) -> bytes | None:
        if self._ready:  # a byte stream may carry several packets in one read
            return self._ready.popleft()
        self._take(await self.link.read(timeout))
        return self._ready.popleft() if self._ready else None

    def _take(self, data: bytes) -> None:
        """Bytes read: the whole packets in them, ready in order."""
        if not data:
            return
        if self.link.packetized:
            frame = self._frames.feed_report(data)
            if frame is not None:
                self._ready.append(frame)
        else:
            self._ready.extend(self._frames.feed(data))

    def _check_jump(self, q: np.ndarray, now: float | None = None,
                    taken: float | None = None) -> None:
        """With no checksum, one changed byte in a reading can stay plausible (a soak caught
        834 ticks read as 1052). A joint cannot move more than JUMP_SPEEDS times its velocity
        limit (plus JUMP_SLACK_RAD) since the last reading accepted: such a reading is refused
        as corrupt. The bound grows with the time since, so a real fast move is accepted late,
        never refused for ever. `now`: the latest the reading can have been taken
        (`time.monotonic()`; for replies read ahead on the poll thread, their read time: a
        batch of them is checked back to back, and the time between them is the time between
        their readings); None: now. `taken`: the earliest (when it was asked for; default
        `now`), kept as the next check's start: the time since is from the earliest the last
        reading can have been taken to the latest this one can, so a process held up between
        a reading and its read (a loaded machine: the arm moved on meanwhile) does not read
        the arm's motion over the hold as a jump (a clean clone's run refused one so,
        session 31)."""
        if now is None:
            now = time.monotonic()
        if taken is None:
            taken = now
        if self._last_units != self.units_version:  # a calibration moved the zero: a new start
            self._last_q, self._last_units = None, self.units_version
        if self._last_q is not None and q.tolist() != self._last_q.tolist():  # (at rest: equal)
            since = max(0.0, now - self._last_q_t)
            bound = JUMP_SPEEDS * self.model.vmax * since + JUMP_SLACK_RAD
            jump = np.abs(q - self._last_q)
            if np.any(jump > bound):
                k = int(np.argmax(jump - bound))
                self.stats["corrupt"] += 1
                raise CorruptReply(f"{self.name}: {self.model.names[k]} reading jumped "
                                   f"{jump[k]:.3f} rad since the last one, more than the arm "
                                   f"can move ({bound[k]:.3f} rad): a corrupted reply")
        self._last_q, self._last_q_t = q, taken

    def _check_plausible(self, reply: Any) -> None:
        pos = getattr(reply, "position_ticks", None)
        if pos is None or reply is self._plausible:  # (the matcher's reply for the same bytes)
            return
        vel, adc = reply.velocity_ticks_s, reply.strain_adc
        # Three values each, at every poll: plain floats, not numpy (the decoder already
        # refused NaN and infinity).
        if (any(abs(p) > m or abs(v) > m for p, v, m in zip(pos, vel, self._max_ticks, strict=True))
                or min(adc) < -1.0 or max(adc) > 2.0):
            self.stats["corrupt"] += 1
            raise CorruptReply(f"{self.name}: implausible values in reply "
                               f"(positions {list(pos)}, velocities {list(vel)}, adc {list(adc)})")
        self._plausible = reply


_STATUS = rb.Status()
#: A SET_GAIN / SET_CLAW that got no reply within the quiet wait (module doc).
_SENT = object()


def _how(reply: object) -> AckHow:
    if reply is _SENT:
        return "sent"
    return "other" if isinstance(reply, rb.Ack) and reply.other else "acknowledged"


def _command_name(message: Any) -> str:
    return {"SetPid": "SET_PID", "Status": "STATUS", "SetGain": "SET_GAIN",
            "SetClaw": "SET_CLAW"}[type(message).__name__]
