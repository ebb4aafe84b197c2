"""Load: many REST clients and WebSocket subscribers at once, then a slow consumer.

Starts `armserver serve` (simulated arms, no tokens) in a subprocess, so the server's figures
are its own, and:

1. runs `--clients` concurrent httpx clients (a mix: cached state, arm detail, forward
   kinematics, rbe3001 STATUS and Dynamixel register reads through the links) and `--subs`
   WebSocket subscribers (half on each arm) for `--seconds`; prints throughput, latency
   percentiles (p50/p90/p99) per kind, errors by status and code, telemetry received (gaps
   against reported drops), the server's CPU and memory (RSS) at start and end;
2. the slow consumer: `--readers` subscribers on the rbe3001 for `--slow-seconds`, once alone
   and once beside one client that stops reading for `--stall` seconds (its socket's receive
   buffer kept small, so the server's send to it blocks) and then reads again; prints, per run,
   the readers' sample rate, gaps and longest silence, and what the stalled client was told it
   lost. The readers' figures should not change.

    python bench/load.py --seconds 20 [--clients 50 --subs 50]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import random
import socket
import time
from collections import Counter
from dataclasses import dataclass, field

import httpx
from _server import ServerProcess, pct, server  # bench/_server.py
from websockets.asyncio.client import connect
from websockets.exceptions import ConnectionClosed

API = "/api/v1"


# ---------------------------------------------------------------- the server


# ---------------------------------------------------------------- REST load

KINDS = [  # (weight, kind, method, path, body)
    (50, "GET state", "GET", f"{API}/arms/{{arm}}/state", None),
    (10, "GET arm", "GET", f"{API}/arms/{{arm}}", None),
    (15, "POST kinematics/forward", "POST", f"{API}/arms/{{arm}}/kinematics/forward", "q"),
    (15, "GET rbe3001/status", "GET", f"{API}/arms/rbe3001/rbe3001/status", None),
    (10, "GET dynamixel register", "GET", f"{API}/arms/angler/dynamixel/2/registers/id", None),
]
Q = {"rbe3001": [0.1, 0.5, 0.3], "angler": [0.0, 0.0, 0.1, 0.0]}


@dataclass
class RestStats:
    lat: dict[str, list[float]] = field(default_factory=dict)
    errors: Counter[str] = field(default_factory=Counter)
    n: int = 0


async def rest_worker(client: httpx.AsyncClient, until: float, st: RestStats, seed: int) -> None:
    rng = random.Random(seed)
    weights = [k[0] for k in KINDS]
    while time.monotonic() < until:
        _, kind, method, path, body = rng.choices(KINDS, weights)[0]
        arm = rng.choice(["rbe3001", "angler"])
        t0 = time.perf_counter()
        try:
            r = await client.request(method, path.format(arm=arm),
                                     json={"positions": Q[arm]} if body else None)
        except httpx.HTTPError as exc:
            st.errors[f"transport {type(exc).__name__}"] += 1
            continue
        st.n += 1
        st.lat.setdefault(kind, []).append(time.perf_counter() - t0)
        if r.status_code >= 400:
            try:
                code = r.json().get("code")
            except ValueError:
                code = "not-json"
            st.errors[f"{r.status_code} {code}"] += 1


# ---------------------------------------------------------------- WebSocket subscribers


@dataclass
class SubStats:
    samples: int = 0
    messages: int = 0
    gaps: int = 0
    dropped: int = 0
    backwards: int = 0
    longest_silence: float = 0.0
    closed: int = 0


async def subscriber(url: str, until: float, st: SubStats, stall: tuple[float, float] | None = None,
                     rcvbuf: int | None = None) -> None:
    """Read telemetry until `until`; with `stall` (start, end) monotonic times, stop reading in
    between (with a small receive buffer the server's send to this client blocks)."""
    sock = None
    if rcvbuf is not None:
        host, port = url.split("//")[1].split("/")[0].split(":")
        sock = socket.socket()
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
        sock.connect((host, int(port)))
        sock.setblocking(False)
    last_seq: int | None = None
    try:
        async with connect(url, sock=sock, max_size=2**24,
                           max_queue=1 if rcvbuf else 16) as ws:
            last_t = time.monotonic()
            while (left := until - time.monotonic()) > 0:
                if stall and stall[0] <= time.monotonic() < stall[1]:
                    await asyncio.sleep(stall[1] - time.monotonic())
                    continue
                try:
                    raw = await asyncio.wait_for(ws.recv(), left)
                except TimeoutError:
                    break
                now = time.monotonic()
                st.longest_silence = max(st.longest_silence, now - last_t)
                last_t = now
                msg = json.loads(raw)
                st.messages += 1
                if msg["type"] != "telemetry":
                    continue
                st.dropped += msg["dropped"]
                for s in msg["samples"]:
                    st.samples += 1
                    if last_seq is not None:
                        if s["seq"] <= last_seq:
                            st.backwards += 1
                        else:
                            st.gaps += s["seq"] - last_seq - 1
                    last_seq = s["seq"]
    except (OSError, ConnectionClosed):
        st.closed += 1


# ---------------------------------------------------------------- scenarios


async def load(srv: ServerProcess, seconds: float, clients: int, subs: int,
               rate: float) -> str:
    st = RestStats()
    sub_stats = [SubStats() for _ in range(subs)]
    pool = [httpx.AsyncClient(base_url=srv.url, timeout=30.0) for _ in range(clients)]
    try:
        await asyncio.gather(*(c.get(f"{API}/health") for c in pool))  # connected first
        rss0, cpu0 = srv.rss_mib(), srv.cpu_seconds()
        t0 = time.monotonic()
        until = t0 + seconds
        arms = ["rbe3001", "angler"]
        await asyncio.gather(
            *(rest_worker(c, until, st, k) for k, c in enumerate(pool)),
            *(subscriber(f"{srv.ws_url}{API}/arms/{arms[k % 2]}/telemetry?rate={rate}", until,
                         s) for k, s in enumerate(sub_stats)))
        elapsed = time.monotonic() - t0
        cpu1, rss1 = srv.cpu_seconds(), srv.rss_mib()
    finally:
        await asyncio.gather(*(c.aclose() for c in pool))
    all_lat = [x for v in st.lat.values() for x in v]
    lines = [f"REST: {clients} clients, WebSocket: {subs} subscribers at {rate:g} Hz, "
             f"{elapsed:.1f} s",
             f"  {'kind':26s} {'req/s':>8s} {'p50 ms':>8s} {'p90 ms':>8s} {'p99 ms':>8s}"]
    for kind, lat in sorted(st.lat.items()) + [("all", all_lat)]:
        lines.append(f"  {kind:26s} {len(lat) / elapsed:8.0f} {pct(lat, .5) * 1e3:8.1f} "
                     f"{pct(lat, .9) * 1e3:8.1f} {pct(lat, .99) * 1e3:8.1f}")
    lines.append("  errors: " + (", ".join(f"{k} x{v}" for k, v in st.errors.most_common())
                                 or "none"))
    samples = sum(s.samples for s in sub_stats)
    gaps = sum(s.gaps for s in sub_stats)
    dropped = sum(s.dropped for s in sub_stats)
    lines += [
        f"  telemetry: {samples} samples ({samples / elapsed / max(1, subs):.0f}/s per "
        f"subscriber), {sum(s.messages for s in sub_stats)} messages; seq gaps {gaps}, "
        f"reported dropped {dropped}, unexplained {max(0, gaps - dropped)}, backwards "
        f"{sum(s.backwards for s in sub_stats)}, closed {sum(s.closed for s in sub_stats)}",
        f"  server: CPU {(cpu1 - cpu0) / elapsed:.0%} of one core; RSS {rss0:.1f} -> "
        f"{rss1:.1f} MiB ({rss1 - rss0:+.1f})",
    ]
    return "\n".join(lines)


async def slow_consumer(srv: ServerProcess, seconds: float, readers: int, stall_s: float,
                        rate: float) -> str:
    url = f"{srv.ws_url}{API}/arms/rbe3001/telemetry?rate={rate}"
    lines = [f"slow consumer: {readers} readers on rbe3001 at {rate:g} Hz for {seconds:g} s, "
             f"one client stalled {stall_s:g} s"]
    lines.append(f"  {'run':22s} {'samples/s':>10s} {'min/s':>8s} {'gaps':>6s} {'dropped':>8s} "
                 f"{'longest silence':>16s}")
    for with_slow in (False, True):
        rs = [SubStats() for _ in range(readers)]
        slow = SubStats()
        t0 = time.monotonic()
        until = t0 + seconds
        tasks = [subscriber(url, until, s) for s in rs]
        if with_slow:
            stall = (t0 + 1.0, t0 + 1.0 + stall_s)
            tasks.append(subscriber(url, until, slow, stall=stall, rcvbuf=4096))
        await asyncio.gather(*tasks)
        el = time.monotonic() - t0
        rates = [s.samples / el for s in rs]
        lines.append(f"  {'with stalled client' if with_slow else 'readers alone':22s} "
                     f"{sum(rates) / len(rates):10.0f} {min(rates):8.0f} "
                     f"{sum(s.gaps for s in rs):6d} {sum(s.dropped for s in rs):8d} "
                     f"{max(s.longest_silence for s in rs) * 1e3:13.0f} ms")
        if with_slow:
            lines.append(f"  stalled client: {slow.samples} samples, told it lost "
                         f"{slow.dropped}, seq gaps {slow.gaps} (unexplained "
                         f"{max(0, slow.gaps - slow.dropped)}), longest silence "
                         f"{slow.longest_silence:.1f} s, closed {slow.closed}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--seconds", type=float, default=20.0)
    p.add_argument("--clients", type=int, default=50)
    p.add_argument("--subs", type=int, default=50)
    p.add_argument("--rate", type=float, default=20.0, help="telemetry messages/s asked, Hz")
    p.add_argument("--readers", type=int, default=5)
    p.add_argument("--slow-seconds", type=float, default=12.0)
    p.add_argument("--stall", type=float, default=8.0, help="s (the server keeps 2000 samples "
                   "per client: 4 s at 500 Hz, beyond which the oldest are dropped)")
    args = p.parse_args(argv)
    with server() as srv:
        print(asyncio.run(load(srv, args.seconds, args.clients, args.subs, args.rate)))
        print()
        print(asyncio.run(slow_consumer(srv, args.slow_seconds, args.readers, args.stall,
                                        args.rate)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
