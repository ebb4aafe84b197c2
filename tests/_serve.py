"""`armserver serve` as a user starts it, for the tests that need a real process (a signal, a
kill -9, the command line itself): a subprocess on a free loopback port, the caller's
`ARMSERVER_*` settings left out, its output to a file.

Not to a pipe: a pipe nobody reads while the test runs holds 64 KiB, and then the server's next
log line blocks the thread that writes it (an arm's, the HTTP thread) until the test reads,
which it does at the end. A file never fills; a failure's message quotes its last lines.

    with served(tmp_path / "server.log", "--log-level", "warning") as srv:
        httpx.get(f"{srv.url}/api/v1/health")
    assert "stopping every arm" in srv.output()
"""

from __future__ import annotations

import contextlib
import os
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import httpx

from tests._http import HTTP
from tests._mosquitto import free_port

ROOT = Path(__file__).resolve().parent.parent
API = "/api/v1"
#: Longest a server may take to start and have every arm's state fresh, s (a process start
#: and its imports on a loaded two-core machine).
START_S = 30.0
#: Longest a server may take to end after SIGTERM before the test kills it, s.
STOP_S = 20.0


def clean_env(**extra: str) -> dict[str, str]:
    """This process's environment without its `ARMSERVER_*` settings, plus `extra`."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("ARMSERVER_")}
    env.update(extra)
    return env


@dataclass
class Served:
    proc: subprocess.Popen[bytes]
    url: str
    log: Path

    def output(self) -> str:
        """Everything the server has written so far (stdout and stderr)."""
        return self.log.read_text(errors="replace") if self.log.exists() else ""

    def tail(self, lines: int = 30) -> str:
        """The last lines of output, for a failure's message."""
        return "the server said:\n" + "\n".join(self.output().splitlines()[-lines:])

    def ended(self, timeout: float) -> str:
        """Wait up to `timeout` s for the process to end on its own (after a signal): its
        output. Past it, an AssertionError (the process is killed)."""
        try:
            self.proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
            raise AssertionError(f"the server did not end within {timeout} s; "
                                 f"{self.tail()}") from None
        return self.output()

    def stop(self) -> None:
        """SIGTERM, then SIGKILL if it has not ended within STOP_S; nothing if it has ended."""
        if self.proc.poll() is not None:
            return
        self.proc.terminate()
        try:
            self.proc.wait(timeout=STOP_S)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()


def start(log: Path, *args: str, env: dict[str, str] | None = None,
          command: tuple[str, ...] = ("-m", "app.cli", "serve"),
          start_s: float = START_S, headers: dict[str, str] | None = None) -> Served:
    """`armserver serve ARGS --port P`, output appended to `log`, once its health is "ok"
    (every worker of a lab up, every link connected) and every arm it hosts answers a state
    that is not stale (an AssertionError with its output and what it last answered after
    `start_s`, or as soon as it exits). `headers`: what those requests carry (a viewer's
    token, on a server with tokens)."""
    port = free_port()
    log.parent.mkdir(parents=True, exist_ok=True)
    with log.open("ab") as out:
        proc = subprocess.Popen([sys.executable, *command, *args, "--port", str(port)],
                                cwd=ROOT, env=clean_env() if env is None else env,
                                stdout=out, stderr=subprocess.STDOUT)
    srv = Served(proc, f"http://127.0.0.1:{port}", log)
    deadline = time.monotonic() + start_s
    last = "no answer"
    try:
        # the tests' one client (tests/_http.py): a client per try, every 0.1 s, was 2 % of
        # the parallel part's CPU (py-spy, session 28)
        def get(path: str) -> httpx.Response:
            return HTTP.get(f"{srv.url}{API}{path}", headers=headers, timeout=2)

        while True:
            assert proc.poll() is None, f"the server exited ({proc.returncode}); {srv.tail()}"
            assert time.monotonic() < deadline, \
                f"the server was not ready within {start_s} s ({last}); {srv.tail()}"
            try:
                health = get("/health").json()["status"]
                arms = get("/arms").raise_for_status().json()
                stale = [a["name"] for a in arms
                         if get(f"/arms/{a['name']}/state").json()["stale"]]
                if health == "ok" and arms and not stale:
                    return srv
                last = f"health {health}, stale: {stale}" if arms else f"health {health}"
            except (httpx.HTTPError, ValueError, KeyError) as exc:
                last = f"{type(exc).__name__}: {exc}"
            time.sleep(0.1)
    except BaseException:
        srv.stop()
        raise


@contextlib.contextmanager
def served(log: Path, *args: str, **kw: object) -> Iterator[Served]:
    """`start(...)`, stopped (SIGTERM, bounded) on the way out whatever happened."""
    srv = start(log, *args, **kw)  # type: ignore[arg-type]
    try:
        yield srv
    finally:
        srv.stop()
