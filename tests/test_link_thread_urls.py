"""The thread link over pyserial URLs that give no descriptor (issue 27): `loop://` (pyserial's
loopback: what is written is read back) and `rfc2217://` (a port over Telnet, RFC 2217).

Without a descriptor the link's calls run on its own thread with pyserial's `write` and `read`
with a timeout, and the owner task makes every poll itself (nothing is polled on the poll
thread's schedule). The rfc2217 server here is pyserial's own protocol code
(`serial.rfc2217.PortManager`, as pyserial's examples/rfc2217_server.py uses it) in front of a
`loop://` port, on a loopback TCP socket: what is written comes back through both.

An rbe3001 board that echoes is a valid one for STATUS: the request's floats are zeros, and a
STATUS reply of zeros is a reading at the encoders' zero, so the driver runs whole over both.
"""

from __future__ import annotations

import contextlib
import socket
import threading
from collections.abc import Iterator

import pytest
import serial
import serial.rfc2217
from _wait import wait_for

from app.arms.loading import load_profile
from app.arms.rbe3001.driver import Rbe3001Driver
from app.links.base import LinkState
from app.links.threaded import ThreadLink
from app.telemetry.hub import TelemetryHub
from protocol import rbe3001 as rb

#: pyserial 3.5's rfc2217 client starts its reader thread with the deprecated setName and
#: setDaemon
pytestmark = [pytest.mark.filterwarnings("ignore:setName:DeprecationWarning"),
              pytest.mark.filterwarnings("ignore:setDaemon:DeprecationWarning")]


class _Connection:
    """The client's socket as PortManager writes to it (pyserial's rfc2217_server.py)."""

    def __init__(self, sock: socket.socket) -> None:
        self.sock = sock
        self._lock = threading.Lock()

    def write(self, data: bytes) -> None:
        with self._lock:
            self.sock.sendall(data)


@contextlib.contextmanager
def rfc2217_echo() -> Iterator[int]:
    """An RFC 2217 server (pyserial's PortManager) for a `loop://` port on a loopback port,
    one client at a time, on a thread; its TCP port."""
    listener = socket.create_server(("127.0.0.1", 0))
    port = listener.getsockname()[1]
    stop = threading.Event()

    def serve() -> None:
        while not stop.is_set():
            listener.settimeout(0.2)
            try:
                conn, _ = listener.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            loop_port = serial.serial_for_url("loop://", timeout=0.01)
            # (the example's Redirector: the manager answers the client's options by `write`)
            manager = serial.rfc2217.PortManager(loop_port, _Connection(conn))
            conn.settimeout(0.01)
            with conn, loop_port:
                while not stop.is_set():
                    try:
                        data = conn.recv(4096)
                    except TimeoutError:
                        data = None
                    except OSError:
                        break
                    if data == b"":
                        break
                    if data:
                        loop_port.write(b"".join(manager.filter(data)))
                    echoed = loop_port.read(loop_port.in_waiting or 1)
                    if echoed:
                        try:
                            conn.sendall(b"".join(manager.escape(echoed)))
                        except OSError:
                            break

    thread = threading.Thread(target=serve, name="rfc2217 echo", daemon=True)
    thread.start()
    try:
        yield port
    finally:
        stop.set()
        listener.close()
        thread.join(5)


def _urls() -> list[str]:
    return ["loop://", "rfc2217"]


@contextlib.contextmanager
def _url(kind: str) -> Iterator[str]:
    if kind == "loop://":
        yield "loop://"
    else:
        with rfc2217_echo() as port:
            yield f"rfc2217://127.0.0.1:{port}"


@pytest.mark.parametrize("kind", _urls())
async def test_a_request_comes_back_whole_over_a_url_without_a_descriptor(kind):
    with _url(kind) as url:
        link = ThreadLink(url)
        await link.open()
        try:
            assert link.state is LinkState.UP
            packet = bytes(range(64))
            reply = await link.transact(packet, len(packet), 2.0)
            data = reply.data
            while len(data) < len(packet):  # (a stream: the rest by reads, as a driver does)
                more = await link.read(1.0)
                assert more, data
                data += more
            assert data == packet
            await link.write(b"\xff\x00 two")
            got = b""
            while len(got) < 6:
                got += await link.read(1.0)
            assert got == b"\xff\x00 two"
            assert await link.read(0.05) == b""  # nothing more: silence, not a lost link
            assert not link.can_schedule  # no descriptor: nothing for the poll thread
            assert link.arm(0.0, 0.002, lambda: None) is False
        finally:
            await link.close()
        assert link.state is LinkState.DOWN


@pytest.mark.parametrize("kind", _urls())
async def test_the_rbe3001_driver_runs_over_an_echoing_board_without_a_descriptor(kind):
    """The owner task polls itself (no schedule without a descriptor): every sample in order,
    the readings of an echo (zeros)."""
    profile = load_profile("rbe3001")
    with _url(kind) as url:
        link = ThreadLink(url)
        driver = Rbe3001Driver(profile, link, TelemetryHub("rbe3001"))
        await driver.start()
        try:
            assert await driver.wait_connected(10.0), link.last_error
            sub = driver.hub.subscribe()
            try:
                seq = driver.hub.latest["seq"]
                await wait_for(lambda: driver.hub.latest["seq"] > seq + 20, what="samples")
                samples, _events, dropped = sub.take()
            finally:
                sub.close()
            assert dropped == 0 and len(samples) >= 20
            reply = await driver.status()  # a request between the polls
            assert reply == rb.StatusReply((0.0,) * 3, (0.0,) * 3, (0.0,) * 3)
            assert link.stats["scheduled"] == 0  # every poll the owner task's own
            assert driver.stats["corrupt"] == 0 and driver.stats["poll_failures"] == 0
        finally:
            await driver.close()
