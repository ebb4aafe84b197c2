"""Hostile and careless clients against one `armserver serve` (issue 11): does control hold?

    python bench/hostile.py [--stalled 500] [--slowloris 200] [--presses 1000]

Phase 1, while the rbe3001 runs a move (`wait: true`) back and forth: a 64 MiB request header,
`--stalled` telemetry WebSockets that never read, `--slowloris` sockets sending a header byte
a second. Phase 2: an estop storm (`--presses` viewer presses) during a move.

Phase 3 (issue 22, `--passthrough-rounds`, 0 to leave it out; `--only-passthrough` runs it
alone): the protocol pass-through routes, careless and hostile, with a keep-out zone put near
each arm's path first: rbe3001 SET_PID storms of big steps (0.2..3 rad from where the arm is)
and of small ones back to back (each as far ahead of the reported position as the route
takes), angler goal_position and multi-id sync-write storms (some aimed through the zone),
and estop presses fired in the middle of bursts of pass-through commands. From every sample
of both arms it prints the refusals by route and code, each joint's peak measured speed
against its limit, the samples with a body point inside a zone (the envelope's own point
model: joint origins and tip, zones grown by their margins), and how far each arm's setpoint
moved from where the arm was at each latch (rbe3001: the joints 0.4 s after the latch, which
settle on the hold; angler: the servos' Goal Position registers read back).

`--serial-arm`: phases 1 and 2 with a third arm on a terminal (the angler's simulated servos
on a pty, a process of their own, as a serial arm's USB adapter): while a terminal is open the
server holds its raised threads at the default niceness and its main thread below them
(`TerminalHold`, app/runtime/control_thread.py), the README's "a server with a serial arm
open" row.

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
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import numpy as np
from websockets.asyncio.client import connect

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import _machine  # noqa: E402
from _server import ROOT, ServerProcess  # noqa: E402

from app.arms.loading import load_profile  # noqa: E402
from app.config import KeepOutBox, SafetySettings  # noqa: E402
from app.service import ArmService  # noqa: E402

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
    ap.add_argument("--passthrough-rounds", type=int, default=10,
                    help="estop rounds of phase 3 per arm (its storms scale with it); 0: none")
    ap.add_argument("--only-passthrough", action="store_true", help="phase 3 alone")
    ap.add_argument("--seed", type=int, default=22)
    ap.add_argument("--serial-arm", action="store_true",
                    help="phases 1 and 2 with a third arm on a pty (the server's terminal hold)")
    args = ap.parse_args()
    if args.only_passthrough:
        server = ServerProcess(pin=True)
        try:
            print(f"server pinned apart from this client: {server.pinned}")
            await passthrough_phase(server, args.passthrough_rounds, args.seed)
        finally:
            server.close()
        return
    profile = load_profile("rbe3001")
    nominal = profile.link.poll_hz
    vmax = max(j.max_velocity for j in profile.joints)
    with serial_arm_config() if args.serial_arm else contextlib.nullcontext() as config:
        await attack(args, nominal, vmax, config)
    if args.passthrough_rounds > 0:
        server = ServerProcess(pin=True)  # a fresh server: phase 3 starts from a known state
        try:
            await passthrough_phase(server, args.passthrough_rounds, args.seed)
        finally:
            server.close()


@contextlib.contextmanager
def serial_arm_config() -> Iterator[Path]:
    """A config file: the built-in simulated arms, and the angler again as `angler-tty` on a
    pty served by `armserver sim angler` (stopped at the end)."""
    with tempfile.TemporaryDirectory() as tmp:
        tty_path = Path(tmp) / "ttyANGLER"
        sim = subprocess.Popen([sys.executable, "-m", "app.cli", "sim", "angler", "--pty",
                                str(tty_path)], cwd=ROOT, stdout=subprocess.DEVNULL)
        try:
            deadline = time.monotonic() + 60
            while not tty_path.exists():
                if time.monotonic() > deadline or sim.poll() is not None:
                    raise RuntimeError("the simulated angler's pty did not appear")
                time.sleep(0.05)
            config = Path(tmp) / "hostile.toml"
            config.write_text(
                '[[arms]]\nprofile = "rbe3001"\n[arms.link]\nkind = "sim"\n'
                'homed_at_start = true\n\n'
                '[[arms]]\nprofile = "angler"\n[arms.link]\nkind = "sim"\n'
                'homed_at_start = true\n\n'
                '[[arms]]\nprofile = "angler"\nname = "angler-tty"\n[arms.link]\n'
                f'kind = "serial"\naddress = "{tty_path}"\n')
            yield config
        finally:
            sim.terminate()
            sim.wait(10)


async def attack(args: argparse.Namespace, nominal: float, vmax: float,
                 config: Path | None) -> None:
    """Phases 1 and 2 on one server (`config`'s arms, or the built-in simulated ones)."""
    server = ServerProcess(pin=True, config=config)
    try:
        print(f"the server's threads by niceness: {_machine.threads_by_niceness(server.proc.pid)}")
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


# ---------------------------------------------------------------- phase 3: pass-through (issue 22)

RB, AN = "/api/v1/arms/rbe3001", "/api/v1/arms/angler"
#: A SET_PID step at least this far from where the arm is must be refused (0.03 s at 1.5 rad/s
#: is 0.045 rad); the big-step storm draws its steps from here up.
BIG_STEP = 0.2
#: Estop hold tolerance: 8 encoder ticks or 30 ms at the joint's limit, whichever is more.
HOLD_S, HOLD_TICKS = 0.03, 8.0


class ArmWatcher:
    """Every sample of one arm: (seq, time, positions, velocities, estop)."""

    def __init__(self, ws_url: str, arm: str) -> None:
        self.url = f"{ws_url}/api/v1/arms/{arm}/telemetry"
        self.samples: list[tuple[int, float, np.ndarray, np.ndarray, bool]] = []
        self.dropped = 0
        self.task: asyncio.Task[None] | None = None

    async def run(self) -> None:
        async with connect(self.url, max_size=None) as ws:
            async for raw in ws:
                msg = json.loads(raw)
                if msg.get("type") == "telemetry":
                    self.dropped += msg["dropped"]
                    self.samples += [(x["seq"], x["time"], np.array(x["positions"], dtype=float),
                                      np.array(x["velocities"], dtype=float), bool(x["estop"]))
                                     for x in msg["samples"] if x.get("positions") is not None]

    async def fresh(self, after: float, n: int = 1, timeout: float = 5.0) -> None:
        """Until n samples stamped after `after` (wall time) are in (bounded)."""
        deadline = time.monotonic() + timeout
        while sum(1 for x in self.samples[-n:] if x[1] > after) < n:
            if time.monotonic() > deadline:
                return
            await asyncio.sleep(0.01)


class Arm:
    """One arm of the bench's server as the bench sees it: its model (for ticks, limits and
    the envelope's body points, built here from the same profile), its watcher, the zones in
    force and since when, and the figures."""

    def __init__(self, name: str, ws_url: str) -> None:
        self.name = name
        self.url = f"/api/v1/arms/{name}"
        self.svc = ArmService(load_profile(name))  # never started: its model and envelope
        self.model = self.svc.model
        self.profile = self.svc.profile
        self.watch = ArmWatcher(ws_url, name)
        self.zones: list[dict[str, Any]] = []
        self.zone_since = float("inf")
        self.answers: dict[str, int] = {}
        self.latch_offsets: list[np.ndarray] = []
        tpu = np.abs(np.asarray(self.model.transmission.ticks_per_unit, dtype=float))
        self.hold_tol = np.maximum(HOLD_TICKS / tpu, self.model.vmax * HOLD_S)

    def count(self, what: str, r: httpx.Response) -> bool:
        code = "" if r.status_code < 300 else str(r.json().get("code"))
        key = f"{what} {r.status_code} {code}".strip()
        self.answers[key] = self.answers.get(key, 0) + 1
        return r.status_code < 300

    def q(self) -> np.ndarray:
        return self.watch.samples[-1][2].copy()

    def ticks(self, q: np.ndarray) -> np.ndarray:
        return np.asarray(self.model.transmission.to_ticks(np.asarray(q, dtype=float)))

    def set_pid(self, q: np.ndarray) -> dict[str, Any]:
        return {"joints": [{"position_ticks": float(t)} for t in self.ticks(q)]}

    def goals(self, q: np.ndarray, joints: list[int]) -> dict[str, int]:
        t = self.ticks(q)
        return {str(self.profile.joints[k].motor_id): int(round(float(t[k]))) for k in joints}

    def clip(self, q: np.ndarray) -> np.ndarray:
        lo, hi = self.model.lower, self.model.upper
        return np.clip(q, lo + 0.03 * (hi - lo), hi - 0.03 * (hi - lo))

    def inside(self, t0: float = -np.inf) -> tuple[int, int, float]:
        """(samples, samples with a body point inside a zone in force, the deepest such
        point's depth in m) since the zone was put; zones grown by the envelope's margins."""
        got = [x for x in self.watch.samples if x[1] >= max(t0, self.zone_since)]
        if not got or not self.zones:
            return len(got), 0, 0.0
        boxes = [KeepOutBox.model_validate(z) for z in self.zones]
        env = self.svc.safety.preview(SafetySettings(zones=boxes))
        p = env.points(np.array([x[2] for x in got]))  # (T, B, 3)
        m = env.margins[None, :, None]
        depth = np.zeros(len(got))
        for z in boxes:
            lo = np.array([z.min.x, z.min.y, z.min.z]) - m
            hi = np.array([z.max.x, z.max.y, z.max.z]) + m
            d = np.minimum(p - lo, hi - p).min(axis=-1).max(axis=-1)  # >= 0: inside
            depth = np.maximum(depth, np.where(d >= 0, d, 0.0))
            depth[(d >= 0) & (depth == 0)] = 1e-12
        return len(got), int((depth > 0).sum()), float(depth.max())

    def peak(self, t0: float) -> np.ndarray:
        v = [np.abs(x[3]) for x in self.watch.samples if x[1] >= t0]
        return np.max(v, axis=0) if v else np.zeros(self.model.n)


def zone_box(name: str, centre: np.ndarray, half: float) -> dict[str, Any]:
    lo, hi = centre - half, centre + half
    return {"name": name, "min": dict(zip("xyz", lo.tolist(), strict=True)),
            "max": dict(zip("xyz", hi.tolist(), strict=True))}


async def put_zone(client: httpx.AsyncClient, arm: Arm, q_at: np.ndarray, body: int,
                   half: float) -> None:
    zone = zone_box("bench", arm.svc.safety.points(q_at)[body], half)
    r = await client.put(f"{arm.url}/safety", json={"zones": [zone]})
    arm.count("PUT safety", r)
    if r.status_code == 200:
        arm.zones, arm.zone_since = [zone], time.time()


async def until_still(arm: Arm, timeout: float = 8.0) -> None:
    """Until the last 20 samples show every joint under 1 % of its limit (bounded)."""
    deadline = time.monotonic() + timeout
    slow = 0.01 * arm.model.vmax
    while time.monotonic() < deadline:
        last = arm.watch.samples[-20:]
        if len(last) == 20 and all(np.all(np.abs(x[3]) <= slow) for x in last):
            return
        await asyncio.sleep(0.02)


async def setpid_big_storm(client: httpx.AsyncClient, rb: Arm, n: int,
                           rng: np.random.Generator) -> None:
    """Bursts of SET_PID steps of BIG_STEP..3 rad from where the arm is (one joint each)."""
    for _ in range(n):
        here = rb.q()
        bodies = []
        for _ in range(10):
            k = int(rng.integers(0, 3))
            target = here.copy()
            target[k] += rng.choice([-1.0, 1.0]) * rng.uniform(BIG_STEP, 3.0)
            bodies.append(rb.set_pid(rb.clip(target)))
        answers = await asyncio.gather(*(client.post(f"{rb.url}/rbe3001/set-pid", json=b)
                                         for b in bodies))
        for r in answers:
            rb.count("SET_PID big", r)


async def setpid_chase(client: httpx.AsyncClient, rb: Arm, frm: float, to: float) -> float:
    """SET_PID back to back, each as far ahead of the reported base as the route takes
    (from 0.08 rad, 5 mrad less after a refusal); the largest step taken."""
    tr = rb.model.transmission
    hold = rb.q()
    hold[0] = frm
    r = await client.post(f"{rb.url}/move/joints", json={"positions": hold.tolist(),
                                                         "wait": True})
    rb.count("move", r)
    await until_still(rb)
    sign = 1.0 if to > frm else -1.0
    reported, step, largest = rb.q(), 0.08, 0.0
    deadline = time.monotonic() + 10.0
    while sign * (to - reported[0]) > 0 and time.monotonic() < deadline:
        target = hold.copy()
        target[0] = reported[0] + sign * step
        r = await client.post(f"{rb.url}/rbe3001/set-pid", json=rb.set_pid(target))
        if not rb.count("SET_PID chase", r):
            if r.json().get("code") != "velocity_limit":
                break
            step = max(0.01, step - 0.005)
            reported = rb.q()
            continue
        largest = max(largest, step)
        reported = np.asarray(tr.from_ticks(np.asarray(r.json()["position_ticks"],
                                                       dtype=float)))
    await until_still(rb)
    return largest


async def goal_storm(client: httpx.AsyncClient, an: Arm, n: int,
                     rng: np.random.Generator, anchor: np.ndarray) -> None:
    """Bursts of goal_position PUTs and multi-id sync-writes: random goals near where the
    arm is (x, y 1 cm, theta3 1.3 rad, z 3 cm), a third of them through the zone's anchor."""
    span = np.array([0.01, 0.01, 1.3, 0.03])
    for _ in range(n):
        here = an.q()
        calls = []
        for _ in range(6):
            through = rng.random() < 1 / 3
            aim = (anchor + 0.3 * (anchor - here) if through
                   else here + rng.uniform(-1, 1, 4) * span)
            joints = sorted(rng.choice(4, size=int(rng.integers(1, 5)), replace=False).tolist())
            target = here.copy()
            target[joints] = aim[joints]
            goals = an.goals(an.clip(target), joints)
            if len(goals) == 1:
                (dxl, raw), = goals.items()
                calls.append(("goal_position", client.put(
                    f"{an.url}/dynamixel/{dxl}/registers/goal_position", json={"raw": raw})))
            else:
                calls.append(("sync-write", client.post(
                    f"{an.url}/dynamixel/sync-write",
                    json={"name": "goal_position", "values": goals})))
        answers = await asyncio.gather(*(c for _, c in calls))
        for (what, _), r in zip(calls, answers, strict=True):
            an.count(what, r)
        await an.watch.fresh(time.time(), 20)  # 0.1 s of samples between bursts


async def read_goals(client: httpx.AsyncClient, an: Arm) -> np.ndarray | None:
    ids = [j.motor_id for j in an.profile.joints]
    r = await client.post(f"{an.url}/dynamixel/sync-read",
                          json={"name": "goal_position", "ids": ids})
    if r.status_code != 200:
        return None
    raw = np.array([r.json()["values"][str(i)] for i in ids], dtype=float)
    return np.asarray(an.model.transmission.from_ticks(raw), dtype=float)


async def estop_round(client: httpx.AsyncClient, arm: Arm, rng: np.random.Generator,
                      anchor: np.ndarray) -> None:
    """A burst of pass-through commands with an estop press in the middle of it; then how far
    the arm's setpoint is from where the arm was at the latch."""
    await client.delete(f"{arm.url}/estop")
    await until_still(arm, 3.0)
    here = arm.q()
    calls: list[tuple[str, Any]] = []
    for _ in range(8):
        target = here.copy()
        if arm.name == "rbe3001":
            target += rng.uniform(-0.04, 0.04, 3)
            target[int(rng.integers(0, 3))] += rng.choice([0.0, 0.5])
            calls.append(("SET_PID", client.post(f"{arm.url}/rbe3001/set-pid",
                                                 json=arm.set_pid(arm.clip(target)))))
        else:
            aim = here + rng.uniform(-1, 1, 4) * np.array([0.01, 0.01, 1.3, 0.03])
            if rng.random() < 0.3:
                aim = anchor + 0.3 * (anchor - here)
            calls.append(("sync-write", client.post(
                f"{arm.url}/dynamixel/sync-write",
                json={"name": "goal_position", "values": arm.goals(arm.clip(aim), [0, 1, 2, 3])})))
    at = int(rng.integers(1, len(calls)))
    calls.insert(at, ("estop", client.post(f"{arm.url}/estop")))
    t0 = time.time()
    answers = await asyncio.gather(*(c for _, c in calls))
    for (what, _), r in zip(calls, answers, strict=True):
        arm.count(what, r)
    await arm.watch.fresh(t0 + 0.4, 1, 5.0)  # 0.4 s of latched samples
    latched = [x for x in arm.watch.samples if x[1] >= t0 - 0.01 and x[4]]
    if not latched:
        return
    ref = latched[0][2]
    if arm.name == "angler":
        told = await read_goals(client, arm)
        if told is not None:
            arm.latch_offsets.append(np.abs(told - ref))
    else:  # the firmware's setpoint is not readable: where the joints settle on the hold
        arm.latch_offsets.append(np.abs(latched[-1][2] - ref))


async def passthrough_phase(server: ServerProcess, rounds: int, seed: int) -> None:
    rng = np.random.default_rng(seed)
    rb, an = Arm("rbe3001", server.ws_url), Arm("angler", server.ws_url)
    for arm in (rb, an):
        arm.watch.task = asyncio.create_task(arm.watch.run())
    async with httpx.AsyncClient(base_url=server.url, timeout=60) as client:
        for arm in (rb, an):
            await arm.watch.fresh(0.0, 20)
        t_start = time.time()
        # the rbe3001 at its A pose, a zone around the tip at base +1.0 rad
        r = await client.post(f"{RB}/move/joints", json={"positions": A, "wait": True})
        rb.count("move", r)
        await until_still(rb)
        await put_zone(client, rb, np.array([1.0, *A[1:]]), 3, 0.03)
        # the angler at rest, a zone around its tip at theta3 +0.8 rad
        a_anchor = an.q()
        a_anchor[2] = 0.8
        await put_zone(client, an, a_anchor, 4, 0.008)
        rb_anchor = np.array([1.0, *A[1:]])

        t1 = time.time()
        await setpid_big_storm(client, rb, 3 * rounds, rng)
        await until_still(rb)
        largest = 0.0
        for frm, to in ((-0.9, 0.3), (0.3, -0.9)):
            largest = max(largest, await setpid_chase(client, rb, frm, to))
        r = await client.post(f"{RB}/move/joints", json={"positions": A, "wait": True})
        rb.count("move", r)
        t2 = time.time()
        await goal_storm(client, an, 3 * rounds, rng, a_anchor)
        await until_still(an)
        t3 = time.time()
        for _ in range(rounds):
            await estop_round(client, rb, rng, rb_anchor)
            await estop_round(client, an, rng, a_anchor)
        t4 = time.time()
        for arm in (rb, an):
            await client.delete(f"{arm.url}/estop")
            await until_still(arm)
            r = await client.put(f"{arm.url}/safety", json={"zones": []})
            arm.count("PUT safety", r)
    for arm in (rb, an):
        if arm.watch.task is not None:
            arm.watch.task.cancel()

    print(f"\nphase 3, pass-through (issue 22), seed {seed}, {rounds} estop rounds per arm:")
    for arm, t_storm in ((rb, t1), (an, t2)):
        print(f"  {arm.name}: answers {dict(sorted(arm.answers.items()))}")
        for what, t in (("storms", t_storm), ("estop rounds", t3), ("whole phase", t_start)):
            peak = arm.peak(t)
            ratio = peak / arm.model.vmax
            print(f"  {arm.name} {what:<13} peak speed "
                  + ", ".join(f"{n} {p:.4g}/{v:g} ({r:.2f}x)" for n, p, v, r in
                              zip(arm.model.names, peak, arm.model.vmax, ratio, strict=True))
                  + ("  OVER 1.1x" if np.any(ratio > 1.1) else ""))
        n, hits, deepest = arm.inside()
        print(f"  {arm.name} zone 'bench': {hits} of {n} samples with a body point inside "
              f"(the zone grown by the point's margin), deepest {deepest * 1e3:.2f} mm")
        if arm.latch_offsets:
            worst = np.max(arm.latch_offsets, axis=0)
            over = sum(bool(np.any(o > arm.hold_tol)) for o in arm.latch_offsets)
            what = ("joints moved, latch to 0.4 s after (measured: the hold, plus a "
                    "loaded joint's droop and overshoot)" if arm.name == "rbe3001"
                    else "servo goals from where the arm was")
            print(f"  {arm.name} after {len(arm.latch_offsets)} latches: {what}: worst "
                  + ", ".join(f"{n} {w:.4g} (hold tolerance {t:.3g})" for n, w, t in
                              zip(arm.model.names, worst, arm.hold_tol, strict=True))
                  + f"; {over} latches over it")
        print(f"  {arm.name} telemetry dropped {arm.watch.dropped} samples")
    print(f"  SET_PID chase: the largest step the route took {largest:.3f} rad "
          f"(0.03 s at the limit is {0.03 * rb.model.vmax[0]:.3f})")
    _ = t4


if __name__ == "__main__":
    asyncio.run(main())
