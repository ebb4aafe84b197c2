"""Which serial ports and HID devices are attached, and which look like a known arm.

For `armserver devices`. Each back end is optional: a missing pyserial or hidapi shows up
as a warning in the listing, never as a crash. The known USB ids are the arm types' own
(`ArmType.usb`, app/arms), e.g. the RBE3001 Nucleo firmware's HID 3742:0007 and the ROBOTIS
U2D2 (FTDI 0403:6014). An FTDI adapter's latency timer defaults to 16 ms, which caps a
Dynamixel read loop near 60 Hz; ROBOTIS recommends 1 ms, so one whose timer is above 1 ms
gets a warning with the fix.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

from app.arms import all_arm_types
from app.arms.base import UsbMatch

#: The label of a known device (an arm type's `UsbMatch.label`).
Match = str
SYSFS_USB_SERIAL = Path("/sys/bus/usb-serial/devices")
MAX_LATENCY_MS = 1  # ROBOTIS' recommended U2D2 latency timer


@dataclass(frozen=True)
class DeviceInfo:
    kind: Literal["serial", "hid"]
    address: str  # serial device path or hidapi path
    description: str
    vid: int | None = None
    pid: int | None = None
    serial_number: str | None = None
    match: Match | None = None
    warning: str | None = None


def match_device(kind: str, vid: int | None, pid: int | None) -> Match | None:
    """The known arm a USB id pair belongs to, if any."""
    if vid is None or pid is None:
        return None
    found = known_usb().get((kind, vid, pid))
    return None if found is None else found.label


def known_usb() -> dict[tuple[str, int, int], UsbMatch]:
    """(kind, vid, pid) -> the match, from every registered arm type."""
    return {(u.kind, u.vid, u.pid): u for t in all_arm_types() for u in t.usb}


def latency_warning(tty: str, sysfs: Path = SYSFS_USB_SERIAL) -> str | None:
    """A warning if the FTDI latency timer of `tty` (e.g. "ttyUSB0") is above 1 ms."""
    path = sysfs / tty / "latency_timer"
    try:
        ms = int(path.read_text().strip())
    except (OSError, ValueError) as exc:
        return f"cannot read the latency timer at {path}: {exc}"
    if ms <= MAX_LATENCY_MS:
        return None
    return (
        f"latency timer is {ms} ms (caps a read loop near {1000 // ms} Hz); "
        f"set it to 1 ms: echo 1 | sudo tee {path}"
    )


def list_devices(sysfs: Path = SYSFS_USB_SERIAL) -> list[DeviceInfo]:
    """Serial ports first, then HID devices; known arms are tagged in `match`."""
    return _serial_devices(sysfs) + _hid_devices()


def _serial_devices(sysfs: Path) -> list[DeviceInfo]:
    try:
        from serial.tools import list_ports
    except ImportError as exc:
        why = f"pyserial not available: {exc}"
        return [DeviceInfo("serial", "", "serial ports not listed", warning=why)]
    out = []
    for port in sorted(list_ports.comports(), key=lambda p: p.device):
        match = match_device("serial", port.vid, port.pid)
        warning = None
        usb = known_usb().get(("serial", port.vid or -1, port.pid or -1))
        if usb is not None and usb.ftdi_latency:
            warning = latency_warning(Path(port.device).name, sysfs)
        out.append(
            DeviceInfo(
                kind="serial",
                address=port.device,
                description=port.description or "",
                vid=port.vid,
                pid=port.pid,
                serial_number=port.serial_number,
                match=match,
                warning=warning,
            )
        )
    return out


def _hid_devices() -> list[DeviceInfo]:
    try:
        import hid

        found: list[dict[str, Any]] = hid.enumerate()
    except (ImportError, OSError) as exc:
        why = f"hidapi not available: {exc}"
        return [DeviceInfo("hid", "", "HID devices not listed", warning=why)]
    out, seen = [], set()
    for d in found:
        path = d.get("path", b"")
        address = path.decode(errors="replace") if isinstance(path, bytes) else str(path)
        if address in seen:
            continue
        seen.add(address)
        vid, pid = d.get("vendor_id"), d.get("product_id")
        name = " ".join(s for s in (d.get("manufacturer_string"), d.get("product_string")) if s)
        out.append(
            DeviceInfo(
                kind="hid",
                address=address,
                description=name,
                vid=vid,
                pid=pid,
                serial_number=d.get("serial_number") or None,
                match=match_device("hid", vid, pid),
            )
        )
    return out


def format_devices(devices: list[DeviceInfo]) -> str:
    """A plain-text table for the CLI, warnings indented under their device."""
    if not devices:
        return "no serial ports or HID devices found"
    head = ("KIND", "ADDRESS", "VID:PID", "SERIAL", "MATCH", "DESCRIPTION")
    rows = [
        (
            d.kind,
            d.address or "-",
            f"{d.vid:04x}:{d.pid:04x}" if d.vid is not None and d.pid is not None else "-",
            d.serial_number or "-",
            d.match or "-",
            d.description or "-",
        )
        for d in devices
    ]
    widths = [max(len(r[i]) for r in (head, *rows)) for i in range(len(head) - 1)]
    lines = []
    for row, dev in zip((head, *rows), (None, *devices), strict=True):
        cells = [c.ljust(w) for c, w in zip(row, widths, strict=False)] + [row[-1]]
        lines.append("  ".join(cells).rstrip())
        if dev is not None and dev.warning:
            lines.append(f"    warning: {dev.warning}")
    return "\n".join(lines)
