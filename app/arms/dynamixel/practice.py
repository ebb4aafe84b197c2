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

The bus runs in a process of its own (`python -m app.arms.dynamixel.practice`, on a thread
and event loop there), never in the server's: a scan's PING it read after the scan had moved
on to the next rate would be read at that rate (the pty's rate is the one set when the bus
reads), and in the server's process its thread shared the GIL with the server's threads; beside
busy workers it read a PING late enough for the factory servo to stay silent (session 14).
Its own process waits only for a core. The server talks to it over the child's stdin and
stdout, a JSON line each way; the child ends when its stdin closes (the server gone).

Where the system lets it (root, CAP_SYS_NICE), the child raises its own priority
(`NICENESS`) before its bus starts: the servos it stands in for answer from processors of
their own, whatever else the PC runs. It spends CPU only on a request, so the server and the
rest lose nothing. At the same niceness as everything else, beside a load on both cores
(stress-ng, `make test-loaded`) it was starved past a scan's window and a READ's 1 s, and its
servos read as silent.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import select
import shutil
import subprocess
import sys
import tempfile
import threading
from collections.abc import Callable, Coroutine
from dataclasses import dataclass
from typing import Any, TypeVar

from app.arms.dynamixel.sim_bus import FACTORY_BAUDRATE, DynamixelBus
from app.arms.dynamixel.sim_mx28 import BAUD_CODES
from app.runtime.control_thread import thread_ids
from app.sim.servers import PtyServer, serve_pty

T = TypeVar("T")

#: How long starting or stopping the bus's thread, or one change to its bus, may take, s.
CALL_TIMEOUT_S = 10.0
#: The pty's symlink's private folder, in the system's temporary directory.
FOLDER_PREFIX = "armserver-practice-"
#: Servos one practice bus holds at most (the set-up scan waits for 20 replies).
MAX_SERVOS = 8
#: The bus's process's niceness where the system allows raising it (module doc; 0: as the
#: server's, where it does not).
NICENESS = -5


@dataclass(frozen=True)
class PracticeServo:
    """A servo of the practice bus as the bus holds it (what a scan would find)."""

    id: int
    baudrate: int


class PracticeBus:
    """A factory-state simulated bus on a pseudo-terminal, served by a process of its own
    (`_BusThread` there); `port` is the path to open. Blocking calls, one at a time."""

    def __init__(self, servos: int = 1) -> None:
        self._lock = threading.Lock()
        self._proc = subprocess.Popen(
            [sys.executable, "-m", __name__, str(int(servos))], stdin=subprocess.PIPE,
            stdout=subprocess.PIPE, text=True, bufsize=1, close_fds=True)
        try:
            self.port: str = self._answer()
        except BaseException:
            self._end()
            raise

    def _answer(self) -> Any:
        """The child's next answer line; ValueError for its refusal, or once it has ended."""
        out = self._proc.stdout
        assert out is not None
        ready, _, _ = select.select([out], [], [], CALL_TIMEOUT_S)
        line = out.readline() if ready else ""
        if not line:
            raise ValueError("the practice bus is stopped")
        answer = json.loads(line)
        if "error" in answer:
            raise ValueError(answer["error"])
        return answer["ok"]

    def _ask(self, op: str) -> list[PracticeServo]:
        with self._lock:
            if self._proc.poll() is not None or self._proc.stdin is None:
                raise ValueError("the practice bus is stopped")
            try:
                self._proc.stdin.write(op + "\n")
                self._proc.stdin.flush()
            except (BrokenPipeError, ValueError):
                raise ValueError("the practice bus is stopped") from None
            return [PracticeServo(i, b) for i, b in self._answer()]

    def servos(self) -> list[PracticeServo]:
        """Every servo on the bus, in the order plugged in."""
        return self._ask("servos")

    def plug(self) -> list[PracticeServo]:
        """Plug one more factory servo (ID 1, 57,600 bps) into the bus; ValueError past
        MAX_SERVOS."""
        return self._ask("plug")

    def close(self) -> None:
        """Stop listening and end the process (idempotent)."""
        with self._lock:
            self._end()

    def _end(self) -> None:
        if self._proc.stdin is not None and not self._proc.stdin.closed:
            try:
                self._proc.stdin.close()  # the child closes its bus and ends
            except BrokenPipeError:
                pass
        try:
            self._proc.wait(CALL_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            self._proc.kill()
            self._proc.wait(CALL_TIMEOUT_S)
        if self._proc.stdout is not None:
            self._proc.stdout.close()
        folder = os.path.dirname(getattr(self, "port", "") or "")
        if os.path.basename(folder).startswith(FOLDER_PREFIX):  # a killed child's, left
            shutil.rmtree(folder, ignore_errors=True)


class _BusThread:
    """The bus itself, in the child process: owned by its own thread and event loop."""

    def __init__(self, servos: int = 1) -> None:
        self.bus = DynamixelBus.factory(servos, baudrate=FACTORY_BAUDRATE)
        self._dir = tempfile.mkdtemp(prefix=FOLDER_PREFIX)
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


def raise_priority(tid: int = 0) -> None:
    """Thread `tid` (0: the calling one) at NICENESS, where the system allows it (else as it
    is: not allowed, it keeps the niceness it had). Also for a simulated board served from a
    test's thread (tests/_tcp.py `LoopThread`)."""
    with contextlib.suppress(OSError):
        os.setpriority(os.PRIO_PROCESS, tid, NICENESS)


def _raise_priority() -> None:
    """This process's threads at NICENESS, where the system allows it (else as they are).
    Niceness is a thread's own on Linux: each thread there now (the imports' own, numpy's
    BLAS workers) is set; the bus's thread, started after, inherits it."""
    for tid in thread_ids():
        raise_priority(tid)


def _serve(servos: int) -> None:
    """The child: the bus, then one answer line for each request line until stdin closes."""
    def say(**answer: Any) -> None:
        sys.stdout.write(json.dumps(answer) + "\n")
        sys.stdout.flush()

    _raise_priority()
    bus = _BusThread(servos)
    try:
        say(ok=bus.port)
        for line in sys.stdin:
            op = line.strip()
            if op not in ("plug", "servos"):
                say(error=f"unknown request {op!r}")
                continue
            try:
                if op == "plug":
                    bus.plug()
                say(ok=[[p.id, p.baudrate] for p in bus.servos()])
            except ValueError as exc:
                say(error=str(exc))
    finally:
        bus.close()


if __name__ == "__main__":
    _serve(int(sys.argv[1]))
