"""RBE3001 driver: the 64-byte HID packet protocol (protocol/rbe3001.py) over any link.

Reply matching: the firmware sends the request buffer back with only the floats its server
writes replaced (STATUS writes floats 0-8; SET_GAIN and SET_CLAW write none; PidServer zeroes
the buffer and writes floats 0-8), so float 14 carries a request tag and floats 9-13 zeros. A
reply whose id or tag is not the outstanding request's is stale (a late answer to an earlier
request) and is discarded. SET_PID replies carry no tag, so after a SET_PID times out the
link must be quiet for one timeout before the next SET_PID: a late reply cannot complete the
wrong request. The protocol has no checksum: a reply is
refused as corrupt when its echoed zeros changed, or a value is not finite or not plausible.
"""

from __future__ import annotations

import asyncio
import struct
import time
from typing import Any

import numpy as np

from app.devices.base import Driver
from app.errors import CorruptReply, DeviceTimeout
from protocol import rbe3001 as rb

_TAG = struct.Struct("<f")
#: A reading may differ from the last accepted one by at most JUMP_SPEEDS x the joint's
#: velocity limit x the time since, plus JUMP_SLACK_RAD (encoder noise and averaging).
JUMP_SPEEDS = 10.0
JUMP_SLACK_RAD = 0.05
_TAG_OFFSET = 4 + 14 * 4
_ECHO = slice(4 + 9 * 4, 4 + 14 * 4)  # floats 9-13, sent as zeros and echoed
_TAG_MOD = 1 << 20  # exactly representable in float32


class Rbe3001Driver(Driver):
    """Owns an rbe3001 link; polls STATUS; sends SET_PID setpoints for motion."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._tag = 0
        self._buf = bytearray()
        self._dirty = False
        self._last_q: np.ndarray | None = None
        self._last_q_t = 0.0
        f = self.profile.force
        self._adc_scale = np.array(f.adc_scale if f else [0.0] * 3)
        self._adc_offset = np.array(f.adc_offset if f else [0.0] * 3)
        tpr = np.array([j.ticks_per_rev for j in self.profile.joints], dtype=float)
        #: Plausibility bounds for decoded values: 64 turns and 64 turns/s.
        self._max_ticks = 64 * tpr
        self.gripper = None

    # --------------------------------------------------------- pass-through

    async def status(self) -> rb.StatusReply:
        return await self.submit(rb.Status())  # type: ignore[no-any-return]

    async def set_pid(self, setpoints: list[tuple[float, float, float]]) -> rb.SetPidReply:
        cmd = rb.SetPid(tuple(rb.JointSetpoint(p, v, f) for p, v, f in setpoints))  # type: ignore[arg-type]
        return await self.submit(cmd)  # type: ignore[no-any-return]

    async def set_gain(self, axis: int, kp: float, ki: float, kd: float) -> None:
        await self.submit(rb.SetGain(axis, kp, ki, kd))

    async def set_claw(self, value: float) -> None:
        await self.submit(rb.SetClaw(value))
        self.gripper = float(value)

    # --------------------------------------------------------- motion interface

    async def command_joints(self, q: np.ndarray) -> None:
        ticks = self.model.transmission.to_ticks(np.asarray(q, dtype=float))
        await self.set_pid([(float(t), 0.0, 0.0) for t in ticks])

    async def set_gripper(self, value: float) -> None:
        await self.set_claw(value)

    # --------------------------------------------------------- owner task

    def _reset_reader(self) -> None:
        self._buf.clear()

    async def _drain(self) -> None:
        """After a timeout, discard input until the link has been quiet for one timeout: a reply
        later than that is as good as lost, and one sooner is swallowed here."""
        while await self.link.read(self.timeout):
            pass
        self._buf.clear()
        self._dirty = False

    async def _poll(self) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        reply: rb.StatusReply = await self._exchange(rb.Status(), self.timeout)
        tr = self.model.transmission
        q = tr.from_ticks(np.array(reply.position_ticks, dtype=float))
        self._check_jump(q)
        qd = tr.velocity_from_ticks(np.array(reply.velocity_ticks_s, dtype=float))
        tau = None
        if self.profile.force is not None:
            tau = self._adc_scale * (np.array(reply.strain_adc, dtype=float) - self._adc_offset)
        return q, qd, tau

    async def _exchange(self, message: Any, timeout: float) -> Any:
        self._tag = (self._tag + 1) % _TAG_MOD
        packet = bytearray(rb.encode_command(message))
        packet[_TAG_OFFSET:_TAG_OFFSET + 4] = _TAG.pack(float(self._tag))
        want_id = int(rb.CommandId[_command_name(message)])
        tags = (float(self._tag), 0.0) if want_id == rb.CommandId.SET_PID else (float(self._tag),)
        if self._dirty and want_id == rb.CommandId.SET_PID:
            await self._drain()
        await self.link.write(bytes(packet))
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout
        while True:
            left = deadline - loop.time()
            if left <= 0:
                self._dirty = self._dirty or want_id == rb.CommandId.SET_PID
                raise DeviceTimeout(f"{self.name}: no reply to {_command_name(message)} "
                                    f"within {timeout * 1000:.0f} ms")
            frame = await self._next_frame(left)
            if frame is None:
                continue
            rid = int.from_bytes(frame[0:4], "little")
            tag = _TAG.unpack_from(frame, _TAG_OFFSET)[0]
            if rid != want_id or tag not in tags:
                self.stats["stale_replies"] += 1
                continue
            if want_id in _ECHOED and frame[4:_TAG_OFFSET] != packet[4:_TAG_OFFSET]:
                self.stats["corrupt"] += 1
                raise CorruptReply(f"{self.name}: reply to {_command_name(message)} is not the "
                                   "echo of the request")
            if frame[_ECHO] != bytes(20):
                self.stats["corrupt"] += 1
                raise CorruptReply(f"{self.name}: reply to {_command_name(message)} corrupted "
                                   "(echoed bytes changed)")
            try:
                reply = rb.decode_reply(message, frame)
            except rb.DecodeError as exc:
                self.stats["corrupt"] += 1
                raise CorruptReply(f"{self.name}: {exc}") from None
            self._check_plausible(reply)
            return reply

    async def _next_frame(self, timeout: float) -> bytes | None:
        if self.link.packetized:
            data = await self.link.read(timeout)
            if not data:
                return None
            return bytes(data[: rb.PACKET_SIZE]) if len(data) >= rb.PACKET_SIZE else None
        while len(self._buf) < rb.PACKET_SIZE:
            data = await self.link.read(timeout)
            if not data:
                return None
            self._buf.extend(data)
        # resynchronise a byte stream on a known command id
        while len(self._buf) >= rb.PACKET_SIZE:
            rid = int.from_bytes(self._buf[0:4], "little")
            if rid in _KNOWN_IDS:
                frame = bytes(self._buf[: rb.PACKET_SIZE])
                del self._buf[: rb.PACKET_SIZE]
                return frame
            del self._buf[0]
        return None

    def _check_jump(self, q: np.ndarray) -> None:
        """With no checksum, one changed byte in a reading can stay plausible (a soak caught
        834 ticks read as 1052). A joint cannot move more than JUMP_SPEEDS times its velocity
        limit (plus JUMP_SLACK_RAD) since the last reading accepted: such a reading is refused
        as corrupt. The bound grows with the time since, so a real fast move is accepted late,
        never refused for ever."""
        now = time.monotonic()
        if self._last_q is not None:
            bound = JUMP_SPEEDS * self.model.vmax * (now - self._last_q_t) + JUMP_SLACK_RAD
            jump = np.abs(q - self._last_q)
            if np.any(jump > bound):
                k = int(np.argmax(jump - bound))
                self.stats["corrupt"] += 1
                raise CorruptReply(f"{self.name}: {self.model.names[k]} reading jumped "
                                   f"{jump[k]:.3f} rad since the last one, more than the arm "
                                   f"can move ({bound[k]:.3f} rad): a corrupted reply")
        self._last_q, self._last_q_t = q, now

    def _check_plausible(self, reply: Any) -> None:
        pos = getattr(reply, "position_ticks", None)
        if pos is None:
            return
        vel = np.abs(np.array(reply.velocity_ticks_s, dtype=float))
        adc = np.array(reply.strain_adc, dtype=float)
        if (np.any(np.abs(np.array(pos)) > self._max_ticks) or np.any(vel > self._max_ticks)
                or np.any(adc < -1.0) or np.any(adc > 2.0)):
            self.stats["corrupt"] += 1
            raise CorruptReply(f"{self.name}: implausible values in reply "
                               f"(positions {list(pos)}, velocities {list(vel)}, adc {list(adc)})")


_KNOWN_IDS = {int(c) for c in rb.CommandId}
#: Commands whose reply is the request sent back unchanged (no reply values).
_ECHOED = {int(rb.CommandId.SET_GAIN), int(rb.CommandId.SET_CLAW)}


def _command_name(message: Any) -> str:
    return {"SetPid": "SET_PID", "Status": "STATUS", "SetGain": "SET_GAIN",
            "SetClaw": "SET_CLAW"}[type(message).__name__]
