"""Where a Dynamixel goal's time goes, hop by hop (issue 23's goal latency tail).

    python bench/goal_trace.py [--n 2000] [--json out.json]

The server runs in this process exactly as `armserver serve` runs it (the app of
`create_app`, uvicorn with httptools, the control thread, the simulated arms and cameras),
pinned to one core as `make bench-peers` pins it; a client in a subprocess on the other core
does what the harness's goal measure does (../shared/peers/rtt_armserver.py): a WebSocket on
the angler at rate=500, then for each goal a pause of 50-100 ms, `GET .../state`, and a `PUT
.../dynamixel/3/registers/goal_position` of 20-60 ticks, timed to the first sample whose joint 2
moved. Server and client read one clock (`time.perf_counter`: CLOCK_MONOTONIC on Linux).

The server is traced by wrapping a few functions of this process (nothing of the app changes):
each goal gets the wall time and the calling thread's CPU time (`time.thread_time`) at

    recv      the request's bytes reach the HTTP loop (the protocol's data_received)
    asgi      the ASGI app is called (httptools has parsed the head and body)
    route     the route calls ArmService.command_passthrough (middleware, auth, lease, body;
              since issue 23's HTTP change the register write's inner layer,
              app/arms/dynamixel/api.py `RegisterWriteFastPath`, in place of FastAPI's router
              and dependencies: `--root` on an export of the code before it, for both sides;
              bench/goal_http.py profiles this hop's CPU)
    ctrl      its body starts on the control thread (the hand-over: a thread switch and the
              control loop's wake-up, behind whatever that loop was running)
    check0/1  SafetyGuard.check_passthrough
    queued    Driver._submit queues the write for the owner task
    serve     the owner task takes it (a poll in progress on the bus goes first)
    write     the exchange starts (after the estop gate and the commanded note)
    reply     the servo's status reply is read
    ctrl_done the body returns on the control thread
    back      the answer is back on the HTTP loop
    resp      the response body is handed to the transport
    moved     the first published sample in which joint 2 moved (the poll after the write, or
              a later scheduled poll)

    ws_take   the HTTP loop takes that sample for the angler's WebSocket (at rate=500 each
              sample goes out as it is published: the telemetry route's prompt sender)

and the client adds `sent`, `answered` and `seen` (the sample on its WebSocket). Every poll of
every arm (start, end), every garbage collection (generation, start, end, and its own CPU time
on the thread that ran it) and every write of the telemetry batcher (`Broadcast._write_slice`)
is recorded too, to tell a wait behind a poll or a collection from work of the goal's own.
Figures: per hop p50, p90, p99 and max of the wall time, the CPU time where a hop stays on one
thread, for the slowest goals which hop holds their excess over the median, and what
overlapped each goal from `sent` to `seen`: for all goals, the slowest 2 % and the slowest 1 %,
how many met a collection of each generation (and in which hop it began), the share of their
excess over the median that collections' pauses account for, how many were queued behind a
poll, and the p99 with each goal's collection pauses taken out. On a shared machine the
figures move from run to run: compare hops within a run, not runs.

    python bench/goal_trace.py --n 1000 --no-hold

runs the garbage-collection policy as it was before issue 23's change (no `hold` by a goal,
no young collections on the policy's timer: app/runtime/gc_policy.py), for runs side by side.

    python bench/goal_trace.py --light --root /tmp/v030 --n 300

traces only the simulated link's bytes (the goal's WRITE and the polls after it), which works
on another checkout's code too: here an export of 0.3.0 (`git archive ece2776 | tar -x -C
/tmp/v030`). What it found (issue 23): the goals whose move showed a poll period late were
those whose poll read the bus sooner than theta3's first tick after the write (`TICK_S`);
docs/performance.md has the figures.
"""

from __future__ import annotations

import argparse
import asyncio
import gc
import json
import os
import random
import subprocess
import sys
import tempfile
import threading
import time
from collections import deque
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
# --root: another checkout's app (an export of 0.3.0, ece2776), traced with --light
_root = sys.argv[sys.argv.index("--root") + 1] if "--root" in sys.argv else str(ROOT)
sys.path.insert(0, _root)
#: One tick of the simulated theta3 at its Profile Velocity (2 rad/s: 1,304 ticks/s): the
#: simulated servo's first integration step of a velocity step goes half of v h, and Present
#: Position rounds, so a poll's read sooner than this after the goal's write reads the position
#: before it (app/arms/dynamixel/sim_motion.py; `--light` counts those).
TICK_S = 1.0 / 1304.0

PC = time.perf_counter
CPU = time.thread_time

#: The hops reported, as (name, from mark, to mark, same thread): the CPU time of a hop is
#: given only where both marks are taken on one thread.
HOPS = [
    ("client -> HTTP loop", "sent", "recv", False),
    ("parse (httptools, ASGI call)", "recv", "asgi", True),
    ("middleware, auth, lease, body", "asgi", "route", True),
    ("hand-over to the control loop", "route", "ctrl", False),
    ("before the check (busy, told)", "ctrl", "check0", True),
    ("check_passthrough", "check0", "check1", True),
    ("check -> queued", "check1", "queued", True),
    ("queue wait (behind a poll)", "queued", "serve", True),
    ("gate, note, encode", "serve", "write", True),
    ("write -> status reply", "write", "reply", True),
    ("reply -> body returns", "reply", "ctrl_done", True),
    ("answer back to the HTTP loop", "ctrl_done", "back", False),
    ("response built and written", "back", "resp", True),
    ("response -> client", "resp", "answered", False),
    ("reply -> the poll's read is written", "reply", "poll_write", True),
    ("goal written -> poll's read written", "write", "poll_write", True),
    ("reply -> moved sample published", "reply", "moved", True),
    ("moved sample -> the HTTP loop takes it", "moved", "ws_take", False),
    ("taken -> client's WebSocket", "ws_take", "seen", False),
    ("moved sample -> client's WebSocket", "moved", "seen", False),
]
TOTALS = [("goal -> response (client)", "sent", "answered"),
          ("goal -> moved sample seen (client: the harness's figure)", "sent", "seen")]

# ------------------------------------------------------------------ the client (subprocess)


async def client(base: str, n: int, gap: tuple[float, float], seed: int) -> list[dict[str, Any]]:
    import httpx
    import websockets

    rng = random.Random(seed)
    ws_url = base.replace("http", "ws") + "/api/v1/arms/angler/telemetry?rate=500"
    q: asyncio.Queue[tuple[float, dict[str, Any]]] = asyncio.Queue()
    out: list[dict[str, Any]] = []
    async with httpx.AsyncClient(base_url=base, timeout=5) as c, \
            websockets.connect(ws_url, max_size=None, compression=None) as ws:
        async def read() -> None:
            async for m in ws:
                t = PC()
                for s in json.loads(m).get("samples", []):
                    q.put_nowait((t, s))
        reader = asyncio.create_task(read())
        r = await c.get("/api/v1/arms/angler/dynamixel/3/registers/present_position")
        base_raw = r.json()["raw"] if r.status_code == 200 else 2048
        last = base_raw
        for i in range(n):
            await asyncio.sleep(rng.uniform(*gap))
            while not q.empty():
                q.get_nowait()
            cur = (await c.get("/api/v1/arms/angler/state")).json()["positions"][2]
            goal = last + rng.choice([-1, 1]) * rng.randint(20, 60)
            if abs(goal - base_raw) > 300:
                goal = last - (goal - last)
            last = goal
            rec: dict[str, Any] = {"i": i, "goal": goal}
            rec["sent"] = PC()
            r = await c.put("/api/v1/arms/angler/dynamixel/3/registers/goal_position",
                            json={"raw": goal}, headers={"x-goal": str(i)})
            rec["answered"] = PC()
            rec["status"] = r.status_code
            try:
                while True:
                    ts, s = await asyncio.wait_for(q.get(), max(0.01, rec["sent"] + 2 - PC()))
                    if abs(s["positions"][2] - cur) > 1e-4:
                        rec["seen"] = ts
                        break
            except TimeoutError:
                pass
            out.append(rec)
        reader.cancel()
    return out

# ------------------------------------------------------------------ the traced server


class Trace:
    """Marks of the goal in flight (goals are sequential), the polls and the collections."""

    def __init__(self) -> None:
        self.cur: dict[str, Any] | None = None
        self.goals: dict[int, dict[str, Any]] = {}
        self.polls: deque[tuple[str, float, float]] = deque(maxlen=2_000_000)
        self.gcs: list[tuple[int, float, float]] = []
        #: the telemetry batcher's writes of the angler's broadcast (start, end)
        self.batches: deque[tuple[str, float, float]] = deque(maxlen=2_000_000)
        self._gc_start = 0.0
        self._gc_cpu = 0.0
        self.gc_cpu: list[float] = []
        self.last_recv: tuple[float, float] | None = None

    def mark(self, name: str) -> None:
        g = self.cur
        if g is not None and name not in g:
            g[name] = (PC(), CPU(), threading.get_ident())

    def on_gc(self, phase: str, info: dict[str, Any]) -> None:
        if phase == "start":
            self._gc_cpu = CPU()
            self._gc_start = PC()
        else:
            t = PC()
            self.gcs.append((int(info["generation"]), self._gc_start, t))
            # the collection's own CPU time (wall minus what the OS took the core for)
            self.gc_cpu.append(CPU() - self._gc_cpu)


def install(trace: Trace) -> None:
    """Wrap the classes' functions (before the app is built)."""
    from app.device.owner import OwnerTask
    from app.safety.guard import SafetyGuard
    from app.service import ArmService
    from app.web.serving import ArmHttpToolsProtocol

    recv = ArmHttpToolsProtocol.data_received

    def data_received(self: Any, data: bytes) -> None:
        if data.startswith(b"PUT ") and b"goal_position" in data:
            trace.last_recv = (PC(), CPU())
        recv(self, data)
    ArmHttpToolsProtocol.data_received = data_received  # type: ignore[method-assign]

    outer = ArmService.command_passthrough

    async def command_passthrough(self: Any, goals: Any, send: Any) -> Any:
        trace.mark("route")
        try:
            return await outer(self, goals, send)
        finally:
            trace.mark("back")
    ArmService.command_passthrough = command_passthrough  # type: ignore[method-assign]

    inner = ArmService._command_passthrough

    async def _command_passthrough(self: Any, goals: Any, send: Any) -> Any:
        trace.mark("ctrl")
        g = trace.cur
        if g is not None and self.driver.positions is not None:
            g["pos0"] = float(self.driver.positions[2])
        try:
            return await inner(self, goals, send)
        finally:
            trace.mark("ctrl_done")
    ArmService._command_passthrough = _command_passthrough  # type: ignore[method-assign]

    check = SafetyGuard.check_passthrough

    def check_passthrough(self: Any, *a: Any, **k: Any) -> None:
        trace.mark("check0")
        try:
            check(self, *a, **k)
        finally:
            trace.mark("check1")
    SafetyGuard.check_passthrough = check_passthrough  # type: ignore[method-assign]

    serve = OwnerTask._serve

    async def _serve(self: Any, req: Any) -> None:
        if self.name == "angler" and "goal_position" in getattr(req.message, "what", ""):
            trace.mark("serve")
        await serve(self, req)
    OwnerTask._serve = _serve  # type: ignore[method-assign]

    do_poll = OwnerTask._do_poll

    async def _do_poll(self: Any) -> None:
        t0 = PC()
        self._bench_polling = True
        try:
            await do_poll(self)
        finally:
            self._bench_polling = False
            trace.polls.append((self.name, t0, PC()))
    OwnerTask._do_poll = _do_poll  # type: ignore[method-assign]

    from app.telemetry.hub import Subscription

    take_message = Subscription.take_message

    def _take_message(self: Any, *a: Any, **k: Any) -> Any:
        g = trace.cur
        if g is not None and "moved" in g and self.hub.arm == "angler":
            trace.mark("ws_take")
        return take_message(self, *a, **k)
    Subscription.take_message = _take_message  # type: ignore[method-assign]

    from app.web.ws_fanout import Broadcast

    write_slice = Broadcast._write_slice

    def _write_slice(self: Any, *a: Any, **k: Any) -> None:
        t0 = PC()
        try:
            write_slice(self, *a, **k)
        finally:
            trace.batches.append((self.hub.arm, t0, PC()))
    Broadcast._write_slice = _write_slice  # type: ignore[method-assign]

    from app.device.driver import Driver

    submit = Driver._submit

    async def _submit(self: Any, message: Any, *a: Any, **k: Any) -> Any:
        if self.name == "angler" and "goal_position" in getattr(message, "what", ""):
            trace.mark("queued")
            g = trace.cur
            if g is not None:  # the owner task is in a poll's exchange: the write waits for it
                g["queued_behind_poll"] = getattr(self, "_bench_polling", False)
        return await submit(self, message, *a, **k)
    Driver._submit = _submit  # type: ignore[method-assign]


def install_light(trace: Trace) -> None:
    """Only the simulated link (the same module in 0.3.0 and now): the goal's WRITE to servo 3
    and the SYNC_READ polls after it, by their bytes (Protocol 2.0: id at 4, instruction at
    7, a WRITE's address at 8-9)."""
    from app.links.sim import SimLink

    write = SimLink.write

    async def traced(self: Any, data: bytes) -> None:
        g = trace.cur
        if g is not None and len(data) > 10:
            if data[4] == 3 and data[7] == 0x03 and int.from_bytes(data[8:10], "little") == 116:
                trace.mark("write")
            elif data[7] == 0x82 and "write" in g:
                g.setdefault("polls", []).append(PC())
        await write(self, data)
    SimLink.write = traced  # type: ignore[method-assign]


def wrap_angler(trace: Trace, svc: Any) -> None:
    """Instance wrappers on the running angler: its exchange and its hub's publish."""
    drv = svc.driver
    exchange = drv._exchange

    async def _exchange(message: Any, timeout: float) -> Any:
        what = getattr(message, "what", "")
        goal = "goal_position" in what
        if goal:
            trace.mark("write")
        elif what == "SYNC_READ present state" and trace.cur is not None \
                and "reply" in trace.cur:
            trace.mark("poll_write")
        try:
            return await exchange(message, timeout)
        finally:
            if goal:
                trace.mark("reply")
    drv._exchange = _exchange

    hub = svc.hub
    publish = hub.publish

    def _publish(sample: dict[str, Any], inputs: Any = None) -> None:
        g = trace.cur
        if g is not None and "reply" in g and len(g.setdefault("after", [])) < 3:
            g["after"].append((round((PC() - g["reply"][0]) * 1e6),
                               round(sample["positions"][2] - g.get("pos0", 0.0), 6)))
        if (g is not None and "reply" in g and "moved" not in g and "pos0" in g
                and abs(sample["positions"][2] - g["pos0"]) > 1e-4):
            trace.mark("moved")
            g["moved_polls"] = g.get("polls_after", 0) + 1
        elif g is not None and "reply" in g and "moved" not in g:
            g["polls_after"] = g.get("polls_after", 0) + 1
        publish(sample, inputs)
    hub.publish = _publish


def traced_app(trace: Trace, app: Any) -> Any:
    async def asgi(scope: Any, receive: Any, send: Any) -> None:
        if scope["type"] != "http" or scope["method"] != "PUT" or \
                not scope["path"].endswith("goal_position"):
            await app(scope, receive, send)
            return
        i = int(dict(scope["headers"]).get(b"x-goal", b"-1"))
        g: dict[str, Any] = {}
        if trace.last_recv is not None:
            g["recv"] = (*trace.last_recv, threading.get_ident())
        trace.goals[i] = trace.cur = g
        trace.mark("asgi")

        async def traced_send(message: Any) -> None:
            await send(message)
            if message["type"] == "http.response.body":
                trace.mark("resp")
        await app(scope, receive, traced_send)
    return asgi


def run_server(args: argparse.Namespace) -> tuple[Trace, list[dict[str, Any]], float]:
    import uvicorn

    from app.cli import http_limits
    from app.config import Settings
    try:
        from app.web.factory import create_app
        from app.web.serving import ArmServer
    except ImportError:  # 0.3.0's layout (--root)
        from app.main import create_app  # type: ignore[no-redef]
        from app.serving import ArmServer  # type: ignore[no-redef]

    cpus = sorted(os.sched_getaffinity(0))
    if len(cpus) >= 2:  # as make bench-peers: server on one core, load on another
        os.sched_setaffinity(0, {cpus[0]})
    trace = Trace()
    if args.light:
        install_light(trace)
    else:
        install(trace)
    gc.callbacks.append(trace.on_gc)
    if args.no_hold:  # the goals as before issue 23's hold: collections may fall in them
        from app.runtime import gc_policy
        gc_policy.hold = lambda seconds=0.0: False
        gc_policy.Collector.collect_young = lambda self: None
    settings = Settings()
    app = create_app(settings, camera_configs=[]) if args.no_cameras else create_app(settings)
    import socket
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    config = uvicorn.Config(traced_app(trace, app), host="127.0.0.1", port=port,
                            log_level="warning", proxy_headers=False,
                            ws_max_size=settings.max_ws_message_bytes, **http_limits(settings))
    server = ArmServer(config, app)
    result: list[dict[str, Any]] = []
    load: list[float] = []

    def drive() -> None:
        deadline = time.monotonic() + 60
        while not getattr(app.state, "services", None) or not server.started:
            if time.monotonic() > deadline:
                server.should_exit = True
                return
            time.sleep(0.1)
        svc = app.state.services["angler"]
        while svc.driver.stale and time.monotonic() < deadline:
            time.sleep(0.1)
        if not args.light:
            wrap_angler(trace, svc)
        time.sleep(1.0)
        load.append(os.getloadavg()[0])
        cmd = [sys.executable, __file__, "--client", f"http://127.0.0.1:{port}", "--n",
               str(args.n), "--seed", str(args.seed), "--gap", *map(str, args.gap)]
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, cwd=ROOT)
        if len(cpus) >= 2:
            os.sched_setaffinity(proc.pid, set(cpus[1:]))
        out, _ = proc.communicate()
        load.append(os.getloadavg()[0])
        result.extend(json.loads(out) if out else [])
        server.should_exit = True

    threading.Thread(target=drive, name="bench-drive", daemon=True).start()
    server.run()
    return trace, result, max(load) if load else float("nan")

# ------------------------------------------------------------------ figures


def pct(xs: list[float], q: float) -> float:
    xs = sorted(xs)
    return xs[min(len(xs) - 1, int(q * len(xs)))] if xs else float("nan")


def overlaps(spans: Any, t0: float, t1: float) -> float:
    """How much of [t0, t1] the spans (name, start, end) cover, s."""
    return sum(max(0.0, min(e, t1) - max(s, t0)) for _, s, e in spans)


def analyse(trace: Trace, client_recs: list[dict[str, Any]], load: float) -> dict[str, Any]:
    rows = []
    for c in client_recs:
        g = trace.goals.get(c["i"])
        if g is None or c.get("status") != 200:
            continue
        row = {k: v[0] for k, v in g.items() if isinstance(v, tuple)}
        cpu = {k: v[1] for k, v in g.items() if isinstance(v, tuple)}
        tid = {k: v[2] for k, v in g.items() if isinstance(v, tuple)}
        row.update({k: c[k] for k in ("sent", "answered", "seen") if k in c})
        rows.append((row, cpu, tid, g))
    hops: dict[str, Any] = {}
    for name, a, b, same in HOPS:
        wall = [r[b] - r[a] for r, _, _, _ in rows if a in r and b in r]
        cpu = [c[b] - c[a] for r, c, t, _ in rows if same and a in c and b in c and t[a] == t[b]]
        hops[name] = {"n": len(wall), **{f"wall_{k}": round(pct(wall, q) * 1e6, 1)
                                         for k, q in (("p50", .5), ("p90", .9), ("p99", .99),
                                                      ("max", 1.0))}}
        if cpu:
            hops[name].update({f"cpu_{k}": round(pct(cpu, q) * 1e6, 1)
                               for k, q in (("p50", .5), ("p99", .99))})
    totals = {}
    for name, a, b in TOTALS:
        xs = [r[b] - r[a] for r, _, _, _ in rows if a in r and b in r]
        totals[name] = {"n": len(xs), **{k: round(pct(xs, q) * 1e3, 3) for k, q in
                                         (("p50", .5), ("p90", .9), ("p99", .99), ("max", 1.))}}
    # the slowest goals by the harness's figure: which hop holds their excess over the median
    seen = sorted(((r["seen"] - r["sent"], r, g) for r, _, _, g in rows if "seen" in r),
                  key=lambda x: x[0])
    med = {name: pct([r[b] - r[a] for r, _, _, _ in rows if a in r and b in r], .5)
           for name, a, b, _ in HOPS}
    slow = seen[-max(1, len(seen) // 100):]
    blame: dict[str, int] = {}
    detail = []
    for total, r, g in slow:
        excess = {name: (r[b] - r[a]) - med[name] for name, a, b, _ in HOPS if a in r and b in r}
        worst = max(excess, key=lambda k: excess[k])
        blame[worst] = blame.get(worst, 0) + 1
        gc_in = [(gen, round((e - s) * 1e3, 2)) for gen, s, e in trace.gcs
                 if e > r["sent"] and s < r["seen"]]
        polls = [p for p in trace.polls if p[2] > r["sent"] and p[1] < r["seen"]]
        detail.append({
            "total_ms": round(total * 1e3, 2),
            "excess_us": {k: round(v * 1e6) for k, v in sorted(excess.items(),
                                                               key=lambda kv: -kv[1])[:3]},
            "moved_at_poll": g.get("moved_polls"),
            "after_reply": g.get("after"),
            "queued_behind_poll": g.get("queued_behind_poll"),
            "gc": gc_in,
            "other_arms_polling_ms": round(overlaps([p for p in polls if p[0] != "angler"],
                                                    r["sent"], r["seen"]) * 1e3, 2),
        })
    causes = tail_causes(trace, rows)
    first_poll = [g["polls"][0] - r["write"] for r, _, _, g in rows
                  if g.get("polls") and "write" in r]
    early = sum(1 for dt in first_poll if dt < TICK_S)
    moved_at = [g.get("moved_polls") for _, _, _, g in rows]
    split = {}
    for k in sorted(set(moved_at), key=str):
        xs = [r["poll_write"] - r["write"] for r, _, _, g in rows
              if g.get("moved_polls") == k and "poll_write" in r and "write" in r]
        if xs:
            split[str(k)] = [round(pct(xs, q) * 1e6) for q in (0, .1, .5, .9, 1.)]
    return {
        "goals": len(rows), "load_average_1min": round(load, 2),
        "totals_ms": totals, "hops_us": hops,
        "moved_at_poll": {str(k): moved_at.count(k) for k in sorted(set(moved_at), key=str)},
        "write_to_poll_by_mode_us": split,
        "first_poll_read_before_a_tick": f"{early} of {len(first_poll)}",
        "write_to_first_poll_us": [round(pct(first_poll, q) * 1e6) for q in
                                   (0, .01, .1, .5, .9, .99, 1.)] if first_poll else [],
        "queued_behind_poll": sum(1 for *_, g in rows if g.get("queued_behind_poll")),
        "gc_collections": {str(gen): sum(1 for g, _, _ in trace.gcs if g == gen)
                           for gen in (0, 1, 2)},
        "gc_ms_p50_max": {str(gen): [round(pct(d, q) * 1e3, 2) for q in (.5, 1.)]
                          for gen in (0, 1, 2)
                          if (d := [e - s for g, s, e in trace.gcs if g == gen])},
        "gc_cpu_ms_p50_p99_max": {str(gen): [round(pct(d, q) * 1e3, 2) for q in (.5, .99, 1.)]
                                  for gen in (0, 1, 2)
                                  if (d := [c for (g, _, _), c in zip(trace.gcs, trace.gc_cpu,
                                                                      strict=False) if g == gen])},
        "slowest_1pct_blame": blame, "slowest_1pct": detail, "causes": causes,
    }


#: The marks of a goal's one path, in order (the answer's marks run beside it).
CHAIN = ["sent", "recv", "asgi", "route", "ctrl", "check0", "check1", "queued", "serve",
         "write", "reply", "poll_write", "moved", "ws_take", "seen"]


def pct_i(xs: list[float], q: float) -> float:
    """The harness's percentile (rtt_armserver.py: linear between the two nearest ranks)."""
    xs = sorted(xs)
    if not xs:
        return float("nan")
    k = (len(xs) - 1) * q
    f = int(k)
    c = min(f + 1, len(xs) - 1)
    return xs[f] + (xs[c] - xs[f]) * (k - f)


def tail_causes(trace: Trace, rows: list[Any]) -> dict[str, Any]:
    """For every goal, what overlapped it between sent and seen: collections (generation,
    pause, and the hop each began in), the angler's poll in progress when the write was
    queued, the other arms' polls, the telemetry batcher's writes; then the slowest 2 % and
    1 % against all goals, and the p99 with the collections' pauses taken out of each goal."""
    per = []
    for r, _, _, g in rows:
        if "seen" not in r:
            continue
        t0, t1 = r["sent"], r["seen"]
        chain = [(r[m], m) for m in CHAIN if m in r]
        gcs = []
        for gen, s, e in trace.gcs:
            if e > t0 and s < t1:
                hop = max((c for c in chain if c[0] <= s), default=(0.0, "before"))[1]
                gcs.append((gen, min(e, t1) - max(s, t0), hop))
        polls = [p for p in trace.polls if p[2] > t0 and p[1] < t1]
        batches = [b for b in trace.batches if b[2] > t0 and b[1] < t1]
        per.append({
            "total": t1 - t0, "gc": gcs, "gc_s": sum(x[1] for x in gcs),
            "gc_gen": max((x[0] for x in gcs), default=-1),
            "behind_poll": bool(g.get("queued_behind_poll")),
            "angler_polls_s": overlaps([p for p in polls if p[0] == "angler"], t0, t1),
            "other_polls_s": overlaps([p for p in polls if p[0] != "angler"], t0, t1),
            "batch_s": overlaps(batches, t0, t1),
            "moved_at": g.get("moved_polls"),
        })
    if not per:
        return {}
    per.sort(key=lambda x: x["total"])
    med = pct([x["total"] for x in per], .5)

    def group(xs: list[dict[str, Any]]) -> dict[str, Any]:
        n = len(xs)
        excess = sum(max(0.0, x["total"] - med) for x in xs)
        gc_hops: dict[str, int] = {}
        for x in xs:
            for _, _, hop in x["gc"]:
                gc_hops[hop] = gc_hops.get(hop, 0) + 1
        return {
            "n": n,
            "with_gen2": sum(1 for x in xs if x["gc_gen"] == 2),
            "with_gen1": sum(1 for x in xs if x["gc_gen"] == 1),
            "with_gen0_only": sum(1 for x in xs if x["gc_gen"] == 0),
            "without_gc": sum(1 for x in xs if x["gc_gen"] < 0),
            "gc_ms_mean": round(sum(x["gc_s"] for x in xs) / n * 1e3, 2),
            "excess_over_median_ms_mean": round(excess / n * 1e3, 2),
            "share_of_excess_in_gc": round(sum(min(x["gc_s"], max(0.0, x["total"] - med))
                                               for x in xs) / excess, 2) if excess else 0.0,
            "behind_a_poll": sum(1 for x in xs if x["behind_poll"]),
            "moved_after_first_poll": sum(1 for x in xs if (x["moved_at"] or 1) > 1),
            "other_arms_polls_ms_mean": round(sum(x["other_polls_s"] for x in xs) / n * 1e3, 2),
            "batcher_ms_mean": round(sum(x["batch_s"] for x in xs) / n * 1e3, 2),
            "gc_began_in_hop": gc_hops,
        }
    totals = [x["total"] for x in per]
    without = [x["total"] - x["gc_s"] for x in per]
    n = len(per)
    return {
        "all": group(per), "slowest_2pct": group(per[-max(1, n // 50):]),
        "slowest_1pct": group(per[-max(1, n // 100):]),
        "p50_p99_ms (harness percentile)": [round(pct_i(totals, q) * 1e3, 2) for q in (.5, .99)],
        "p50_p99_ms without the collections pauses": [round(pct_i(without, q) * 1e3, 2)
                                                        for q in (.5, .99)],
        "slowest_10": [{"ms": round(x["total"] * 1e3, 2),
                        "gc": [(gen, round(d * 1e3, 2), hop) for gen, d, hop in x["gc"]],
                        "behind_poll": x["behind_poll"], "moved_at": x["moved_at"],
                        "other_polls_ms": round(x["other_polls_s"] * 1e3, 2),
                        "batcher_ms": round(x["batch_s"] * 1e3, 2)} for x in per[-10:]],
    }


def show(fig: dict[str, Any]) -> None:
    print(f"{fig['goals']} goals, load average {fig['load_average_1min']}")
    for name, t in fig["totals_ms"].items():
        print(f"  {name}: p50 {t['p50']:.2f}  p90 {t['p90']:.2f}  p99 {t['p99']:.2f}  "
              f"max {t['max']:.2f} ms")
    print(f"  {'hop':40s} {'wall p50':>9s} {'p90':>8s} {'p99':>8s} {'max':>8s} "
          f"{'cpu p50':>8s} {'cpu p99':>8s}  (us)")
    for name, h in fig["hops_us"].items():
        cpu = (f"{h['cpu_p50']:8.1f} {h['cpu_p99']:8.1f}" if "cpu_p50" in h else "")
        print(f"  {name:40s} {h['wall_p50']:9.1f} {h['wall_p90']:8.1f} {h['wall_p99']:8.1f} "
              f"{h['wall_max']:8.1f} {cpu}")
    print(f"  the move first seen at the n-th poll after the reply: {fig['moved_at_poll']}")
    print(f"  goal written -> the next poll's read written (min, p10, p50, p90, max us), by "
          f"the poll that saw the move: {fig['write_to_poll_by_mode_us']}")
    print(f"  goal written -> the first poll's read written (min, p1, p10, p50, p90, p99, max "
          f"us): {fig['write_to_first_poll_us']}; sooner than a tick of theta3's motion "
          f"({TICK_S * 1e6:.0f} us): {fig['first_poll_read_before_a_tick']}")
    print(f"  goals queued behind a poll in progress: {fig['queued_behind_poll']}")
    print(f"  collections during the run, by generation: {fig['gc_collections']}; their "
          f"pause p50 and max, ms: {fig['gc_ms_p50_max']}")
    print(f"  their CPU time p50, p99 and max, ms: {fig['gc_cpu_ms_p50_p99_max']}")
    print(f"  slowest 1 %: the hop with the largest excess over its median: "
          f"{fig['slowest_1pct_blame']}")
    for d in fig["slowest_1pct"]:
        print(f"    {d['total_ms']:6.2f} ms  {d['excess_us']}  moved at poll "
              f"{d['moved_at_poll']} {d['after_reply']}, behind a poll "
              f"{d['queued_behind_poll']}, gc {d['gc']}, other arms' polls "
              f"{d['other_arms_polling_ms']} ms")


def show_causes(c: dict[str, Any]) -> None:
    if not c:
        return
    print("  what overlapped the goals (sent -> seen), all goals against the slowest:")
    for k in ("all", "slowest_2pct", "slowest_1pct"):
        print(f"    {k:13s} {c[k]}")
    print(f"  goal -> moved sample seen p50, p99 (the harness's percentile): "
          f"{c['p50_p99_ms (harness percentile)']} ms; with each goal's collection pauses "
          f"taken out: {c['p50_p99_ms without the collections pauses']} ms")
    print("  the slowest ten:")
    for x in c["slowest_10"]:
        print(f"    {x}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--n", type=int, default=2000, help="goals (default 2000)")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--gap", type=float, nargs=2, default=(0.05, 0.1),
                    help="pause before each goal, s (default 0.05 0.1, as the harness)")
    ap.add_argument("--json", help="write the figures here too")
    ap.add_argument("--light", action="store_true",
                    help="trace only the simulated link's bytes (works on 0.3.0's code too)")
    ap.add_argument("--root", help="import the app from this checkout (e.g. an export of "
                    "ece2776, with --light)")
    ap.add_argument("--no-cameras", action="store_true",
                    help="without the simulated cameras `armserver serve` starts by default")
    ap.add_argument("--no-hold", action="store_true",
                    help="as before issue 23's change: goals do not hold collections off and the "
                    "policy does not run the young ones (app/runtime/gc_policy.py)")
    ap.add_argument("--client", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.client:
        print(json.dumps(asyncio.run(client(args.client, args.n, tuple(args.gap), args.seed))))
        return
    os.environ.setdefault("ARMSERVER_DATA_DIR", tempfile.mkdtemp(prefix="goal-trace-"))
    trace, recs, load = run_server(args)
    fig = analyse(trace, recs, load)
    show(fig)
    show_causes(fig.get("causes", {}))
    if args.json:
        Path(args.json).write_text(json.dumps(fig, indent=1))


if __name__ == "__main__":
    main()
