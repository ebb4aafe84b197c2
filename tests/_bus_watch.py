"""What a simulated Dynamixel bus receives, watched where it receives bytes (on the control
thread, in the order the owner task writes them): every WRITE and SYNC_WRITE, decoded by its
register. A spy on the device side of the link, not a stand-in: the bus still answers."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from protocol import dynamixel as dxl
from protocol import mx28


def watch_writes(bus: Any, note: Callable[[str, dict[int, int]], None]) -> None:
    """Call `note(register name, {id: raw})` for every WRITE and SYNC_WRITE `bus` receives."""
    items = {item.address: item for item in mx28.TABLE.values()}
    receive = bus.receive
    parser = dxl.Parser()

    def receiving(data: bytes, now: float) -> Any:
        parser.feed(bytes(data))
        while (p := parser.next_event()) is not None:
            if isinstance(p, dxl.ParseError):
                continue
            if p.instruction == dxl.Instruction.SYNC_WRITE:
                address, _size, values = dxl.decode_sync_write(p.params)
                item = items[address]
                note(item.name, {i: dxl.from_bytes(v, item.signed) for i, v in values.items()})
            elif p.instruction == dxl.Instruction.WRITE:
                item = items[int.from_bytes(p.params[:2], "little")]
                note(item.name, {p.id: dxl.from_bytes(p.params[2:], item.signed)})
        return receive(data, now)

    bus.receive = receiving
