"""A whole lab on one PC (issue 27): N simulated arms on emulated links, one server address.

    python bench/lab.py [--arms 4] [--workers 2] [--model rbe3001] [--seconds 10] [--per-sim 16]
                        [--pin]

Starts the arms' simulators out of the server's process (the project's simulated firmware or
servo bus, one device and one `socket://127.0.0.1:PORT` address per arm), `--per-sim` arms of
one worker to a process (`armserver sim MODEL --listen tcp://127.0.0.1:PORT --listen ...`: one
event loop for them, woken once by each of that worker's poll rounds), then `armserver serve
--workers W` over them (W = 1: today's single process), and while every arm runs at its poll
rate prints:

- server CPU: front and workers together, % of one core, in all and per arm, over `--seconds`
  with no client asking anything (what the arms cost); the simulators' CPU and the whole
  machine's beside it (on two cores the simulators share the machine with the server);
- samples/s per arm over that window, min and mean over the arms (each arm's `seq` over its
  own sample clock), the slowest arm's name and how many were under issue 27's 490;
- then REST `GET /state` p50/p99 through the front, round robin over the arms, one client; the
  same request straight to a worker's Unix socket (the front's own cost is the difference);
- the estop through the front, two ways (presses spread over the arms, each released after,
  with the pauses of `make bench-peers`' harness around it):
  - answered: until the POST's answer, which comes once the hold is commanded on the device
    (its status reply read: a device round trip behind the poll in flight); the first press
    on each arm and the later ones apart, and the same straight to a worker's socket;
  - seen: until the first telemetry sample that shows the latch (`make bench-peers`' estop
    figure, and the one issue 27's "estop p99 under 5 ms" is read as), with one telemetry
    client at rate=500 on the arm pressed, a socket opened for each press, as the harness
    (with how far its p99 moves when its presses are resampled: `_server.pct_spread`);
    as many presses again, alternated with those, written as raw bytes on a kept-alive
    connection (`RawClient`: the figure without the measuring client's httpx in it);
    and again with SEEN_STREAMS sockets streaming at 500 Hz all along (the front relays, and
    this client reads, every sample of them).
- the WebSocket relay's cost: `--relay-clients` telemetry clients (default SEEN_STREAMS) at
  `--relay-rate` (default 500: each sample as it is published), spread over the arms: the
  messages a second the front relayed, and its CPU a message (less what it spends with no
  client; user time apart: the rest is the kernel's, the sockets and the wake-ups);
- with `--teleop` (3 arms or more, 2 workers): a teleoperation session's latency from a leader
  sample to the follower's command (p50/p99, as `GET /teleop` reports it), the leader moving
  back and forth, once with both arms on one worker and once with the leader on the other
  worker (read over its worker's telemetry socket: the hop is the difference).

The simulators run at niceness `--sims-nice` (default 19): they stand in for devices that
compute on processors of their own, so they take what CPU the server leaves and never hold a
core the server's threads want (what issue 27's first table got by pinning them to the other
core; `--pin` below). Where the kernel groups the CPU by session (autogroup), each simulator
process is a session of its own with its group at that niceness (in the bench's session their
niceness did not count against the workers' sessions; 32 arms, estop seen p99 6.87-12.26 ms,
median 8.2, in ten runs against 8.89-11.26, median 10.3, in five, mostly alternated, 28 Nov
2026: docs/performance.md "Session 29").
`--sims-nice 0` runs them as the server's equals: on two cores they then
delay the server's wake-ups by their own (at 32 arms, estop seen p99 14.6 / 15.9 ms against
10.2 / 7.1 ms niced, runs alternated on one busy hour, 27 Nov 2026).

`--pin` puts the server's processes on core 0 and the simulators and this client on the
others (as issue 27's table was measured). The figures need a quiet machine: on a shared one,
quote ratios from one run, not these numbers.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import random
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
import urllib.request
from pathlib import Path
from typing import Any

import httpx
import websockets

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parent.parent))  # (its `kinematics` first)
import _machine  # noqa: E402
from _server import ROOT, pct, pct_spread  # noqa: E402

from app.config import Settings  # noqa: E402
from app.lab.placement import plan_lab  # noqa: E402

API = "/api/v1"


def _free_ports(n: int) -> list[int]:
    socks = [socket.socket() for _ in range(n)]
    for s in socks:
        s.bind(("127.0.0.1", 0))
    ports = [s.getsockname()[1] for s in socks]
    for s in socks:
        s.close()
    return ports


def _sim_groups(config: Path, workers: int, per: int, in_order: bool) -> list[list[int]]:
    """The simulators' ports, `per` to a process: each process's arms those of one worker
    (a worker's poll thread writes its arms' due polls at once, so their requests reach one
    simulator process together: one wake-up a round, not one per worker), or with `in_order`
    the config's next `per` arms (the arms of every worker: the bench before session 33)."""
    plan = plan_lab(Settings(config=str(config)), workers)
    ports = {p.name: int(str(p.link.address).rsplit(":", 1)[1])
             for arms in plan.workers for p in arms}
    lists = [list(plan.names)] if in_order else [[p.name for p in arms] for arms in plan.workers]
    return [[ports[n] for n in names[k:k + per]] for names in lists
            for k in range(0, len(names), per)]


def _autogroup_nice(pid: int, niceness: int) -> bool:
    """Give `pid`'s autogroup `niceness`, where the kernel groups by session (most desktop
    distributions' kernels do: /proc/sys/kernel/sched_autogroup_enabled). There the scheduler
    first shares the CPU between sessions, each worker (a session of its own) equal to the
    session that runs the simulators, and a thread's niceness counts only within its own:
    at niceness 19 in the bench's session the simulators still held a core the workers
    wanted. So each simulator process is a session of its own, its group at `niceness`."""
    try:
        if Path("/proc/sys/kernel/sched_autogroup_enabled").read_text().strip() != "1":
            return False
        Path(f"/proc/{pid}/autogroup").write_text(str(niceness))
    except OSError:
        return False
    return True


def _tree(pid: int) -> list[int]:
    """`pid` and its children (the front and its workers)."""
    try:
        kids = Path(f"/proc/{pid}/task/{pid}/children").read_text().split()
    except FileNotFoundError:
        return []
    return [pid, *(int(k) for k in kids)]


def _worker_socket(pids: list[int]) -> str | None:
    for pid in pids[1:]:
        argv = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
        if b"--uds" in argv:
            return argv[argv.index(b"--uds") + 1].decode()
    return None


def _wait_healthy(url: str, timeout: float) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            with urllib.request.urlopen(url + API + "/health", timeout=2) as r:
                if b'"status":"ok"' in r.read():
                    return
        except OSError:
            pass
        time.sleep(0.2)
    raise RuntimeError("the lab did not become healthy")


async def _rates(c: httpx.AsyncClient, arms: list[str]) -> dict[str, tuple[int, float]]:
    out = {}
    for arm in arms:
        s = (await c.get(f"{API}/arms/{arm}/state")).json()
        out[arm] = (s["seq"], s["time"])
    return out


def _idle_s() -> float:
    """Idle time of all the machine's cores, s (/proc/stat)."""
    with open("/proc/stat") as f:
        return int(f.readline().split()[4]) / os.sysconf("SC_CLK_TCK")


#: Issue 27's least samples/s of any arm (of 500).
MIN_RATE = 490
#: Arms whose telemetry streams at once (each at the poll rate) in the second "latch seen"
#: figure: the first has one stream open at a time, as `make bench-peers`' harness.
SEEN_STREAMS = 4
#: The harness's pauses (../shared/peers/rtt_armserver.py): before a press (uniform, s) and
#: after its release (s): presses land at any phase of the poll schedule, not just after the
#: release's answer.
PAUSE_BEFORE_S = (0.01, 0.03)
PAUSE_AFTER_S = 0.02


async def _telemetry(url: str, arm: str) -> tuple[Any, asyncio.Queue[tuple[float, bool]],
                                                  asyncio.Task[None]]:
    """A telemetry socket on `arm` at rate=500 (each sample as it is published), its samples'
    arrival times and estop flags as they come, and the task that reads them."""
    ws = await websockets.connect(f"{url.replace('http', 'ws', 1)}{API}/arms/{arm}/telemetry"
                                  "?rate=500", max_size=None, compression=None)
    queue: asyncio.Queue[tuple[float, bool]] = asyncio.Queue()

    async def read() -> None:
        async for m in ws:
            for smp in json.loads(m).get("samples", []):
                queue.put_nowait((time.perf_counter(), bool(smp["estop"])))

    return ws, queue, asyncio.create_task(read())


class RawClient:
    """Body-less requests written as bytes on one kept-alive connection, the answer's head and
    body read back: a press timed from the moment its bytes go, without an HTTP client
    library's own work in it (httpx builds and parses a request in about a millisecond of
    Python on this host: 1.3 ms of the seen median, 2.5 ms of its p99, 28 Nov 2026)."""

    def __init__(self, url: str) -> None:
        self.host, port = url.split("//", 1)[1].split(":")
        self.port = int(port)
        self._io: tuple[asyncio.StreamReader, asyncio.StreamWriter] | None = None

    async def request(self, method: str, path: str) -> int:
        """The answer's status; the answer read whole."""
        if self._io is None:
            self._io = await asyncio.open_connection(self.host, self.port)
        reader, writer = self._io
        writer.write(f"{method} {path} HTTP/1.1\r\nhost: {self.host}:{self.port}\r\n"
                     "content-length: 0\r\n\r\n".encode())
        head = await reader.readuntil(b"\r\n\r\n")
        length = next((int(line.split(b":", 1)[1]) for line in head.split(b"\r\n")
                       if line.lower().startswith(b"content-length:")), 0)
        await reader.readexactly(length)
        return int(head.split(b" ", 2)[1])

    async def close(self) -> None:
        if self._io is not None:
            self._io[1].close()
            await self._io[1].wait_closed()


async def _status(c: httpx.AsyncClient | RawClient, method: str, path: str) -> int:
    """The status of a body-less `method path`, by either client."""
    if isinstance(c, RawClient):
        return await c.request(method, path)
    return (await c.request(method, path)).status_code


async def _press_seen(c: httpx.AsyncClient | RawClient, arm: str,
                      queue: asyncio.Queue[tuple[float, bool]]) -> float:
    """One press as the harness makes it: a pause, `POST /estop`, the time to the first sample
    on `queue` that shows the latch; then the release and a pause."""
    await asyncio.sleep(random.uniform(*PAUSE_BEFORE_S))
    while not queue.empty():
        queue.get_nowait()
    path = f"{API}/arms/{arm}/estop"
    start = time.perf_counter()
    status = await _status(c, "POST", path)
    assert status == 200, status
    while True:
        at, latched = await asyncio.wait_for(queue.get(), 5)
        if latched:
            break
    status = await _status(c, "DELETE", path)
    assert status == 200, status
    await asyncio.sleep(PAUSE_AFTER_S)
    return at - start


async def estop_seen(c: httpx.AsyncClient, url: str, arms: list[str],
                     presses: int) -> tuple[list[float], list[float]]:
    """Seconds from each `POST /estop` to the first telemetry sample that shows the latch, as
    `make bench-peers`' harness measures it: one telemetry client (rate=500) on the arm it
    presses. Presses go over every arm in turn, each with a socket of its own opened before
    and closed after (one stream at a time, as the harness's). `presses` with httpx (the
    harness's client) and as many as raw bytes (`RawClient`), alternated: both lists."""
    out: tuple[list[float], list[float]] = ([], [])
    raw = RawClient(url)
    try:
        for i in range(2 * presses):
            arm = arms[i // 2 % len(arms)]
            way = (i + i // 2) % 2  # (each way first on every other arm)
            ws, queue, reader = await _telemetry(url, arm)
            try:
                await asyncio.wait_for(queue.get(), 5)  # streaming
                out[way].append(await _press_seen((c, raw)[way], arm, queue))
            finally:
                reader.cancel()
                await ws.close()
    finally:
        await raw.close()
    return out


async def estop_seen_streams(c: httpx.AsyncClient, url: str, arms: list[str],
                             presses: int) -> list[float]:
    """The same with a telemetry client streaming on each of `arms` all along (rate=500
    each: the front relays and this client reads every sample of them), presses spread over
    them."""
    socks = [await _telemetry(url, a) for a in arms]
    out: list[float] = []
    try:
        for i in range(presses):
            k = i % len(arms)
            out.append(await _press_seen(c, arms[k], socks[k][1]))
    finally:
        for ws, _, reader in socks:
            reader.cancel()
            await ws.close()
    return out


async def relay_cost(url: str, arms: list[str], seconds: float, front: int,
                     rate: int = 500) -> tuple[float, float, float, float]:
    """Messages and bytes a second the front relayed to one telemetry client (at `rate`; 500:
    each sample as it is published, and an arm at rest hands its repeats over in batches) per
    entry of `arms` over `seconds`, and the front's CPU meanwhile (s a second), in all and
    user."""
    got = [0, 0]

    async def read(arm: str) -> None:
        async with websockets.connect(f"{url.replace('http', 'ws', 1)}{API}/arms/{arm}"
                                      f"/telemetry?rate={rate}", max_size=None,
                                      compression=None) as ws:
            async for m in ws:
                got[0] += 1
                got[1] += len(m)

    readers = [asyncio.create_task(read(a)) for a in arms]
    try:
        await asyncio.sleep(1.0)  # streaming
        n0, b0 = got
        cpu0, user0 = _machine.process_cpu_s(front), _machine.ticks_cpu_s(front, part=slice(0, 1))
        t0 = time.monotonic()
        await asyncio.sleep(seconds)
        span = time.monotonic() - t0
        cpu = (_machine.process_cpu_s(front) - cpu0) / span
        user = (_machine.ticks_cpu_s(front, part=slice(0, 1)) - user0) / span
        n, b = got[0] - n0, got[1] - b0
    finally:
        for r in readers:
            r.cancel()
        await asyncio.gather(*readers, return_exceptions=True)
    return n / span, b / span, cpu, user


async def _presses(c: httpx.AsyncClient, arms: list[str],
                   presses: int) -> tuple[list[float], list[float]]:
    """Seconds each `POST /estop` took to answer (the hold commanded on the device), presses
    spread over `arms` in turn, each released after, with the harness's pauses; the first
    press on each arm and the later ones apart."""
    first: list[float] = []
    later: list[float] = []
    for i in range(presses):
        arm = arms[i % len(arms)]
        await asyncio.sleep(random.uniform(*PAUSE_BEFORE_S))
        start = time.perf_counter()
        r = await c.post(f"{API}/arms/{arm}/estop")
        (first if i < len(arms) else later).append(time.perf_counter() - start)
        assert r.status_code == 200, r.text
        r = await c.delete(f"{API}/arms/{arm}/estop")
        assert r.status_code == 200, r.text
        await asyncio.sleep(PAUSE_AFTER_S)
    return first, later


async def measure(url: str, arms: list[str], seconds: float, presses: int, relay: tuple[int, int],
                  uds: str | None, pids: list[int], sims: list[int]) -> None:
    async with httpx.AsyncClient(base_url=url, timeout=10) as c:
        first = await _rates(c, arms)
        cpu0, sim0 = _machine.ticks_cpu_s(*pids), _machine.ticks_cpu_s(*sims)
        idle0, t0 = _idle_s(), time.monotonic()
        front0 = _machine.process_cpu_s(pids[0])
        await asyncio.sleep(seconds)  # the arms alone: their cost, no client's
        span = time.monotonic() - t0
        cpu = (_machine.ticks_cpu_s(*pids) - cpu0) / span
        front_idle = (_machine.process_cpu_s(pids[0]) - front0) / span
        sim_cpu = (_machine.ticks_cpu_s(*sims) - sim0) / span
        busy = (os.cpu_count() or 1) - (_idle_s() - idle0) / span
        last = await _rates(c, arms)
        rest: list[float] = []
        k = 0
        t0 = time.monotonic()
        while time.monotonic() - t0 < seconds:
            arm = arms[k % len(arms)]
            k += 1
            start = time.perf_counter()
            r = await c.get(f"{API}/arms/{arm}/state")
            rest.append(time.perf_counter() - start)
            assert r.status_code == 200, r.text
        estop_first, estop_later = await _presses(c, arms, presses)
        seen, seen_raw = await estop_seen(c, url, arms, presses)
        seen_streams = await estop_seen_streams(c, url, arms[:SEEN_STREAMS], presses)
        watchers = [arms[k % len(arms)] for k in range(relay[0])]
        relayed, relayed_bytes, front_busy, front_user = await relay_cost(
            url, watchers, seconds, pids[0], relay[1])
    direct: list[float] = []
    estop_direct: list[float] = []
    if uds is not None:
        transport = httpx.AsyncHTTPTransport(uds=uds)
        async with httpx.AsyncClient(transport=transport, base_url="http://localhost") as w:
            mine = (await w.get(f"{API}/arms")).json()
            name = mine[0]["name"]
            for _ in range(max(200, len(rest) // 4)):
                start = time.perf_counter()
                await w.get(f"{API}/arms/{name}/state")
                direct.append(time.perf_counter() - start)
            one, more = await _presses(w, [name], presses)
            estop_direct = one + more
    by_arm = {a: (last[a][0] - first[a][0]) / (last[a][1] - first[a][1]) for a in arms}
    rates = list(by_arm.values())
    slowest = min(by_arm, key=by_arm.__getitem__)
    n = len(arms)
    print(f"server CPU        {100 * cpu:.0f} % of a core in all, {100 * cpu / n:.1f} % per arm")
    print(f"simulators CPU    {100 * sim_cpu:.0f} % of a core; the whole machine busy "
          f"{100 * busy:.0f} % of {100 * (os.cpu_count() or 1)}")
    print(f"samples/s per arm min {by_arm[slowest]:.0f}  mean {sum(rates) / n:.0f}  (the slowest: "
          f"{slowest}; {sum(r < MIN_RATE for r in rates)} of {n} under {MIN_RATE})")
    print(f"REST GET state    p50 {1e3 * pct(rest, 0.5):.2f} ms  p99 {1e3 * pct(rest, 0.99):.2f}"
          f" ms through the front ({len(rest)} requests)")
    if direct:
        print(f"  straight to a worker's socket: p50 {1e3 * pct(direct, 0.5):.2f} ms  p99 "
              f"{1e3 * pct(direct, 0.99):.2f} ms (the front's hop: the difference)")
    estop = estop_first + estop_later
    print(f"estop answered    p50 {1e3 * pct(estop, 0.5):.2f} ms  p99 {1e3 * pct(estop, 0.99):.2f}"
          f" ms through the front ({len(estop)} presses: the hold commanded on the device)")
    if estop_later:
        print(f"  the first press on each arm: p50 {1e3 * pct(estop_first, 0.5):.2f} ms  p99 "
              f"{1e3 * pct(estop_first, 0.99):.2f} ms; the later ones: p50 "
              f"{1e3 * pct(estop_later, 0.5):.2f} ms  p99 {1e3 * pct(estop_later, 0.99):.2f} ms")
    if estop_direct:
        print(f"  straight to a worker's socket: p50 {1e3 * pct(estop_direct, 0.5):.2f} ms  p99 "
              f"{1e3 * pct(estop_direct, 0.99):.2f} ms")
    print(f"estop seen        p50 {1e3 * pct(seen, 0.5):.2f} ms  p99 {1e3 * pct(seen, 0.99):.2f}"
          f" ms: the latch in the first telemetry sample, one stream at a time on the arm "
          f"pressed (as `make bench-peers`; {len(seen)} presses over {n} arms)")
    lo, hi = pct_spread(seen, 0.99)
    print(f"  its p99 resampled (bootstrap, 5-95 %): {1e3 * lo:.2f}-{1e3 * hi:.2f} ms: how far "
          "the figure of this many presses moves on its own")
    print(f"  the press as raw bytes (no httpx in its time), alternated with those: p50 "
          f"{1e3 * pct(seen_raw, 0.5):.2f} ms  p99 {1e3 * pct(seen_raw, 0.99):.2f} ms")
    print(f"  with {min(SEEN_STREAMS, n)} streams at 500 Hz all along: p50 "
          f"{1e3 * pct(seen_streams, 0.5):.2f} ms  p99 {1e3 * pct(seen_streams, 0.99):.2f} ms")
    per = (front_busy - front_idle) / relayed if relayed else float("nan")
    per_user = front_user / relayed if relayed else float("nan")
    print(f"WebSocket relay   {relayed:.0f} messages/s ({relayed_bytes / 1e6:.2f} MB/s) on "
          f"{relay[0]} streams at rate={relay[1]}: the "
          f"front {100 * front_busy:.1f} % of a core ({100 * front_idle:.1f} % with none), "
          f"{1e6 * per:.0f} µs a message ({1e6 * per_user:.0f} of them user)")


async def teleop_latency(url: str, leader: str, follower: str, seconds: float) -> str:
    """One session of `seconds`, the leader moved between two poses: its latency line."""
    async with httpx.AsyncClient(base_url=url, timeout=30) as c:
        # the emulated arms are serial links: their torque stays on (free_leader false), the
        # leader moved by its own commands
        r = await c.post(f"{API}/teleop", json={"leader": leader, "follower": follower,
                                                "rate_hz": 100, "free_leader": False})
        assert r.status_code == 201, r.text
        sid = r.json()["id"]
        t0, k = time.monotonic(), 0
        while time.monotonic() - t0 < seconds:
            q = [0.3, 0.2, 0.1] if k % 2 == 0 else [-0.3, 0.1, 0.2]
            k += 1
            await c.post(f"{API}/arms/{leader}/move/joints", json={"positions": q,
                                                                   "wait": True})
        r = await c.delete(f"{API}/teleop/{sid}")
        lat = r.json()["latency_ms"]
        return (f"p50 {lat['p50']:.2f} ms  p99 {lat['p99']:.2f} ms "
                f"({r.json()['commands']} commands)")


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--arms", type=int, default=4)
    p.add_argument("--workers", type=int, default=2, help="1: today's single process")
    p.add_argument("--model", default="rbe3001", help="built-in profile of every arm")
    p.add_argument("--seconds", type=float, default=10.0)
    p.add_argument("--presses", type=int, default=200)
    p.add_argument("--teleop", action="store_true",
                   help="also a teleoperation session's latency, on one worker and across two")
    p.add_argument("--per-sim", type=int, default=16, metavar="K",
                   help="arms each simulator process serves (one device and address each, "
                        "one process's loop for all: `armserver sim MODEL --listen A --listen B`)")
    p.add_argument("--sims-in-order", action="store_true",
                   help="each simulator process serves the next K arms of the config (the "
                        "arms of both workers), not K arms of one worker")
    p.add_argument("--sims-nice", type=int, default=19, metavar="N",
                   help="the simulators' niceness (19: they take what the server leaves, as "
                        "devices with processors of their own; 0: the server's equals)")
    p.add_argument("--relay-clients", type=int, default=SEEN_STREAMS, metavar="N",
                   help="telemetry clients for the relay's cost, spread over the arms")
    p.add_argument("--relay-rate", type=int, default=500, metavar="HZ",
                   help="their rate (500: each sample as published; 30: a dashboard)")
    p.add_argument("--pin", action="store_true",
                   help="server on core 0; simulators and this client on the others")
    p.add_argument("--io", choices=("thread", "asyncio"), default="thread",
                   help="each arm's serial link ([link] io): on its own thread or on the loop")
    args = p.parse_args()
    # a SIGTERM ends the run through its `finally`: the server and the simulators are sessions
    # of their own, which a signal to this process's group does not reach
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))
    folder = Path(tempfile.mkdtemp(prefix="armserver-bench-lab-"))
    ports = _free_ports(args.arms + 1)
    # (the server's own settings, not the caller's; ARMSERVER_POLL_REST=python passes: the
    # poll thread's rounds of arms at rest in Python, for a before/after of the rounds in C)
    env = {k: v for k, v in os.environ.items()
           if not k.startswith("ARMSERVER_") or k == "ARMSERVER_POLL_REST"}
    env["ARMSERVER_DATA_DIR"] = str(folder / "data")
    cpus = sorted(os.sched_getaffinity(0))
    machine = _machine.describe()  # (before anything of the bench's runs)
    config = []
    for i, port in enumerate(ports[1:]):
        config.append(f'[[arms]]\nprofile = "{args.model}"\nname = "arm-{i + 1}"\n'
                      f'[arms.link]\nkind = "serial"\naddress = "socket://127.0.0.1:{port}"\n'
                      f'io = "{args.io}"\n')
    (folder / "lab.toml").write_text("\n".join(config))
    sims = []
    per = max(1, args.per_sim)
    for group in _sim_groups(folder / "lab.toml", args.workers, per, args.sims_in_order):
        listen = [a for port in group for a in ("--listen", f"tcp://127.0.0.1:{port}")]
        sims.append(subprocess.Popen(  # (nice: every thread of the simulator inherits it)
            ["nice", "-n", str(args.sims_nice), sys.executable, "-m", "app.cli", "sim",
             args.model, *listen], cwd=ROOT, env=env, start_new_session=True,
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
    grouped = all([_autogroup_nice(s.pid, args.sims_nice) for s in sims])
    server = None
    try:
        if args.pin and len(cpus) > 1:
            for s in sims:
                os.sched_setaffinity(s.pid, set(cpus[1:]))
            os.sched_setaffinity(0, set(cpus[1:]))
        time.sleep(1.0)  # the simulators listen (a late one is retried by the link's backoff)
        url = f"http://127.0.0.1:{ports[0]}"
        server = subprocess.Popen(
            [sys.executable, "-m", "app.cli", "serve", "--config", str(folder / "lab.toml"),
             "--port", str(ports[0]), "--workers", str(args.workers), "--log-level",
             "warning"], cwd=ROOT, env=env)
        _wait_healthy(url, 60)
        pids = _tree(server.pid)
        if args.pin and len(cpus) > 1:
            for pid in pids:
                os.sched_setaffinity(pid, {cpus[0]})
        time.sleep(1.0)  # past start-up's bursts
        print(f"{args.arms} {args.model} arms, {args.workers} worker(s), {args.seconds:.0f} s"
              f"{', pinned' if args.pin else ''}, simulators at nice {args.sims_nice}"
              f"{' (their sessions too)' if grouped else ''}; before "
              f"the arms ran: {machine}")
        uds = _worker_socket(pids) if args.workers > 1 else None
        asyncio.run(measure(url, [f"arm-{i + 1}" for i in range(args.arms)], args.seconds,
                            args.presses, (args.relay_clients, args.relay_rate), uds, pids,
                            [p.pid for p in sims]))
        if args.teleop and args.arms >= 3 and args.workers == 2:
            # placement: arm-1 and arm-3 on worker 0, arm-2 on worker 1
            same = asyncio.run(teleop_latency(url, "arm-1", "arm-3", args.seconds))
            across = asyncio.run(teleop_latency(url, "arm-2", "arm-3", args.seconds))
            print(f"teleop latency    one worker: {same}")
            print(f"                  across two: {across}")
    finally:
        if server is not None:
            server.send_signal(signal.SIGTERM)
            try:
                server.wait(30)
            except subprocess.TimeoutExpired:
                server.kill()
        for s in sims:
            s.terminate()
        for s in sims:
            s.wait(10)
        shutil.rmtree(folder, ignore_errors=True)  # its config and the workers' stores
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
