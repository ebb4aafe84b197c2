"""What the benchmarks share: `armserver serve` in a subprocess on a free loopback port (so the
server's CPU and memory figures are its own), and percentile helpers."""

from __future__ import annotations

import contextlib
import json
import os
import random
import socket
import subprocess
import sys
import time
import urllib.request
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import _machine

ROOT = Path(__file__).resolve().parent.parent


def pin_apart(server_pid: int) -> bool:
    """Server on core 0, this (client) process on the others, where there are two or more.

    On a 2-core machine 100 Python WebSocket clients parsing 50,000 samples/s fill a core; left
    to share, they starve the server's 2 ms poll timer and the bench measures its own clients.
    """
    cpus = sorted(os.sched_getaffinity(0))
    if len(cpus) < 2:
        return False
    os.sched_setaffinity(server_pid, {cpus[0]})
    os.sched_setaffinity(0, set(cpus[1:]))
    return True


def free_port() -> int:
    """A loopback port free now (the kernel's pick)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class ServerProcess:
    """`armserver serve` on a free loopback port: simulated arms (or `config`'s), no tokens;
    `env`: ARMSERVER_ settings of its own (none of this process's pass). Ready once its health
    says `ok` (and `ready(health)`, where given) within `timeout` s."""

    def __init__(self, pin: bool = False, config: Path | None = None,
                 env: dict[str, str] | None = None, timeout: float = 30.0,
                 ready: Callable[[dict[str, Any]], bool] | None = None) -> None:
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.ws_url = f"ws://127.0.0.1:{self.port}"
        environ = {k: v for k, v in os.environ.items() if not k.startswith("ARMSERVER_")}
        self.proc = subprocess.Popen(
            [sys.executable, "-c", "from app.cli import run; run()", "serve", "--port",
             str(self.port), "--log-level", "warning",
             *(["--config", str(config)] if config is not None else [])],
            cwd=ROOT, env={**environ, **(env or {})}, stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL)
        self.pinned = pin_apart(self.proc.pid) if pin else False
        self._wait_ready(timeout, ready)

    def health(self, timeout: float = 20.0) -> dict[str, Any]:
        """`GET /health`'s answer."""
        with urllib.request.urlopen(self.url + "/api/v1/health", timeout=timeout) as r:
            return json.loads(r.read())  # type: ignore[no-any-return]

    def _wait_ready(self, timeout: float,
                    ready: Callable[[dict[str, Any]], bool] | None) -> None:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            with contextlib.suppress(OSError, ValueError, KeyError):
                health = self.health(timeout=1)
                if health["status"] == "ok" and (ready is None or ready(health)):
                    return
            time.sleep(0.1)
        self.close()
        raise RuntimeError("the server did not become healthy")

    def _proc(self, name: str) -> str:
        return Path(f"/proc/{self.proc.pid}/{name}").read_text()

    def rss_mib(self) -> float:
        """Resident memory of the server process, MiB."""
        for line in self._proc("status").splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
        return float("nan")

    def cpu_seconds(self) -> float:
        """User + system CPU time of the server process, s."""
        return _machine.ticks_cpu_s(self.proc.pid)

    def close(self) -> None:
        self.proc.terminate()
        try:
            self.proc.wait(10)
        except subprocess.TimeoutExpired:
            self.proc.kill()


@contextlib.contextmanager
def server(pin: bool = False) -> Iterator[ServerProcess]:
    srv = ServerProcess(pin)
    try:
        yield srv
    finally:
        srv.close()


def pct(values: list[float], q: float) -> float:
    """The q-quantile (0..1) of `values`, nearest rank; NaN for none."""
    if not values:
        return float("nan")
    v = sorted(values)
    return v[min(len(v) - 1, int(q * len(v)))]


def pct_spread(values: list[float], q: float, resamples: int = 2000,
               seed: int = 0) -> tuple[float, float]:
    """How far `pct(values, q)` moves on its own: the 5th and 95th percentiles of it over
    `resamples` resamplings of `values` with replacement (bootstrap; a fixed seed, so a run's
    figure is reproducible from its values). The p99 of 300 presses is their third slowest: one
    run's own figure moved by 1-2 ms this way (docs/performance.md "Session 22")."""
    if not values:
        return float("nan"), float("nan")
    rnd = random.Random(seed)
    n = len(values)
    got = sorted(pct(rnd.choices(values, k=n), q) for _ in range(resamples))
    return got[int(0.05 * resamples)], got[min(resamples - 1, int(0.95 * resamples))]
