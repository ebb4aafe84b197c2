"""A byte-stream link over any pyserial URL, on pyserial-asyncio.

Works with a USB serial adapter (`/dev/ttyUSB0`, the Dynamixel U2D2), a pseudo-terminal
(`/dev/pts/N` or a symlink to it, as `app/sim/servers.py` makes) and a TCP socket
(`socket://127.0.0.1:PORT`). pyserial and pyserial-asyncio are imported only when a link
is opened, so a server with no serial arm never loads them.

Reads are buffered by an asyncio Protocol: bytes land in a buffer as the loop receives them,
a read with bytes waiting returns them at once, and a read that must wait does so on one timer
the loop keeps (no task per read, as `asyncio.wait_for` would make). pyserial-asyncio's
transport gets a leaner reader and a direct write (app/doors/serial_asyncio.py, the only place
that touches its internals).
"""

from __future__ import annotations

import asyncio
import logging
import os
from typing import Any

from app.doors import serial_asyncio as serial_door
from app.links.base import READ_CHUNK, Link, LinkError, LinkState
from app.runtime.control_thread import TerminalHold, terminal_hold

log = logging.getLogger(__name__)

CLOSE_TIMEOUT_S = 1.0  # closing a transport whose peer is gone must not hang the owner task


class _Buffered(asyncio.Protocol):
    """Received bytes, the end of the connection, and write flow control."""

    def __init__(self) -> None:
        self.buf = bytearray()
        self.transport: asyncio.Transport | None = None
        self.ended: str | None = None  # why the connection ended, once it has
        self.waiter: asyncio.Future[None] | None = None
        self.paused: asyncio.Future[None] | None = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = transport  # type: ignore[assignment]  # a pyserial-asyncio Transport

    def data_received(self, data: bytes) -> None:
        self.buf += data
        _resolve(self.waiter)

    def connection_lost(self, exc: Exception | None) -> None:
        self.ended = str(exc) if exc is not None else "closed by the peer (end of file)"
        _resolve(self.waiter)
        _resolve(self.paused)

    def pause_writing(self) -> None:
        if self.paused is None:
            self.paused = asyncio.get_running_loop().create_future()

    def resume_writing(self) -> None:
        paused, self.paused = self.paused, None
        _resolve(paused)


def _resolve(fut: asyncio.Future[None] | None) -> None:
    if fut is not None and not fut.done():
        fut.set_result(None)


def on_terminal(kind: str, address: str) -> bool:
    """Whether a link of `kind` at `address` is a terminal's (a device path such as
    /dev/ttyUSB0, not a pyserial URL such as socket://)."""
    return kind == "serial" and "://" not in address


def port_fileno(port: Any) -> int | None:
    """The descriptor of an open pyserial port, or None where it has none (`loop://`,
    rfc2217)."""
    import serial

    try:
        fd: int = port.fileno()
    except (AttributeError, NotImplementedError, OSError, ValueError,
            serial.SerialException):
        return None
    return fd


def cannot_open(address: str, exc: BaseException) -> str:
    """Why the port at `address` did not open: who holds it, where its exclusive lock (flock)
    refused us (a second server would break the first's link mid-move), else the error."""
    holder = lock_holder(address) if "lock" in str(exc) else None
    if holder is not None:
        return (f"cannot open {address}: it is in use by {holder}; a port is driven by one "
                "server at a time")
    return f"cannot open {address}: {exc}"


def lock_holder(path: str) -> str | None:
    """Who holds an flock on the device `path` ("process 1234 (armserver serve ...)"), from
    /proc/locks (Linux); None if unknown."""
    try:
        st = os.stat(os.path.realpath(path))
        with open("/proc/locks") as f:
            lines = f.read().splitlines()
    except OSError:
        return None
    for line in lines:
        fields = line.split()
        if len(fields) < 6 or fields[1] != "FLOCK":
            continue
        try:
            major, minor, inode = fields[5].split(":")
            if (int(major, 16), int(minor, 16), int(inode)) != (
                    os.major(st.st_dev), os.minor(st.st_dev), st.st_ino):
                continue
            pid = int(fields[4])
        except ValueError:
            continue
        try:
            with open(f"/proc/{pid}/cmdline", "rb") as f:
                cmd = f.read().replace(b"\0", b" ").decode(errors="replace").strip()
        except OSError:
            cmd = ""
        return f"process {pid}" + (f" ({cmd[:120]})" if cmd else "")
    return None


class SerialLink(Link):
    """A stream link: `read` returns whatever bytes have arrived (up to READ_CHUNK)."""

    kind = "serial"
    packetized = False

    def __init__(self, address: str, baudrate: int = 1_000_000) -> None:
        super().__init__(address)
        self.baudrate = baudrate
        self._proto: _Buffered | None = None
        self._errors: tuple[type[BaseException], ...] = (OSError,)
        self._terminal: TerminalHold | None = None  # the port is a terminal (a tty, a pty)

    async def open(self) -> None:
        """Open the port; LinkError naming the URL and the reason if it cannot be opened."""
        if self._proto is not None:
            await self.close()
        self.state = LinkState.CONNECTING
        try:
            import serial
            import serial_asyncio  # noqa: F401  (its transport: app/doors/serial_asyncio.py)
        except ImportError as exc:
            raise self._down(f"pyserial-asyncio not available: {exc}") from exc
        self._errors = (OSError, serial.SerialException)
        try:
            # Exclusive (flock): a second server on the same port would break this one's link
            # mid-move; it is refused instead, told who holds the port.
            port = serial.serial_for_url(self.address, baudrate=self.baudrate, exclusive=True)
            proto = _Buffered()
            # what serial_asyncio.create_serial_connection does, with a leaner reader
            proto.transport = serial_door.open_transport(asyncio.get_running_loop(), proto,
                                                         port, READ_CHUNK)
            self._proto = proto  # (connection_made comes later, from call_soon)
        except (*self._errors, ValueError) as exc:
            raise self._down(cannot_open(self.address, exc)) from exc
        self._terminal = terminal_hold(port_fileno(port))  # (the raised threads at 0 meanwhile)
        self.state = LinkState.UP
        self.last_error = None
        log.info("serial link %s open at %d baud", self.address, self.baudrate)

    async def write(self, data: bytes) -> None:
        proto = self._require()
        transport = proto.transport
        if proto.ended is not None or transport is None or transport.is_closing():
            raise self._lost(proto.ended or "closed")
        try:
            data = serial_door.write_now(transport, data)
            if data:
                transport.write(data)
        except self._errors as exc:
            raise self._lost(str(exc)) from exc
        if proto.paused is not None:  # the transport's buffer is full: wait for it to drain
            await asyncio.shield(proto.paused)
            if proto.ended is not None:
                raise self._lost(proto.ended)

    async def read(self, timeout: float) -> bytes:
        proto = self._require()
        if not proto.buf and proto.ended is None:
            loop = asyncio.get_running_loop()
            fut = loop.create_future()
            proto.waiter = fut
            timer = loop.call_at(loop.time() + timeout, _resolve, fut)
            try:
                await fut
            finally:
                proto.waiter = None
                timer.cancel()
        if proto.buf:  # bytes that arrived before the connection ended are still read
            data = bytes(proto.buf[:READ_CHUNK])
            del proto.buf[:READ_CHUNK]
            return data
        if proto.ended is not None:
            raise self._lost(proto.ended)
        return b""

    async def close(self) -> None:
        proto, self._proto = self._proto, None
        self.state = LinkState.DOWN
        terminal, self._terminal = self._terminal, None
        if terminal is not None:
            terminal.release()
        if proto is None or proto.transport is None:
            return
        proto.transport.close()
        if proto.ended is None:
            done = asyncio.get_running_loop().create_future()
            proto.waiter = done
            timer = asyncio.get_running_loop().call_later(CLOSE_TIMEOUT_S, _resolve, done)
            try:
                await done  # connection_lost, or CLOSE_TIMEOUT_S: a gone peer must not hang us
            finally:
                timer.cancel()
        if proto.ended is None:
            log.debug("serial link %s not closed within %.1f s", self.address, CLOSE_TIMEOUT_S)

    def _require(self) -> _Buffered:
        if self._proto is None or self.state is not LinkState.UP:
            raise LinkError(self.last_error or f"serial link {self.address} is not open")
        return self._proto

    def _lost(self, reason: str) -> LinkError:
        """Mark the link DOWN, drop the transport and return the error to raise."""
        proto, self._proto = self._proto, None
        if proto is not None and proto.transport is not None:
            proto.transport.close()
        log.warning("serial link %s lost: %s", self.address, reason)
        return self._down(f"serial link {self.address} lost: {reason}")
