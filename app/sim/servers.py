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
from collections.abc import Callable
from pathlib import Path

from app.config import FaultConfig
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
    """Host bytes -> device -> timed, ordered replies through `write`."""

    def __init__(self, device: SimDevice, write: Callable[[bytes], None],
                 faults: ReplyFaults | None = None) -> None:
        self.device = device
        self._write = write
        self.faults = faults or ReplyFaults()
        self._last_due = 0.0
        self._pending = bytearray()
        self._queue: asyncio.Queue[tuple[float, bytes]] = asyncio.Queue(REPLY_BACKLOG)
        self._task = asyncio.get_running_loop().create_task(self._writer())

    def on_data(self, data: bytes) -> None:
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
                # latency delays every reply alike: never reordered
                self._last_due = max(self._last_due, now + delay + self.faults.latency_s)
                try:
                    self._queue.put_nowait((self._last_due, out))
                except asyncio.QueueFull:
                    log.warning("reply backlog full (%d); reply dropped", REPLY_BACKLOG)

    async def _writer(self) -> None:
        while True:
            due, reply = await self._queue.get()
            wait = due - time.monotonic()
            if wait > 0:
                await asyncio.sleep(wait)
            try:
                self._write(reply)
            except OSError as exc:
                log.warning("reply not written: %s", exc)

    async def close(self) -> None:
        self._task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await self._task


async def _ticker(device: SimDevice, period: float) -> None:
    while True:
        device.advance(time.monotonic())
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
        self._tick = self._loop.create_task(_ticker(device, tick_s)) if tick_s else None
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
            self._tick.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._tick
        await self._pump.close()
        for fd in (self.master, self.slave):
            with contextlib.suppress(OSError):
                os.close(fd)
        if self.link_path.is_symlink():
            self.link_path.unlink()


class TcpServer:
    """A device behind a TCP listener; every connection feeds the same device."""

    def __init__(self, device: SimDevice, tick_s: float | None = TICK_S,
                 faults: FaultConfig | None = None, seed: int | None = 0) -> None:
        self.device = device
        self.faults = ReplyFaults(faults, seed)
        self.server: asyncio.Server | None = None
        self._conns: set[asyncio.Task[None]] = set()
        self._refuse_until = 0.0
        loop = asyncio.get_running_loop()
        self._tick = loop.create_task(_ticker(device, tick_s)) if tick_s else None

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
        for t in list(self._conns):
            t.cancel()

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        if time.monotonic() < self._refuse_until:
            writer.close()
            return
        task = asyncio.current_task()
        assert task is not None
        self._conns.add(task)
        after = self.faults.faults.disconnect_after_s
        timer = (asyncio.get_running_loop().call_later(after, self.disconnect)
                 if after is not None else None)
        pump = _Pump(self.device, writer.write, self.faults)
        try:
            while data := await reader.read(READ_CHUNK):
                pump.on_data(data)
        except ConnectionError as exc:
            log.info("connection lost: %s", exc)
        except asyncio.CancelledError:
            log.info("connection dropped (simulated disconnect or shutdown)")
        finally:
            if timer is not None:
                timer.cancel()
            self._conns.discard(task)
            await pump.close()
            writer.close()
            with contextlib.suppress(ConnectionError):
                await writer.wait_closed()

    async def close(self) -> None:
        if self.server is not None:
            self.server.close()
        for t in [*self._conns, *([self._tick] if self._tick else [])]:
            t.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await t
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
    srv.server = await asyncio.start_server(srv._serve, host, port)
    return srv
