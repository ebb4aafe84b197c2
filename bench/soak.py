"""Faults soak: the server under injected link faults, concurrent clients and telemetry.

Starts the server in this process (uvicorn on a loopback port, in its own thread and event
loop) over the two simulated arms, sets faults on their simulated links at run time (replies
dropped, corrupted and delayed, and the link cut every few seconds), then runs for `--seconds`:

- one mover per arm: joint and line moves, `wait: true` and 202-then-poll, each verified when
  it ends `done` against three fresh `/state` samples taken after it ended (the median of the
  joints at the target within 1.5 x the settle tolerance: `judge_done`), or counted failed
  with its code and reason;
- protocol clients: rbe3001 STATUS and SET_GAIN, Dynamixel register reads (`id`,
  `model_number`), PING and SYNC_READ, each answer checked against what the device must say;
- WebSocket subscribers on both arms, checking that sample numbers only grow and that every
  gap is one the server reported in `dropped`.

It prints a table: requests sent, answered correctly, failed with a clear error (a documented
status and code), lost (no answer within the bound), wrongly answered; motions done (verified),
failed (with a reason), wrongly reported done; telemetry gaps against reported drops; memory
(RSS of this process) at start and end. Exit status 1 if anything was lost or wrong.

    python bench/soak.py --seconds 300 [--drop 0.05 --corrupt 0.02 --latency 0.005
                                        --disconnect-every 10]
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import math
import random
import socket
import sys
import threading
import time
from collections import Counter
from collections.abc import Awaitable, Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import httpx  # noqa: E402
import numpy as np  # noqa: E402
import uvicorn  # noqa: E402
from websockets.asyncio.client import connect  # noqa: E402
from websockets.exceptions import ConnectionClosed  # noqa: E402

from app.config import FaultConfig, Settings  # noqa: E402
from app.web.factory import create_app  # noqa: E402

API = "/api/v1"
#: Codes a request may fail with under link faults and concurrent use (API.md, app/errors.py).
CLEAR_CODES = {"device_timeout", "corrupt_reply", "device_error", "link_down", "busy",
               "joint_limit", "unreachable", "invalid_request", "not_settled"}
#: Bound on a protocol request, s: the driver answers or fails within its timeout and queue.
REQUEST_BOUND_S = 10.0
#: Bound on a motion beyond its planned duration, s (settle timeout, reconnects, queueing).
MOTION_SLACK_S = 20.0
#: Tolerance of the done check against /state (1.5 x the executor's settle tolerance).
TOL = {"revolute": 0.045, "prismatic": 0.003}
#: The done check reads this many fresh samples (distinct `seq`, taken at or after the motion's
#: `ended`) and judges their per-joint median (`judge_done`): one sample is not where the arm
#: is under injected corruption (module doc of `judge_done`).
DONE_SAMPLES = 3
#: Bound on reading them, s (a link cut right after the motion: 0.5 s down, then set-up).
DONE_READ_BOUND_S = 3.0


# ---------------------------------------------------------------- the server, in process


@dataclass
class Server:
    url: str
    ws_url: str
    app: Any
    loop: asyncio.AbstractEventLoop

    def call(self, fn: Callable[[], Awaitable[Any]], timeout: float = 10.0) -> Any:
        """Run `await fn()` in the server's loop (the services and links belong to it)."""
        return asyncio.run_coroutine_threadsafe(fn(), self.loop).result(timeout)

    def set_faults(self, faults: FaultConfig) -> None:
        async def _set() -> None:
            for svc in self.app.state.services.values():
                svc.driver.link.set_faults(faults)
        self.call(_set)


@contextlib.contextmanager
def serve(settings: Settings | None = None, ready_s: float = 15.0) -> Iterator[Server]:
    """uvicorn over the default simulated arms on 127.0.0.1 (a free port), in a thread."""
    settings = settings or Settings(config=None, operator_tokens="", viewer_tokens="")
    app = create_app(settings)
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    sock.bind(("127.0.0.1", 0))
    port = sock.getsockname()[1]
    server = uvicorn.Server(uvicorn.Config(app, log_level="warning", lifespan="on",
                                           ws_max_size=settings.max_ws_message_bytes))
    box: dict[str, asyncio.AbstractEventLoop] = {}

    def run() -> None:
        async def main() -> None:
            box["loop"] = asyncio.get_running_loop()
            await server.serve(sockets=[sock])
        asyncio.run(main())

    thread = threading.Thread(target=run, name="soak-uvicorn", daemon=True)
    thread.start()
    deadline = time.monotonic() + ready_s
    while not server.started or not _ready(app):
        if not thread.is_alive() or time.monotonic() > deadline:
            raise RuntimeError("the server did not start")
        time.sleep(0.02)
    try:
        yield Server(f"http://127.0.0.1:{port}", f"ws://127.0.0.1:{port}", app, box["loop"])
    finally:
        server.should_exit = True
        thread.join(15)
        sock.close()


def _ready(app: Any) -> bool:
    svcs = getattr(app.state, "services", {})
    return bool(svcs) and all(s.hub.latest is not None and not s.driver.stale
                              for s in svcs.values())


def rss_kib() -> int:
    """Resident set size of this process, KiB (/proc/self/status VmRSS)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    return 0


# ---------------------------------------------------------------- tallies


@dataclass
class Tally:
    sent: int = 0
    correct: int = 0
    failed: Counter[str] = field(default_factory=Counter)
    lost: int = 0
    wrong: int = 0
    wrong_examples: list[str] = field(default_factory=list)
    by_kind: Counter[str] = field(default_factory=Counter)
    motions: Counter[str] = field(default_factory=Counter)
    motion_codes: Counter[str] = field(default_factory=Counter)
    wrongly_done: int = 0
    done_unverified: int = 0  # no fresh sample after it ended: its final_positions
    samples: int = 0
    seq_gaps: int = 0
    reported_dropped: int = 0
    seq_backwards: int = 0
    ws_messages: int = 0
    ws_reconnects: int = 0
    events: Counter[str] = field(default_factory=Counter)

    def wrong_answer(self, what: str) -> None:
        self.wrong += 1
        if len(self.wrong_examples) < 10:
            self.wrong_examples.append(what[:400])


class Client:
    """Sends one request, classifies its answer; `check(json) -> bool` says whether a 2xx
    answer is right."""

    def __init__(self, http: httpx.AsyncClient, tally: Tally) -> None:
        self.http = http
        self.t = tally

    async def request(self, kind: str, method: str, path: str, *, json_body: Any = None,
                      check: Callable[[Any], bool] | None = None,
                      bound: float = REQUEST_BOUND_S) -> tuple[int, Any] | None:
        self.t.sent += 1
        self.t.by_kind[kind] += 1
        try:
            r = await asyncio.wait_for(self.http.request(method, path, json=json_body), bound)
        except (TimeoutError, httpx.HTTPError) as exc:
            self.t.lost += 1
            self.t.wrong_examples.append(f"LOST {method} {path}: {type(exc).__name__} {exc}")
            return None
        try:
            body = r.json()
        except ValueError:
            self.t.wrong_answer(f"{method} {path} -> {r.status_code} not JSON: {r.text[:200]}")
            return None
        if r.status_code < 300:
            if check is None or check(body):
                self.t.correct += 1
            else:
                self.t.wrong_answer(f"{method} {path} -> {r.status_code} {body}")
            return r.status_code, body
        if (isinstance(body, dict) and set(body) == {"detail", "code"} and r.status_code != 500
                and body["code"] in CLEAR_CODES and body["detail"]):
            self.t.failed[body["code"]] += 1
        else:
            self.t.wrong_answer(f"{method} {path} -> {r.status_code} {body}")
        return r.status_code, body


# ---------------------------------------------------------------- workers


def _inner(lo: float, hi: float, rng: random.Random, frac: float = 0.25) -> float:
    return rng.uniform(lo + frac * (hi - lo), hi - frac * (hi - lo))


class Mover:
    """One arm's only mover: a move, then its verification, then the next."""

    def __init__(self, c: Client, arm: str, detail: dict[str, Any], model: Any, seed: int) -> None:
        self.c = c
        self.arm = arm
        self.joints = detail["joints"]
        self.model = model
        self.rng = random.Random(seed)

    def _target(self, current: list[float]) -> list[float]:
        out = []
        for j, q in zip(self.joints, current, strict=True):
            lo, hi = j["min"], j["max"]
            if j["kind"] == "prismatic":  # the angler's leads are slow: short hops
                step = 0.012
                out.append(float(np.clip(q + self.rng.uniform(-step, step),
                                         lo + 0.1 * (hi - lo), hi - 0.1 * (hi - lo))))
            else:
                out.append(_inner(lo, hi, self.rng))
        return out

    async def run(self, until: float) -> None:
        n = 0
        while time.monotonic() < until:
            st = await self.c.request("state", "GET", f"{API}/arms/{self.arm}/state",
                                      check=_sample_ok)
            if st is None or st[0] != 200:
                await asyncio.sleep(0.2)
                continue
            q = self._target(st[1]["positions"])
            wait = n % 2 == 0
            shape = n % 4
            n += 1
            if shape < 2:
                path, body = "move/joints", {"positions": q, "wait": wait}
            else:
                tip = self.model.fk(np.array(q))
                body = {"x": float(tip[0]), "y": float(tip[1]), "z": float(tip[2]),
                        "path": "line" if shape == 3 else "joint", "wait": wait}
                path = "move/pose"
            await self._move(path, body, wait)

    async def _move(self, path: str, body: dict[str, Any], wait: bool) -> None:
        url = f"{API}/arms/{self.arm}/{path}"
        res = await self.c.request(f"move {path} wait={wait}", "POST", url, json_body=body,
                                   check=_motion_ok, bound=120.0 if wait else REQUEST_BOUND_S)
        if res is None or res[0] >= 300:
            return
        m = res[1]
        if not wait:
            m = await self._poll(m)
            if m is None:
                return
        await self._verify(m)

    async def _poll(self, m: dict[str, Any]) -> dict[str, Any] | None:
        deadline = time.monotonic() + m["planned_duration"] + MOTION_SLACK_S
        while time.monotonic() < deadline:
            res = await self.c.request("motion status", "GET",
                                       f"{API}/arms/{self.arm}/motions/{m['id']}",
                                       check=lambda b, mid=m["id"]: b.get("id") == mid)
            if res is not None and res[0] == 200 and res[1]["status"] not in ("queued",
                                                                                "running"):
                return res[1]
            await asyncio.sleep(0.05)
        self.c.t.lost += 1
        self.c.t.wrong_examples.append(f"LOST motion {m['id']}: never ended")
        return None

    async def _verify(self, m: dict[str, Any]) -> None:
        t = self.c.t
        t.motions[m["status"]] += 1
        if m["status"] == "failed":
            t.motion_codes[m.get("code") or "-"] += 1
            if not m.get("reason") or not m.get("code"):
                t.wrong_answer(f"motion failed without a reason: {m}")
            return
        if m["status"] != "done":
            return
        target = np.array(m["target_positions"])
        tol = np.array([TOL[j["kind"]] for j in self.joints])
        samples = await self._samples_after(m["ended"])
        if not samples:  # no fresh sample within the bound: the server's own record
            t.done_unverified += 1
            samples = [{"seq": -1, "time": m["ended"],
                        "positions": m["final_positions"] or (target + np.inf).tolist()}]
        ok, q = judge_done([s["positions"] for s in samples], target, tol)
        if not ok:
            t.wrongly_done += 1
            t.wrong_examples.append(
                f"WRONGLY DONE {self.arm} {m['id']}: at {q.tolist()} (median of "
                f"{len(samples)}), target {target.tolist()}; ended {m['ended']:.3f}, samples "
                + "; ".join(f"seq {s['seq']} t {s['time']:.3f} {s['positions']}"
                            for s in samples))

    async def _samples_after(self, ended: float) -> list[dict[str, Any]]:
        """Up to DONE_SAMPLES fresh samples (not stale, distinct seq) taken at or after
        `ended` (both Unix time: the sample's `time` is when the device was read), read from
        `/state` within DONE_READ_BOUND_S."""
        out: list[dict[str, Any]] = []
        deadline = time.monotonic() + DONE_READ_BOUND_S
        while len(out) < DONE_SAMPLES and time.monotonic() < deadline:
            st = await self.c.request("state", "GET", f"{API}/arms/{self.arm}/state",
                                      check=_sample_ok)
            if (st is not None and st[0] == 200 and not st[1]["stale"]
                    and st[1]["time"] >= ended
                    and all(st[1]["seq"] != s["seq"] for s in out)):
                out.append(st[1])
                continue
            await asyncio.sleep(0.01)
        return out


def judge_done(samples: list[list[float]], target: np.ndarray,
               tol: np.ndarray) -> tuple[bool, np.ndarray]:
    """Whether the arm is at `target` (within `tol`) after a motion reported `done` (API.md:
    "nothing is reported done that was not"), from fresh samples taken after it ended.

    Judged on the per-joint median of three or more samples, or, with fewer, wrong only if
    every sample is off: never on one sample alone. The soak corrupts 2 % of replies (one byte
    each) and the rbe3001 protocol has no checksum, so a corrupted reading the driver cannot
    refuse is published as one sample (it stays within the jump check's bound, and the next
    poll replaces it). The failure of this soak's old check was such a sample: the rbe3001
    settled at base -268 ticks (-0.4111 rad, target -0.4116), and the one `/state` it read said
    -151 ticks (-0.2316 rad): float32 -268.0 is c3 86 00 00 and -151.0 is c3 17 00 00, one
    byte changed, a jump of 0.18 rad inside the 0.35 rad a reading 10 ms later may move. An arm
    really away from its target reads away in every sample, and is caught. Answers the
    verdict and the positions judged."""
    q = np.array(samples, dtype=float)
    if len(q) >= DONE_SAMPLES:
        mid = np.median(q, axis=0)
        return bool(np.all(np.abs(mid - target) <= tol)), mid
    near = [bool(np.all(np.abs(row - target) <= tol)) for row in q]
    return any(near), q[near.index(True)] if any(near) else q[0]


def _sample_ok(b: Any) -> bool:
    return (isinstance(b, dict) and isinstance(b.get("seq"), int)
            and all(math.isfinite(v) for v in b["positions"]))


def _motion_ok(b: Any) -> bool:
    return isinstance(b, dict) and isinstance(b.get("id"), str) and b.get("status") in (
        "queued", "running", "done", "stopped", "failed")


async def rbe3001_protocol(c: Client, until: float, seed: int) -> None:
    rng = random.Random(seed)
    url = f"{API}/arms/rbe3001/rbe3001"

    def status_ok(b: Any) -> bool:
        return (all(len(b[k]) == 3 for k in ("position_ticks", "velocity_ticks_s", "strain_adc"))
                and all(math.isfinite(v) and abs(v) < 64 * 4096 for v in b["position_ticks"]))

    def set_gain_ok(b: Any) -> bool:
        # "no return values" (design document): the firmware's answer is told, never refused
        # (issue 24): zeros or the echo, other bytes (a corrupted reply: logged), or none
        return (b.get("ok") is True and b.get("command") == "SET_GAIN"
                and b.get("reply") in ("acknowledged", "other", "sent"))

    while time.monotonic() < until:
        if rng.random() < 0.8:
            await c.request("rbe3001 status", "GET", f"{url}/status", check=status_ok)
        else:  # the firmware's own gains: harmless to the motion under way
            await c.request("rbe3001 set-gain", "POST", f"{url}/set-gain",
                            json_body={"axis": rng.randrange(3), "kp": 0.005, "ki": 0.0,
                                       "kd": 0.0},
                            check=set_gain_ok)
        await asyncio.sleep(rng.uniform(0.0, 0.02))


async def dynamixel_protocol(c: Client, until: float, seed: int) -> None:
    rng = random.Random(seed)
    url = f"{API}/arms/angler/dynamixel"
    while time.monotonic() < until:
        i = rng.choice([1, 2, 3, 4])
        k = rng.random()
        if k < 0.4:
            await c.request("dxl read id", "GET", f"{url}/{i}/registers/id",
                            check=lambda b, i=i: b["raw"] == i and b["id"] == i)
        elif k < 0.6:
            await c.request("dxl read model_number", "GET", f"{url}/{i}/registers/model_number",
                            check=lambda b: b["raw"] == 30)
        elif k < 0.8:
            await c.request("dxl ping", "POST", f"{url}/ping", json_body={"id": i},
                            check=lambda b, i=i: [(d["id"], d["model_number"])
                                                  for d in b["devices"]] == [(i, 30)])
        else:
            ids = rng.sample([1, 2, 3, 4], 3)
            await c.request("dxl sync-read id", "POST", f"{url}/sync-read",
                            json_body={"name": "id", "ids": ids},
                            check=lambda b, ids=ids: b["values"] == {str(x): x for x in ids})
        await asyncio.sleep(rng.uniform(0.0, 0.02))


async def subscriber(ws_url: str, arm: str, until: float, t: Tally, rate: float = 20.0) -> None:
    """Counts samples, gaps in `seq` and the drops the server reported; reconnects if cut."""
    url = f"{ws_url}{API}/arms/{arm}/telemetry?rate={rate}"
    last: int | None = None
    while time.monotonic() < until:
        try:
            async with connect(url, max_size=2**24) as ws:
                while (left := until - time.monotonic()) > 0:
                    try:
                        raw = await asyncio.wait_for(ws.recv(), left)
                    except TimeoutError:
                        return
                    msg = json.loads(raw)
                    t.ws_messages += 1
                    if msg["type"] == "event":
                        t.events[msg["event"]] += 1
                        continue
                    t.reported_dropped += msg["dropped"]
                    for s in msg["samples"]:
                        t.samples += 1
                        if last is not None:
                            if s["seq"] <= last:
                                t.seq_backwards += 1
                            else:
                                t.seq_gaps += s["seq"] - last - 1
                        last = s["seq"]
        except (OSError, ConnectionClosed):
            t.ws_reconnects += 1
            last = None  # a new connection starts at the latest sample
            await asyncio.sleep(0.2)


# ---------------------------------------------------------------- the run


async def soak(srv: Server, seconds: float, faults: FaultConfig, seed: int = 1,
               subscribers_per_arm: int = 2) -> dict[str, Any]:
    t = Tally()
    async with httpx.AsyncClient(base_url=srv.url, timeout=None) as http:
        c = Client(http, t)
        details = {a: (await http.get(f"{API}/arms/{a}")).json() for a in ("rbe3001", "angler")}
        await asyncio.sleep(0.3)
        rss0 = rss_kib()
        srv.set_faults(faults)
        t0 = time.monotonic()
        until = t0 + seconds
        models = {a: srv.app.state.services[a].model for a in details}
        tasks = [Mover(c, a, details[a], models[a], seed + k).run(until)
                 for k, a in enumerate(details)]
        tasks += [rbe3001_protocol(c, until, seed + 10 + k) for k in range(2)]
        tasks += [dynamixel_protocol(c, until, seed + 20 + k) for k in range(2)]
        tasks += [subscriber(srv.ws_url, a, until, t) for a in details
                  for _ in range(subscribers_per_arm)]
        rss_marks: list[tuple[float, int]] = []

        async def sample_rss() -> None:  # at each quarter of the run: does memory level off?
            for k in (1, 2, 3, 4):
                await asyncio.sleep(max(0.0, t0 + k * seconds / 4 - time.monotonic()))
                rss_marks.append((time.monotonic() - t0, rss_kib()))

        await asyncio.gather(*tasks, sample_rss())
        elapsed = time.monotonic() - t0
        srv.set_faults(FaultConfig())
        healthy = await _healthy_after(srv, http)
        rss1 = rss_kib()
    stats = {a: dict(s.driver.stats) for a, s in srv.app.state.services.items()}
    return {"tally": t, "elapsed": elapsed, "rss0": rss0, "rss1": rss1, "healthy": healthy,
            "rss_marks": rss_marks,
            "driver_stats": stats, "internal_errors": srv.app.state.internal_errors}


async def _healthy_after(srv: Server, http: httpx.AsyncClient, timeout: float = 10.0) -> bool:
    """Faults off: both links up, link and motion tasks alive, telemetry advancing."""
    deadline = time.monotonic() + timeout
    svcs = srv.app.state.services
    while time.monotonic() < deadline:
        h = (await http.get(f"{API}/health")).json()
        if all(a["state"] == "up" for a in h["arms"].values()) and _ready(srv.app):
            break
        await asyncio.sleep(0.1)
    seq0 = {a: s.hub.latest["seq"] for a, s in svcs.items()}
    await asyncio.sleep(0.3)
    return all(not s.driver._task.done() and not s.motion._task.done()
               and s.driver.link.state.value == "up" and s.hub.latest["seq"] > seq0[a]
               for a, s in svcs.items())


def report(res: dict[str, Any], faults: FaultConfig) -> str:
    t: Tally = res["tally"]
    failed = sum(t.failed.values())
    lines = [
        f"faults: drop {faults.drop:.0%}, corrupt {faults.corrupt:.0%}, latency "
        f"{faults.latency_s * 1000:.0f} ms, link cut every {faults.disconnect_after_s} s for "
        f"{faults.reconnect_after_s} s; {res['elapsed']:.0f} s",
        "",
        f"{'requests sent':34s} {t.sent:8d}",
        f"{'  answered correctly':34s} {t.correct:8d}",
        f"{'  failed with a clear error':34s} {failed:8d}  "
        + ", ".join(f"{k} {v}" for k, v in t.failed.most_common()),
        f"{'  lost (no answer in bound)':34s} {t.lost:8d}",
        f"{'  wrongly answered':34s} {t.wrong:8d}",
        f"{'motions ended':34s} {sum(t.motions.values()):8d}",
        f"{'  done (verified at target)':34s} {t.motions['done']:8d}",
        f"{'  failed with a reason':34s} {t.motions['failed']:8d}  "
        + ", ".join(f"{k} {v}" for k, v in t.motion_codes.most_common()),
        f"{'  stopped':34s} {t.motions['stopped']:8d}",
        f"{'  wrongly reported done':34s} {t.wrongly_done:8d}",
        f"{'  done, checked on final_positions':34s} {t.done_unverified:8d}  (no fresh "
        f"sample within {DONE_READ_BOUND_S:.0f} s of the end)",
        f"{'telemetry samples received':34s} {t.samples:8d}  ({t.ws_messages} messages, "
        f"{t.ws_reconnects} reconnects)",
        f"{'  seq gaps / reported dropped':34s} {t.seq_gaps:8d} / {t.reported_dropped}"
        f"  (unexplained {max(0, t.seq_gaps - t.reported_dropped)}, backwards "
        f"{t.seq_backwards})",
        f"{'  events':34s} " + ", ".join(f"{k} {v}" for k, v in sorted(t.events.items())),
        f"{'memory RSS start / end / delta':34s} {res['rss0'] / 1024:8.1f} / "
        f"{res['rss1'] / 1024:.1f} / {(res['rss1'] - res['rss0']) / 1024:+.1f} MiB",
        f"{'  RSS at each quarter of the run':34s} "
        + " / ".join(f"{kib / 1024:.1f}" for _, kib in res.get("rss_marks", [])) + " MiB",
        f"{'healthy after (links, tasks)':34s} {res['healthy']!s:>8s}",
        f"{'last-resort errors (500s)':34s} {res['internal_errors']:8d}",
        "",
        "requests by kind: " + ", ".join(f"{k} {v}" for k, v in sorted(t.by_kind.items())),
    ]
    for arm, st in res["driver_stats"].items():
        lines.append(f"driver {arm}: " + ", ".join(f"{k} {v}" for k, v in st.items()))
    if t.wrong_examples:
        lines += ["", "examples of lost/wrong:", *("  " + w for w in t.wrong_examples)]
    return "\n".join(lines)


def bad(res: dict[str, Any]) -> int:
    t: Tally = res["tally"]
    return (t.lost + t.wrong + t.wrongly_done + t.seq_backwards + res["internal_errors"]
            + max(0, t.seq_gaps - t.reported_dropped) + (0 if res["healthy"] else 1))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--seconds", type=float, default=60.0)
    p.add_argument("--drop", type=float, default=0.05)
    p.add_argument("--corrupt", type=float, default=0.02)
    p.add_argument("--latency", type=float, default=0.005, help="s")
    p.add_argument("--disconnect-every", type=float, default=10.0, help="s (0: never)")
    p.add_argument("--disconnect-for", type=float, default=0.5, help="s")
    p.add_argument("--seed", type=int, default=1)
    args = p.parse_args(argv)
    faults = FaultConfig(drop=args.drop, corrupt=args.corrupt, latency_s=args.latency,
                         disconnect_after_s=args.disconnect_every or None,
                         reconnect_after_s=args.disconnect_for)
    with serve() as srv:
        res = asyncio.run(soak(srv, args.seconds, faults, args.seed))
    print(report(res, faults))
    n = bad(res)
    print(f"\nRESULT: {'FAIL' if n else 'OK'} ({n} lost, wrong or unexplained)")
    return 1 if n else 0


if __name__ == "__main__":
    raise SystemExit(main())
