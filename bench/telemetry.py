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
import json
import statistics
import sys
import time
from dataclasses import dataclass, field

from _server import ROOT, ServerProcess, pct, server  # bench/_server.py

# ---------------------------------------------------------------- the server under test


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
    with server(pin=True) as srv:
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
