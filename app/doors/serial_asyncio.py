"""pyserial-asyncio's internals: the only module that touches them.

Checked with pyserial-asyncio 0.6 (pyproject.toml: `>=0.6,<0.7`). pyserial-asyncio is imported
only when a serial link opens (`open_transport`), and `check()` runs then, once.

A serial link (a USB adapter, a pseudo-terminal, `socket://`: the simulators behind
`socket://` in `make bench-peers`'s idle figure, 5.4 % of a core for 700 polls a second) makes
a request and reads its reply hundreds of times a second. pyserial-asyncio's transport spends
on each more than the request itself (below); `open_transport` builds it with a leaner reader,
and `write_now` writes past its writer. Without this door the links work unchanged through
`serial_asyncio.create_serial_connection`, at a higher idle CPU figure.
"""

from __future__ import annotations

import asyncio
import functools
import inspect
import os
from typing import Any

from app.doors import require, uses

CHECKED = "0.6"


def open_transport(loop: asyncio.AbstractEventLoop, protocol: asyncio.Protocol, port: Any,
                   read_size: int) -> asyncio.Transport:
    """What `serial_asyncio.create_serial_connection` does (a transport over the open pyserial
    `port`; the protocol's `connection_made` comes from `call_soon`), with a reader that reads
    up to `read_size` bytes with one `os.read` (see `_transport_class`)."""
    transport: asyncio.Transport = _transport_class(read_size)(loop, protocol, port)
    return transport


@functools.cache
def _transport_class(read_size: int) -> Any:
    """pyserial-asyncio's transport with a leaner reader (built on first use, after `check()`).

    Its own `_read_ready` calls pyserial's `read`, which asks `select` whether the port is
    readable (the loop has just said so) and loops on a timeout object: a system call and a
    few dozen lines of Python for each reply, hundreds of times a second on an idle arm. The
    port is non-blocking, so one `os.read` does it: what is there, or end of file (a socket
    whose peer closed, a pseudo-terminal without its master) or an error, both of which end
    the connection as pyserial's `SerialException` would.

    Internals: `SerialTransport(loop, protocol, serial_instance)`, the loop's reader calling
    `_read_ready`, and `_serial`, `_protocol`, `_close(exc=...)`."""
    import serial
    import serial_asyncio

    check()

    class Transport(serial_asyncio.SerialTransport):  # type: ignore[misc]
        def _read_ready(self) -> None:
            try:
                data = os.read(self._serial.fileno(), read_size)
            except (BlockingIOError, InterruptedError):
                return
            except OSError as exc:
                self._close(exc=serial.SerialException(f"read failed: {exc}"))
                return
            if data:
                self._protocol.data_received(data)
            else:
                self._close(exc=serial.SerialException("the port reports end of file "
                                                       "(device disconnected)"))

    return Transport


def write_now(transport: Any, data: bytes) -> bytes:
    """Write what the port takes now, as pyserial-asyncio's own writer would a loop iteration
    later; what is left, for the transport to buffer.

    pyserial-asyncio's `write` only buffers: it adds a writer to the loop, writes when the loop
    says the port is writable and removes the writer again, so each request cost two
    `epoll_ctl` calls and one loop iteration, and left one iteration later (at 700 polls a
    second, a visible part of an idle server's CPU). With nothing buffered ahead of it, the
    bytes go out here with one `os.write` on the non-blocking port (what pyserial's own write
    comes down to, under its timeout loop).

    Internals: that `get_write_buffer_size()` counts every byte the transport holds (its
    `_write_buffer`), so that writing to the port past it keeps the order; `serial`."""
    if transport.get_write_buffer_size():  # (the caller refuses a closing transport)
        return data
    try:
        n = os.write(transport.serial.fileno(), data)
    except (BlockingIOError, InterruptedError):
        return data
    return data[n:]


def check() -> None:
    """Raise app.doors.DoorError naming each internal above the installed pyserial-asyncio
    lacks (it imports pyserial-asyncio)."""
    import serial_asyncio

    t = serial_asyncio.SerialTransport
    slower = "serial links still work, at a higher CPU cost per request (the idle figure)"
    require("app.doors.serial_asyncio", "pyserial-asyncio", CHECKED, [
        ("SerialTransport(loop, protocol, serial_instance)",
         lambda: list(inspect.signature(t.__init__).parameters) == [
             "self", "loop", "protocol", "serial_instance"],
         "no serial link can open"),
        ("SerialTransport._read_ready, called by the loop's reader (_ensure_reader)",
         lambda: callable(t._read_ready) and uses(t._ensure_reader, "_read_ready"),
         "the lean reader is never called: " + slower),
        ("SerialTransport._serial, ._protocol, ._close(exc=...)",
         lambda: (uses(t.__init__, "_serial", "_protocol")
                  and "exc" in inspect.signature(t._close).parameters),
         "the lean reader fails on its first reply: no serial link works"),
        ("SerialTransport.serial, .get_write_buffer_size() over ._write_buffer",
         lambda: (isinstance(t.serial, property)
                  and uses(t.get_write_buffer_size, "_write_buffer")
                  and uses(t.write, "_write_buffer")),
         "a direct write could overtake buffered bytes: requests would reach the device out "
         "of order"),
    ])
