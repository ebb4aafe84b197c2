"""Telemetry fan-out benchmark: N WebSocket clients on the simulated rbe3001 (500 Hz).

Starts `armserver serve` on the simulated arms in a subprocess (so its CPU is its own), connects
N = 1, 10, 100 clients for T seconds each, and prints per N:

- samples/s per client (mean) and messages/s per client,
- lost: gaps in `seq` plus the server's `dropped` counts, summed over clients,
- latency from the device timestamp (`time`) to receipt: median and p99 over every sample
  (includes the batching delay, up to 1/rate) and over the newest sample of each message,
- server CPU: share of one core, from /proc/<pid>/stat (psutil if installed).

    python bench/telemetry.py --seconds 5 --rate 50 --clients 1,10,100
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import os
import socket
import statistics
import subprocess
import sys
import time
import urllib.request
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


# ---------------------------------------------------------------- the server under test


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


class ServerProcess:
    """`armserver serve` on a free loopback port, simulated arms, no tokens."""

    def __init__(self) -> None:
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            self.port = s.getsockname()[1]
        self.url = f"http://127.0.0.1:{self.port}"
        self.ws_url = f"ws://127.0.0.1:{self.port}"
        env = {k: v for k, v in os.environ.items() if not k.startswith("ARMSERVER_")}
        self.proc = subprocess.Popen(
            [sys.executable, "-c", "from app.main import cli; cli()", "serve", "--port",
             str(self.port), "--log-level", "warning"],
            cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        self.pinned = pin_apart(self.proc.pid)
        self._wait_ready()

    def _wait_ready(self, timeout: float = 30.0) -> None:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            try:
                with urllib.request.urlopen(self.url + "/api/v1/health", timeout=1) as r:
                    if json.loads(r.read())["status"] == "ok":
                        return
            except OSError:
                pass
            time.sleep(0.1)
        self.close()
        raise RuntimeError("the server did not become healthy")

    def cpu_seconds(self) -> float:
        """User + system CPU time of the server process, s."""
        try:
            import psutil  # type: ignore[import-not-found]

            t = psutil.Process(self.proc.pid).cpu_times()
            return float(t.user + t.system)
        except ImportError:
            fields = Path(f"/proc/{self.proc.pid}/stat").read_text().rsplit(")", 1)[1].split()
            return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")

    def close(self) -> None:
        self.proc.terminate()
        try:
            self.proc.wait(10)
        except subprocess.TimeoutExpired:
            self.proc.kill()


@contextlib.contextmanager
def server() -> Iterator[ServerProcess]:
    srv = ServerProcess()
    try:
        yield srv
    finally:
        srv.close()


def pct(values: list[float], q: float) -> float:
    if not values:
        return float("nan")
    v = sorted(values)
    return v[min(len(v) - 1, int(q * len(v)))]


# ---------------------------------------------------------------- clients


@dataclass
class ClientStats:
    samples: int = 0
    messages: int = 0
    gaps: int = 0
    dropped: int = 0
    first_seq: int | None = None
    last_seq: int | None = None
    t_first: float = 0.0
    t_last: float = 0.0
    latency: list[float] = field(default_factory=list)
    newest: list[float] = field(default_factory=list)


async def _client(url: str, seconds: float, start: asyncio.Event, st: ClientStats) -> None:
    """Read from connect on (so nothing piles up before the window); count within it."""
    from websockets.asyncio.client import connect

    async with connect(url, max_size=None) as ws:
        last_seq: int | None = None
        deadline: float | None = None
        while deadline is None or time.monotonic() < deadline:
            try:
                raw = await asyncio.wait_for(ws.recv(), 0.2)
            except TimeoutError:
                continue
            now = time.time()
            if deadline is None and start.is_set():
                deadline = time.monotonic() + seconds
            msg = json.loads(raw)
            if msg["type"] != "telemetry" or deadline is None:
                if msg["type"] == "telemetry" and msg["samples"]:
                    last_seq = msg["samples"][-1]["seq"]
                continue
            st.messages += 1
            st.dropped += msg["dropped"]
            samples = msg["samples"]
            if not samples:
                continue
            first, last = samples[0]["seq"], samples[-1]["seq"]
            # gaps between messages, and inside this one (a batch is in seq order)
            if last_seq is not None:
                st.gaps += max(0, first - last_seq - 1)
            st.gaps += (last - first + 1) - len(samples)
            if st.first_seq is None:
                st.first_seq, st.t_first = first, samples[0]["time"]
            st.last_seq, st.t_last = last, samples[-1]["time"]
            last_seq = last
            st.latency.extend([now - x["time"] for x in samples])
            st.newest.append(now - samples[-1]["time"])
            st.samples += len(samples)


async def run_n(srv: ServerProcess, n: int, seconds: float, rate: float, arm: str) -> dict:
    url = f"{srv.ws_url}/api/v1/arms/{arm}/telemetry?rate={rate}"
    stats = [ClientStats() for _ in range(n)]
    start = asyncio.Event()
    tasks = [asyncio.create_task(_client(url, seconds, start, st)) for st in stats]
    await asyncio.sleep(0.5 + n * 0.01)  # let every client connect
    cpu0, t0 = srv.cpu_seconds(), time.monotonic()
    start.set()
    await asyncio.gather(*tasks)
    cpu = (srv.cpu_seconds() - cpu0) / (time.monotonic() - t0)
    lat = [x for st in stats for x in st.latency]
    newest = [x for st in stats for x in st.newest]
    # the device's sample rate, from the sample timestamps a client saw (not its own reading
    # speed: a client process parsing 100 sockets may fall behind its window)
    spans = [(st.last_seq - st.first_seq) / (st.t_last - st.t_first) for st in stats
             if st.first_seq is not None and st.t_last > st.t_first]
    return {
        "n": n,
        "device_hz": statistics.mean(spans) if spans else 0.0,
        "samples_s": statistics.mean(st.samples for st in stats) / seconds,
        "messages_s": statistics.mean(st.messages for st in stats) / seconds,
        "lost": sum(st.gaps + st.dropped for st in stats),
        "lat_med_ms": 1000 * pct(lat, 0.5), "lat_p99_ms": 1000 * pct(lat, 0.99),
        "new_med_ms": 1000 * pct(newest, 0.5), "new_p99_ms": 1000 * pct(newest, 0.99),
        "cpu": cpu,
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--seconds", type=float, default=5.0, help="measuring time per N, s")
    p.add_argument("--rate", type=float, default=50.0, help="messages per second asked, Hz")
    p.add_argument("--clients", default="1,10,100", help="client counts, comma separated")
    p.add_argument("--arm", default="rbe3001")
    a = p.parse_args(argv)
    counts = [int(x) for x in a.clients.split(",") if x.strip()]
    rows = []
    with server() as srv:
        for n in counts:
            rows.append(asyncio.run(run_n(srv, n, a.seconds, a.rate, a.arm)))
    print(f"server pinned to its own core, clients to the other(s): {srv.pinned}")
    print(f"telemetry fan-out: arm {a.arm}, rate {a.rate:g} Hz, {a.seconds:g} s per row "
          f"(latency = device timestamp -> receipt; 'all' includes batching, 'newest' is the "
          f"last sample of each message; 'device Hz' is the sample rate from the samples' own "
          f"timestamps, 'read/s' what each client got through in its window)")
    print(f"{'N':>4} {'device Hz':>9} {'read/s':>7} {'msgs/s':>7} {'lost':>6} "
          f"{'all med':>8} {'all p99':>8} "
          f"{'new med':>8} {'new p99':>8} {'srv CPU':>8}")
    for r in rows:
        print(f"{r['n']:>4} {r['device_hz']:>9.1f} {r['samples_s']:>7.1f} "
              f"{r['messages_s']:>7.1f} {r['lost']:>6} "
              f"{r['lat_med_ms']:>6.1f}ms {r['lat_p99_ms']:>6.1f}ms {r['new_med_ms']:>6.1f}ms "
              f"{r['new_p99_ms']:>6.1f}ms {100 * r['cpu']:>7.0f}%")
    return 0


if __name__ == "__main__":
    sys.path.insert(0, str(ROOT))
    raise SystemExit(main())
