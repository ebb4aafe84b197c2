"""A practice bus for servo set-up from the dashboard: a simulated Dynamixel bus in the factory
state (every servo ID 1 at 57,600 bps, sim_bus.py `DynamixelBus.factory`) served on a
pseudo-terminal, so that its path is a port the set-up routes scan and set up, one servo at a
time, as a student would a box of new servos.

Why the server starts it, rather than the dashboard asking for the port of an `armserver sim
dynamixel --factory N` the student started: at a lab PC the student has a browser and the
server's address, often no shell on the machine the server runs on; and a walk through
"connect only the servo for joint X" needs the next servo plugged in while the bus runs, which
`armserver sim` (a fixed --factory N at start) cannot do. The command stays the way on one's
own machine (README "On real hardware").

Why a pseudo-terminal, not a loopback socket: a socket carries no baud rate, so every servo
hears the host whatever its rate, and the servo set up as the angler's y (ID 1 at 1 Mbps) and
the next factory servo (ID 1 at 57,600) would answer together and collide; on a UART they never
hear each other's rate. A pty carries the termios rate the host sets, which the bus honours
(app/sim/servers.py `set_host_baudrate`), so the scan of each rate is the hardware's. The pty's
symlink sits in a private (0700) folder of the system's temporary directory.

The bus runs on its own thread and event loop (`practice-bus`), never on the HTTP loop nor the
control thread: its physics tick and replies cost neither anything.
"""

from __future__ import annotations

import asyncio
import shutil
import tempfile
import threading
from collections.abc import Callable, Coroutine
from dataclasses import dataclass
from typing import Any, TypeVar

from app.arms.dynamixel.sim_bus import FACTORY_BAUDRATE, DynamixelBus
from app.arms.dynamixel.sim_mx28 import BAUD_CODES
from app.sim.servers import PtyServer, serve_pty

T = TypeVar("T")

#: How long starting or stopping the bus's thread, or one change to its bus, may take, s.
CALL_TIMEOUT_S = 10.0
#: Servos one practice bus holds at most (the set-up scan waits for 20 replies).
MAX_SERVOS = 8


@dataclass(frozen=True)
class PracticeServo:
    """A servo of the practice bus as the bus holds it (what a scan would find)."""

    id: int
    baudrate: int


class PracticeBus:
    """A factory-state simulated bus on a pseudo-terminal, owned by its own thread; `port` is
    the path to open."""

    def __init__(self, servos: int = 1) -> None:
        self.bus = DynamixelBus.factory(servos, baudrate=FACTORY_BAUDRATE)
        self._dir = tempfile.mkdtemp(prefix="armserver-practice-")
        self.port = f"{self._dir}/ttyDXL"
        self._loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self._loop.run_forever, name="practice-bus",
                                        daemon=True)
        self._thread.start()
        try:
            self._server: PtyServer = self._run(serve_pty(self.bus, self.port))
        except BaseException:
            self._stop_loop()
            raise

    def _run(self, coro: Coroutine[Any, Any, T]) -> T:
        """Run `coro` on the bus's loop; ValueError once the bus is stopped."""
        if self._loop.is_closed() or not self._thread.is_alive():
            coro.close()
            raise ValueError("the practice bus is stopped")
        return asyncio.run_coroutine_threadsafe(coro, self._loop).result(CALL_TIMEOUT_S)

    def _call(self, fn: Callable[[], T]) -> T:
        """Run `fn` on the bus's loop (the bus is that thread's)."""
        async def go() -> T:
            return fn()
        return self._run(go())

    def servos(self) -> list[PracticeServo]:
        """Every servo on the bus, in the order plugged in."""
        return self._call(lambda: [PracticeServo(s.id, BAUD_CODES[s.get("baud_rate")])
                                   for s in self.bus.servos])

    def plug(self) -> list[PracticeServo]:
        """Plug one more factory servo (ID 1, 57,600 bps) into the bus; ValueError past
        MAX_SERVOS."""
        def add() -> None:
            if len(self.bus.servos) >= MAX_SERVOS:
                raise ValueError(f"the practice bus holds {MAX_SERVOS} servos at most")
            self.bus.add_servo()
        self._call(add)
        return self.servos()

    def close(self) -> None:
        """Stop listening and end the thread (idempotent)."""
        if not self._thread.is_alive():
            return
        try:
            self._run(self._server.close())
        finally:
            self._stop_loop()

    def _stop_loop(self) -> None:
        self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join(CALL_TIMEOUT_S)
        if not self._thread.is_alive():
            self._loop.close()
        shutil.rmtree(self._dir, ignore_errors=True)
