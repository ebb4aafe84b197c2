"""A USB HID link on hidapi (the `hid` module of the "hidapi" package, `hid.device` API).

The RBE3001 firmware is a USBHID(64, 64) device: host writes are report id 0 plus 64 bytes,
reads return the 64-byte report. hidapi calls block, so each runs on one worker thread
(a single-thread executor: calls never overlap and the event loop never blocks). `hid` is
imported only when a link is opened: a server with no HID arm never loads the native library.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import Any, TypeVar

from app.links.base import Link, LinkError, LinkState

log = logging.getLogger(__name__)

REPORT_SIZE = 64  # bytes in one RBE3001 report (firmware USBHID(64, 64))
REPORT_ID = 0  # the firmware uses unnumbered reports: hidapi wants a leading 0
_T = TypeVar("_T")


def with_report_id(packet: bytes, report_id: int = REPORT_ID) -> bytes:
    """The bytes hidapi's write takes: the report id then the packet (65 for a 64-byte one)."""
    return bytes((report_id,)) + bytes(packet)


def _serial_identity(serial: object) -> str | None:
    """The device's USB serial number (hidapi's `serial_number`) as its identity, the stored
    calibration's key; None where the device reports none."""
    return f"hid-serial:{serial}" if isinstance(serial, str) and serial else None


def describe(vid: int | None, pid: int | None) -> str:
    """`3742:0007`-style name of a USB id pair."""
    return f"{vid or 0:04x}:{pid or 0:04x}"


class HidLink(Link):
    """A packetised link: each `read` returns one 64-byte report or b"" on timeout."""

    kind = "hid"
    packetized = True

    def __init__(
        self,
        address: str = "",
        vid: int | None = None,
        pid: int | None = None,
        serial_number: str | None = None,
    ) -> None:
        """Open by hidraw `address` (a hidapi path) if given, else by `vid`/`pid` and an
        optional serial number."""
        super().__init__(address or describe(vid, pid))
        self.path = address
        self.vid, self.pid, self.serial_number = vid, pid, serial_number
        self._dev: Any = None
        self._executor: ThreadPoolExecutor | None = None
        self._pending: asyncio.Future[bytes] | None = None

    @property
    def target(self) -> str:
        return self.path or describe(self.vid, self.pid)

    async def open(self) -> None:
        """Find and open the device; LinkError if hidapi is missing or nothing matches."""
        await self.close()
        self.state = LinkState.CONNECTING
        try:
            import hid
        except (ImportError, OSError) as exc:
            raise self._down(f"hidapi not available: {exc} (needed for {self.target})") from exc
        if not self.path and (self.vid is None or self.pid is None):
            raise self._down("an HID link needs a path or both vid and pid")
        self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="hid")
        try:
            self._dev = await self._call(self._open_blocking, hid)
        except LinkError as exc:
            self._shutdown()
            raise self._down(str(exc)) from exc
        except (OSError, ValueError) as exc:
            self._shutdown()
            raise self._down(
                f"cannot open HID device {self.target}: {exc} (permissions on /dev/hidraw*?)"
            ) from exc
        self.state = LinkState.UP
        self.last_error = None
        log.info("hid link %s open", self.target)

    def _open_blocking(self, hid: Any) -> Any:
        dev = hid.device()
        if self.path:
            dev.open_path(self.path.encode())
            try:
                self.identity = _serial_identity(dev.get_serial_number_string())
            except (OSError, ValueError, AttributeError):
                self.identity = None
            return dev
        found = [
            d
            for d in hid.enumerate(self.vid, self.pid)
            if self.serial_number is None or d.get("serial_number") == self.serial_number
        ]
        if not found:
            sn = f" with serial number {self.serial_number}" if self.serial_number else ""
            raise LinkError(
                f"no HID device {self.target}{sn} found "
                "(is the arm plugged in? permissions on /dev/hidraw*?)"
            )
        dev.open_path(found[0]["path"])
        self.identity = _serial_identity(found[0].get("serial_number"))
        return dev

    async def write(self, data: bytes) -> None:
        """Send one packet (the report id is added here)."""
        dev = self._require()
        report = with_report_id(data)
        try:
            sent = await self._call(dev.write, report)
        except (OSError, ValueError) as exc:
            raise self._lost(f"write failed: {exc}") from exc
        if sent < 0:
            raise self._lost(f"write failed: {await self._error(dev)}")

    async def read(self, timeout: float) -> bytes:
        """One report, or b"" after `timeout` s. A read cancelled by the caller keeps running
        on the worker thread and its report is returned by the next call, never lost."""
        dev = self._require()
        if self._pending is None:
            timeout_ms = max(1, round(timeout * 1000))
            self._pending = asyncio.ensure_future(self._call(dev.read, REPORT_SIZE, timeout_ms))
        pending = self._pending
        try:
            values = await asyncio.shield(pending)
        except (OSError, ValueError) as exc:
            raise self._lost(f"read failed: {exc}") from exc
        finally:
            if pending.done():
                self._pending = None
        return bytes(values)

    async def close(self) -> None:
        dev, self._dev = self._dev, None
        self._pending = None
        self.state = LinkState.DOWN
        if dev is not None and self._executor is not None:
            try:
                await self._call(dev.close)
            except OSError as exc:
                log.debug("hid link %s closed with %r", self.target, exc)
        self._shutdown()

    def _shutdown(self) -> None:
        if self._executor is not None:
            self._executor.shutdown(wait=False)
            self._executor = None

    async def _call(self, fn: Callable[..., _T], *args: Any) -> _T:
        assert self._executor is not None
        return await asyncio.get_running_loop().run_in_executor(self._executor, fn, *args)

    async def _error(self, dev: Any) -> str:
        try:
            return str(await self._call(dev.error))
        except (OSError, ValueError, AttributeError):
            return "unknown error"

    def _require(self) -> Any:
        if self._dev is None or self.state is not LinkState.UP:
            raise LinkError(self.last_error or f"hid link {self.target} is not open")
        return self._dev

    def _lost(self, reason: str) -> LinkError:
        dev, self._dev = self._dev, None
        self._pending = None
        if dev is not None and self._executor is not None:
            self._executor.submit(dev.close)
        self._shutdown()
        log.warning("hid link %s lost: %s", self.target, reason)
        return self._down(f"hid link {self.target} lost: {reason}")
