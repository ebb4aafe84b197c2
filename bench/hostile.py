"""Hostile and careless clients against one `armserver serve` (issue 11): does control hold?

    python bench/hostile.py [--stalled 500] [--slowloris 200] [--presses 1000]

Phase 1, while the rbe3001 runs a move (`wait: true`) back and forth: a 64 MiB request header,
`--stalled` telemetry WebSockets that never read, `--slowloris` sockets sending a header byte
a second. Phase 2: an estop storm (`--presses` viewer presses) during a move.

One well-behaved subscriber reads the rbe3001's telemetry all along; from its samples (stamped
on the control thread when the device answered) it prints the device sample rate against the
profile's poll rate, the worst gap between consecutive samples, the peak measured joint speed
against the joint limit, and how each motion ended. Targets (issue 11): rate within 5 % of
nominal, worst gap under 20 ms, no limit exceeded, motions that end as they say.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import sys
import time
from pathlib import Path
from typing import Any

import httpx
from websockets.asyncio.client import connect

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from _server import ServerProcess  # noqa: E402

from app.config import load_profile  # noqa: E402

ARM = "/api/v1/arms/rbe3001"
A = [0.0, 0.59, 0.3]
B = [1.0, 1.2, -0.4]


class Watcher:
    """The one subscriber that reads: samples (seq, time, velocities) of the rbe3001."""

    def __init__(self, ws_url: str) -> None:
        self.url = ws_url + ARM + "/telemetry"
        self.samples: list[tuple[int, float, list[float]]] = []
        self.dropped = 0
        self.task: asyncio.Task[None] | None = None

    async def run(self) -> None:
        async with connect(self.url, max_size=None) as ws:
            async for raw in ws:
                msg = json.loads(raw)
                if msg.get("type") == "telemetry":
                    self.dropped += msg["dropped"]
                    self.samples += [(s["seq"], s["time"], s["velocities"]) for s in msg["samples"]]

    def window(self, t0: float, t1: float) -> dict[str, Any]:
        got = [s for s in self.samples if t0 <= s[1] <= t1]
        if len(got) < 2:
            return {"samples": len(got)}
        rate = (got[-1][0] - got[0][0]) / (got[-1][1] - got[0][1])
        gaps = [b[1] - a[1] for a, b in zip(got, got[1:], strict=False) if b[0] == a[0] + 1]
        speed = [max(abs(v) for v in s[2]) for s in got]
        return {"samples": len(got), "rate_hz": rate, "worst_gap_ms": max(gaps) * 1e3,
                "peak_speed": max(speed)}


async def huge_header(port: int, mib: int = 64) -> str:
    """Send a `mib` MiB header; what the server answered and how soon."""
    t0 = time.monotonic()
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    writer.write(b"GET /api/v1/health HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Big: ")
    chunk = b"a" * (1 << 20)
    answer = b""
    with contextlib.suppress(OSError):
        for _ in range(mib):
            writer.write(chunk)
            await writer.drain()
            if reader.at_eof():
                break
    with contextlib.suppress(OSError, TimeoutError):
        answer = await asyncio.wait_for(reader.read(200), 5)
    writer.close()
    line = answer.split(b"\r\n", 1)[0].decode(errors="replace") or "(connection closed)"
    return f"{line} after {time.monotonic() - t0:.2f} s"


async def stalled_subscriber(port: int, arm: str) -> str:
    """Open a telemetry WebSocket by hand and never read from it: 'open' or what refused it."""
    reader, writer = await asyncio.open_connection("127.0.0.1", port, limit=1 << 16)
    writer.write((f"GET /api/v1/arms/{arm}/telemetry HTTP/1.1\r\nHost: 127.0.0.1\r\n"
                  "Upgrade: websocket\r\nConnection: Upgrade\r\n"
                  "Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\nSec-WebSocket-Version: 13\r\n"
                  "\r\n").encode())
    head = await reader.readuntil(b"\r\n\r\n")
    first = await asyncio.wait_for(reader.read(256), 5)
    STALLED.append(writer)  # keep it open, unread
    if b" 101 " not in head:
        return "refused http"
    # A refusal is a close frame (opcode 8) right after the handshake: 1013 busy.
    return "refused 1013" if first[:1] == b"\x88" else "open"


STALLED: list[asyncio.StreamWriter] = []


async def slowloris(port: int, n: int, stop: asyncio.Event) -> None:
    conns = []
    for _ in range(n):
        with contextlib.suppress(OSError):
            _, w = await asyncio.open_connection("127.0.0.1", port)
            w.write(b"GET /api/v1/health HTTP/1.1\r\nHost: 127.0.0.1\r\n")
            conns.append(w)
    while not stop.is_set():
        for w in conns:
            with contextlib.suppress(OSError):
                w.write(b"X-a: b\r\n")
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(stop.wait(), 1.0)
    for w in conns:
        w.close()


async def move(client: httpx.AsyncClient, target: list[float], speed: float = 1.0
               ) -> dict[str, Any]:
    r = await client.post(f"{ARM}/move/joints", json={"positions": target, "wait": True,
                                                      "speed": speed})
    return {"http": r.status_code, **r.json()}


def describe(m: dict[str, Any], target: list[float]) -> str:
    if m.get("status") == "done":
        err = max(abs(a - b) for a, b in zip(m["final_positions"], target, strict=True))
        return f"done, {err * 1e3:.1f} mrad from the target"
    return f"{m.get('status')} ({m.get('code')}: {m.get('reason')})"


async def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--stalled", type=int, default=500)
    ap.add_argument("--slowloris", type=int, default=200)
    ap.add_argument("--presses", type=int, default=1000)
    args = ap.parse_args()
    profile = load_profile("rbe3001")
    nominal = profile.link.poll_hz
    vmax = max(j.max_velocity for j in profile.joints)
    server = ServerProcess(pin=True)
    try:
        watcher = Watcher(server.ws_url)
        watcher.task = asyncio.create_task(watcher.run())
        async with httpx.AsyncClient(base_url=server.url, timeout=60) as client:
            await move(client, A)
            await asyncio.sleep(1.0)
            t0 = time.time()
            quiet = await move(client, B)
            await move(client, A)
            t1 = time.time()
            base = watcher.window(t0, t1)

            # Phase 1: header, stalled subscribers, slowloris, during moves.
            stop = asyncio.Event()
            t2 = time.time()
            loris = asyncio.create_task(slowloris(server.port, args.slowloris, stop))
            moving = asyncio.create_task(move(client, B))
            header = asyncio.create_task(huge_header(server.port))
            subs = await asyncio.gather(*(stalled_subscriber(server.port,
                                                             "rbe3001" if k % 2 else "angler")
                                          for k in range(args.stalled)),
                                        return_exceptions=True)
            hostile_b = await moving
            hostile_a = await move(client, A)
            t3 = time.time()
            header_answer = await header
            stop.set()
            await loris
            attacked = watcher.window(t2, t3)

            # Phase 2: estop storm during a move.
            t4 = time.time()
            moving = asyncio.create_task(move(client, B, speed=0.3))
            await asyncio.sleep(0.5)
            before = None
            for k in range(0, args.presses, 50):
                answers = await asyncio.gather(*(client.post(f"{ARM}/estop")
                                                 for _ in range(min(50, args.presses - k))))
                if before is None:
                    before = (await client.get(f"{ARM}/state")).json()["positions"]
                assert all(a.status_code == 200 for a in answers)
            storm_move = await moving
            await asyncio.sleep(0.5)
            after = (await client.get(f"{ARM}/state")).json()["positions"]
            t5 = time.time()
            storm = watcher.window(t4, t5)
            await client.delete(f"{ARM}/estop")
        watcher.task.cancel()
    finally:
        for w in STALLED:
            w.close()
        server.close()

    counts: dict[str, int] = {}
    for r in subs:
        key = r if isinstance(r, str) else type(r).__name__
        counts[key] = counts.get(key, 0) + 1

    def line(name: str, w: dict[str, Any]) -> None:
        if w.get("samples", 0) < 2:
            print(f"{name:<28} no samples")
            return
        ok = (abs(w["rate_hz"] - nominal) <= 0.05 * nominal and w["worst_gap_ms"] < 20
              and w["peak_speed"] <= vmax * 1.001)
        print(f"{name:<28} {w['rate_hz']:7.1f} Hz ({w['rate_hz'] / nominal - 1:+.1%})  "
              f"worst gap {w['worst_gap_ms']:6.1f} ms  peak speed {w['peak_speed']:.2f} / "
              f"{vmax:.2f} rad/s  {'ok' if ok else 'MISSED'}")

    print(f"server pinned apart from this client: {server.pinned}; nominal poll {nominal:g} Hz")
    line("quiet (2 moves)", base)
    line("header+stalled+slowloris", attacked)
    line("estop storm", storm)
    print(f"64 MiB header: {header_answer}")
    print(f"{args.stalled} stalled subscribers: {counts}")
    print(f"moves: quiet {describe(quiet, B)}; attacked {describe(hostile_b, B)}, "
          f"{describe(hostile_a, A)}")
    drift = max(abs(a - b) for a, b in zip(after, before or after, strict=True))
    print(f"estop storm ({args.presses} presses): move {describe(storm_move, B)}; joints moved "
          f"{drift * 1e3:.1f} mrad from the first press to 0.5 s after the last")
    print(f"watcher dropped {watcher.dropped} samples")


if __name__ == "__main__":
    asyncio.run(main())
