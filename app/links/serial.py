"""A byte-stream link over any pyserial URL, on pyserial-asyncio.

Works with a USB serial adapter (`/dev/ttyUSB0`, the Dynamixel U2D2), a pseudo-terminal
(`/dev/pts/N` or a symlink to it, as `app/sim/serve.py` makes) and a TCP socket
(`socket://127.0.0.1:PORT`). pyserial and pyserial-asyncio are imported only when a link
is opened, so a server with no serial arm never loads them.
"""

from __future__ import annotations

import asyncio
import logging
import os

from app.links.base import Link, LinkError, LinkState

log = logging.getLogger(__name__)

READ_CHUNK = 4096  # bytes per read: several Dynamixel status packets, far above one HID report
CLOSE_TIMEOUT_S = 1.0  # closing a transport whose peer is gone must not hang the owner task


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
        self._reader: asyncio.StreamReader | None = None
        self._writer: asyncio.StreamWriter | None = None
        self._errors: tuple[type[BaseException], ...] = (OSError,)

    async def open(self) -> None:
        """Open the port; LinkError naming the URL and the reason if it cannot be opened."""
        if self._writer is not None:
            await self.close()
        self.state = LinkState.CONNECTING
        try:
            import serial
            import serial_asyncio
        except ImportError as exc:
            raise self._down(f"pyserial-asyncio not available: {exc}") from exc
        self._errors = (OSError, serial.SerialException)
        try:
            # Exclusive (flock): a second server on the same port would break this one's link
            # mid-move; it is refused instead, told who holds the port.
            self._reader, self._writer = await serial_asyncio.open_serial_connection(
                url=self.address, baudrate=self.baudrate, exclusive=True
            )
        except (*self._errors, ValueError) as exc:
            holder = lock_holder(self.address) if "lock" in str(exc) else None
            if holder is not None:
                raise self._down(f"cannot open {self.address}: it is in use by {holder}; a "
                                 "port is driven by one server at a time") from exc
            raise self._down(f"cannot open {self.address}: {exc}") from exc
        self.state = LinkState.UP
        self.last_error = None
        log.info("serial link %s open at %d baud", self.address, self.baudrate)

    async def write(self, data: bytes) -> None:
        writer = self._require()[1]
        if writer.is_closing():
            raise self._lost("closed")
        try:
            writer.write(data)
            await writer.drain()
        except self._errors as exc:
            raise self._lost(str(exc)) from exc

    async def read(self, timeout: float) -> bytes:
        reader = self._require()[0]
        try:
            # Cancelling StreamReader.read loses nothing: unread bytes stay in its buffer.
            data = await asyncio.wait_for(reader.read(READ_CHUNK), timeout)
        except TimeoutError:
            return b""
        except self._errors as exc:
            raise self._lost(str(exc)) from exc
        if not data:
            raise self._lost("closed by the peer (end of file)")
        return data

    async def close(self) -> None:
        writer, self._reader, self._writer = self._writer, None, None
        self.state = LinkState.DOWN
        if writer is None:
            return
        writer.close()
        try:
            await asyncio.wait_for(writer.wait_closed(), CLOSE_TIMEOUT_S)
        except (TimeoutError, *self._errors) as exc:
            log.debug("serial link %s closed with %r", self.address, exc)

    def _require(self) -> tuple[asyncio.StreamReader, asyncio.StreamWriter]:
        if self._reader is None or self._writer is None or self.state is not LinkState.UP:
            raise LinkError(self.last_error or f"serial link {self.address} is not open")
        return self._reader, self._writer

    def _lost(self, reason: str) -> LinkError:
        """Mark the link DOWN, drop the transport and return the error to raise."""
        writer, self._reader, self._writer = self._writer, None, None
        if writer is not None:
            writer.close()
        log.warning("serial link %s lost: %s", self.address, reason)
        return self._down(f"serial link {self.address} lost: {reason}")
