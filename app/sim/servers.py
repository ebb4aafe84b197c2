"""Serve any SimDevice over a real byte stream: a pseudo-terminal or a TCP socket.

This lets unmodified host software (DynamixelSDK, pyserial, our serial link) talk to a
simulator exactly as to hardware: `serve_pty` makes a path that opens like /dev/ttyUSB0,
`serve_tcp` a `socket://host:port` endpoint. On a pty the host's termios baud rate reaches a
device that models it (`set_host_baudrate`: a Dynamixel bus, whose servos at another rate
read the host's bytes as a UART at their rate does, app/sim/uart.py); a socket carries none.
Host bytes go to `device.receive(data, now)`;
each reply is written `delay` seconds after `now`, strictly in order (a FIFO with one
writer, so a later reply never overtakes an earlier one). Packetized devices (HID-style,
64-byte packets) get the host's stream cut into 64-byte packets. A physics tick task calls
`device.advance(now)` every `tick_s` so state evolves between requests. `now` is
`time.monotonic()` in seconds.

The `armserver sim` command that serves a device this way is app/sim/serve.py.
"""

from __future__ import annotations

import asyncio
import contextlib
import fcntl
import logging
import os
import sys
import termios
import time
import tty
from collections import deque
from collections.abc import Callable, Sequence
from pathlib import Path

from app.config import FaultConfig
from app.runtime.tasks import cancel_and_wait
from app.sim.base import SimDevice
from app.sim.faults import ReplyFaults

#: The simulator's logger, as before the servers had a module of their own.
log = logging.getLogger("app.sim.serve")

PACKET_SIZE = 64  # host packet size of packetized devices (rbe3001 HID reports), bytes
TICK_S = 0.01  # physics tick, s: 100 Hz keeps Present* fresh between requests
REPLY_BACKLOG = 1024  # replies waiting to be written; beyond this they are dropped (logged)
READ_CHUNK = 4096  # bytes per read from the pty or socket
#: termios speed constants (tcgetattr's ispeed) -> bit/s, for the rates this platform has.
_TERMIOS_RATES = {getattr(termios, f"B{r}"): r for r in (
    9600, 19200, 38400, 57600, 115200, 230400, 460800, 500000, 576000, 921600, 1000000,
    2000000, 3000000, 4000000) if hasattr(termios, f"B{r}")}


#: Linux's TCGETS2 (asm-generic ioctls: _IOR('T', 0x2A, struct termios2)), and where
#: struct termios2 keeps c_ispeed: after four flags, c_line and 19 control characters.
_TCGETS2 = 0x802C542A
_ISPEED_OFFSET = 36


def pty_baudrate(fd: int) -> int:
    """The input baud rate the host set on a pty, in bit/s: the speed itself where Linux keeps
    it (struct termios2, which holds any rate, such as 4,500,000, that pyserial sets with
    BOTHER), else the termios constant's; 0 for a rate it cannot tell."""
    if sys.platform.startswith("linux"):
        buf = bytearray(64)
        try:
            fcntl.ioctl(fd, _TCGETS2, buf)
            speed = int.from_bytes(buf[_ISPEED_OFFSET:_ISPEED_OFFSET + 4], sys.byteorder)
            if speed:
                return speed
        except OSError:
            pass
    try:
        return _TERMIOS_RATES.get(termios.tcgetattr(fd)[4], 0)
    except termios.error:
        return 0


class _Pump:
    """Host bytes -> device -> timed, ordered replies through `write`.

    Replies wait in a FIFO of (due, bytes) with one timer armed for its head (`call_at`): no
    task and no queue hand-off per reply, which a simulator serving many arms at 500 Hz each
    pays for every request (bench/lab.py). Due times never decrease (latency delays every
    reply alike), so writing the head first keeps the order."""

    def __init__(self, device: SimDevice, write: Callable[[bytes], None],
                 faults: ReplyFaults | None = None) -> None:
        self.device = device
        self._write = write
        self.faults = faults or ReplyFaults()
        self._last_due = 0.0
        self._pending = bytearray()
        self._due: deque[tuple[float, bytes]] = deque()
        self._loop = asyncio.get_running_loop()
        self._timer: asyncio.TimerHandle | None = None
        self._closed = False

    def on_data(self, data: bytes) -> None:
        if self._closed:
            return
        now = time.monotonic()
        chunks = [data]
        if self.device.packetized:
            self._pending += data
            n = len(self._pending) // PACKET_SIZE * PACKET_SIZE
            chunks = [bytes(self._pending[k:k + PACKET_SIZE]) for k in range(0, n, PACKET_SIZE)]
            del self._pending[:n]
        for chunk in chunks:
            for delay, reply in self.device.receive(chunk, now):
                out = self.faults.apply(reply)
                if out is None:
                    continue
                if len(self._due) >= REPLY_BACKLOG:
                    log.warning("reply backlog full (%d); reply dropped", REPLY_BACKLOG)
                    continue
                # latency delays every reply alike: never reordered
                self._last_due = max(self._last_due, now + delay + self.faults.latency_s)
                self._due.append((self._last_due, out))
        if self._due and self._timer is None:
            # the loop's clock is time.monotonic(), as `now` above
            self._timer = self._loop.call_at(self._due[0][0], self._flush)

    def _flush(self) -> None:
        """Write every reply now due, in order; arm the timer for the next one."""
        self._timer = None
        now = self._loop.time()
        while self._due and self._due[0][0] <= now + 1e-6:
            reply = self._due.popleft()[1]
            try:
                self._write(reply)
            except OSError as exc:
                log.warning("reply not written: %s", exc)
        if self._due:
            self._timer = self._loop.call_at(self._due[0][0], self._flush)

    def close(self) -> None:
        """Send nothing more: the replies waiting are dropped (the connection is gone)."""
        self._closed = True
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        self._due.clear()


async def tick_all(devices: Sequence[SimDevice], period: float) -> None:
    """Advance every device's physics each `period` s (one task for a process's devices)."""
    while True:
        now = time.monotonic()
        for device in devices:
            device.advance(now)
        await asyncio.sleep(period)


class PtyServer:
    """A device behind a pseudo-terminal; `link_path` is a symlink to the slave tty."""

    def __init__(self, device: SimDevice, link_path: str | os.PathLike[str],
                 tick_s: float | None = TICK_S, faults: FaultConfig | None = None,
                 seed: int | None = 0) -> None:
        self.device = device
        self.faults = ReplyFaults(faults, seed)
        self.link_path = Path(link_path)
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)  # at once: a cooked pty echoes and turns LF into CRLF
        os.set_blocking(self.master, False)
        self.tty_name = os.ttyname(self.slave)
        if self.link_path.is_symlink():
            self.link_path.unlink()
        self.link_path.symlink_to(self.tty_name)
        self._loop = asyncio.get_running_loop()
        self._pump = _Pump(device, self._write, self.faults)
        self._loop.add_reader(self.master, self._on_readable)
        self._tick = self._loop.create_task(tick_all([device], tick_s)) if tick_s else None
        self._closed = False

    def set_faults(self, faults: FaultConfig) -> None:
        self.faults.faults = faults

    def _on_readable(self) -> None:
        try:
            data = os.read(self.master, READ_CHUNK)
        except (BlockingIOError, InterruptedError):
            return
        except OSError as exc:  # EIO cannot happen while we hold the slave, but be safe
            log.warning("pty read failed: %s", exc)
            return
        if data:
            follow = getattr(self.device, "set_host_baudrate", None)
            if follow is not None:
                follow(pty_baudrate(self.slave))
            self._pump.on_data(data)

    def _write(self, data: bytes) -> None:
        view = memoryview(data)
        while view:
            try:
                view = view[os.write(self.master, view):]
            except BlockingIOError:
                log.warning("pty full (host not reading); %d reply bytes dropped", len(view))
                return

    async def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        self._loop.remove_reader(self.master)
        if self._tick is not None:
            await cancel_and_wait(self._tick)
        self._pump.close()
        for fd in (self.master, self.slave):
            with contextlib.suppress(OSError):
                os.close(fd)
        if self.link_path.is_symlink():
            self.link_path.unlink()


class _Connection(asyncio.Protocol):
    """One host connection of a TcpServer: its bytes straight to the pump (no reader task)."""

    def __init__(self, server: TcpServer) -> None:
        self.server = server
        self.transport: asyncio.Transport | None = None
        self.pump: _Pump | None = None
        self._timer: asyncio.TimerHandle | None = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        if time.monotonic() < self.server._refuse_until:
            transport.close()
            return
        self.transport = transport
        self.pump = _Pump(self.server.device, transport.write, self.server.faults)
        self.server._conns.add(self)
        after = self.server.faults.faults.disconnect_after_s
        if after is not None:
            self._timer = asyncio.get_running_loop().call_later(after, self.server.disconnect)

    def data_received(self, data: bytes) -> None:
        if self.pump is not None:
            self.pump.on_data(data)

    def drop(self) -> None:
        """End the connection now, unsent replies with it (the cable pulled)."""
        if self.transport is not None:
            log.info("connection dropped (simulated disconnect or shutdown)")
            self.transport.abort()

    def connection_lost(self, exc: Exception | None) -> None:
        if exc is not None:
            log.info("connection lost: %s", exc)
        if self._timer is not None:
            self._timer.cancel()
        self.server._conns.discard(self)
        if self.pump is not None:
            self.pump.close()
            self.pump = None


class TcpServer:
    """A device behind a TCP listener; every connection feeds the same device."""

    def __init__(self, device: SimDevice, tick_s: float | None = TICK_S,
                 faults: FaultConfig | None = None, seed: int | None = 0) -> None:
        self.device = device
        self.faults = ReplyFaults(faults, seed)
        self.server: asyncio.Server | None = None
        self._conns: set[_Connection] = set()
        self._refuse_until = 0.0
        loop = asyncio.get_running_loop()
        self._tick = loop.create_task(tick_all([device], tick_s)) if tick_s else None

    @property
    def port(self) -> int:
        assert self.server is not None
        return int(self.server.sockets[0].getsockname()[1])

    def set_faults(self, faults: FaultConfig) -> None:
        self.faults.faults = faults

    def disconnect(self) -> None:
        """Drop every connection now and refuse new ones for `faults.reconnect_after_s`: the
        host sees the cable pulled (end of file), then the device back."""
        self._refuse_until = time.monotonic() + self.faults.faults.reconnect_after_s
        for conn in list(self._conns):
            conn.drop()

    async def close(self) -> None:
        if self.server is not None:
            self.server.close()
        for conn in list(self._conns):
            conn.drop()
        if self._tick is not None:
            await cancel_and_wait(self._tick)
        self._tick = None
        if self.server is not None:
            await self.server.wait_closed()
            self.server = None


async def serve_pty(device: SimDevice, link_path: str | os.PathLike[str],
                    tick_s: float | None = TICK_S, faults: FaultConfig | None = None,
                    seed: int | None = 0) -> PtyServer:
    """Serve `device` on a new pseudo-terminal reachable at the symlink `link_path`, with
    per-reply `faults` (drop, corrupt, latency; settable later with `set_faults`)."""
    return PtyServer(device, link_path, tick_s, faults, seed)


async def serve_tcp(device: SimDevice, host: str = "127.0.0.1", port: int = 0,
                    tick_s: float | None = TICK_S, faults: FaultConfig | None = None,
                    seed: int | None = 0) -> TcpServer:
    """Serve `device` on a TCP listener (port 0: any free port; see `.port`), with per-reply
    `faults` and, for TCP, disconnects (`disconnect()`, or `faults.disconnect_after_s`)."""
    srv = TcpServer(device, tick_s, faults, seed)
    srv.server = await asyncio.get_running_loop().create_server(
        lambda: _Connection(srv), host, port)
    return srv
