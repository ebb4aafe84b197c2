"""REST throughput benchmark: 50 concurrent httpx clients for T seconds per route.

Starts `armserver serve` on the simulated arms in a subprocess and prints, for GET /state
(cached sample, no device traffic) and GET .../rbe3001/status (one STATUS exchange with the
simulated firmware each, through the link owner's bounded queue): requests/s, median and p99
latency, error answers (by status) and the server's CPU share of one core.

    python bench/rest.py --seconds 5 --clients 50
"""

from __future__ import annotations

import argparse
import asyncio
import sys
import time
from collections import Counter
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from _server import ServerProcess, pct, server  # noqa: E402  (bench/_server.py)

ROUTES = {
    "GET /state": "/api/v1/arms/rbe3001/state",
    "GET /rbe3001/status": "/api/v1/arms/rbe3001/rbe3001/status",
}


async def _worker(client: object, path: str, start: asyncio.Event, deadline: list[float],
                  lat: list[float], codes: Counter[int]) -> None:
    import httpx

    assert isinstance(client, httpx.AsyncClient)
    await start.wait()
    while time.monotonic() < deadline[0]:
        t0 = time.perf_counter()
        try:
            r = await client.get(path)
            codes[r.status_code] += 1
        except httpx.HTTPError:
            codes[0] += 1
            continue
        lat.append(time.perf_counter() - t0)


async def run_route(srv: ServerProcess, path: str, clients: int, seconds: float) -> dict:
    """Each client is made and connected (one warm-up request) before the clock starts: the
    figures are the server's, not TLS-context loading or connection set-up."""
    import httpx

    lat: list[float] = []
    codes: Counter[int] = Counter()
    start = asyncio.Event()
    deadline = [0.0]
    pool = [httpx.AsyncClient(base_url=srv.url, timeout=10.0, verify=False)
            for _ in range(clients)]
    try:
        await asyncio.gather(*(c.get(path) for c in pool))
        tasks = [asyncio.create_task(_worker(c, path, start, deadline, lat, codes)) for c in pool]
        cpu0, t0 = srv.cpu_seconds(), time.monotonic()
        deadline[0] = t0 + seconds
        start.set()
        await asyncio.gather(*tasks)
        elapsed = time.monotonic() - t0
    finally:
        await asyncio.gather(*(c.aclose() for c in pool))
    return {"rps": codes[200] / elapsed, "p50": 1000 * pct(lat, 0.5), "p99": 1000 * pct(lat, 0.99),
            "errors": {c: n for c, n in codes.items() if c != 200},
            "cpu": (srv.cpu_seconds() - cpu0) / elapsed}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--seconds", type=float, default=5.0, help="measuring time per route, s")
    p.add_argument("--clients", type=int, default=50, help="concurrent clients")
    a = p.parse_args(argv)
    rows = []
    with server(pin=True) as srv:
        for name, path in ROUTES.items():
            rows.append((name, asyncio.run(run_route(srv, path, a.clients, a.seconds))))
    print(f"REST: {a.clients} concurrent clients, {a.seconds:g} s per route, simulated rbe3001")
    print(f"{'route':<22} {'req/s':>8} {'p50':>8} {'p99':>8} {'srv CPU':>8}  errors")
    for name, r in rows:
        print(f"{name:<22} {r['rps']:>8.0f} {r['p50']:>6.1f}ms {r['p99']:>6.1f}ms "
              f"{100 * r['cpu']:>7.0f}%  {r['errors'] or '-'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
