"""armserver against pypot, side by side: the issue-12 table as ratios, from one run.

`make bench-peers` runs the shared harness (`../shared/peers/run.sh OUT`: pypot 5.0.2 and
armserver, each pinned to CPU 0 with the load on CPU 1), then this script, which adds the one
figure the harness does not take (the server's idle CPU with the simulators in their own
process behind socket:// links) and prints the table:

    python bench/peers.py OUT            (OUT: the harness's output directory)
    python bench/peers.py OUT --no-remote (skip the own-process measurement)

Figures on a shared 2-core machine are noisy: compare the ratios of one run.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import _machine
from _server import free_port

ROOT = Path(__file__).resolve().parent.parent
PY = str(ROOT / ".venv" / "bin" / "python")

#: Serves both simulated devices on TCP (one process), prints the two ports, runs until killed.
SIMS = """
import asyncio, sys
from app.arms.loading import load_profile
from app.device.factory import make_sim_device
from app.sim.serve import serve_tcp
async def main():
    servers = [await serve_tcp(make_sim_device(load_profile(n))) for n in ("rbe3001", "angler")]
    print(" ".join(str(s.port) for s in servers), flush=True)
    await asyncio.Event().wait()
asyncio.run(main())
"""

CONFIG = """
[[arms]]
profile = "rbe3001"
[arms.link]
kind = "serial"
address = "socket://127.0.0.1:{rbe}"

[[arms]]
profile = "angler"
[arms.link]
kind = "serial"
address = "socket://127.0.0.1:{angler}"
"""


def idle_cpu(pid: int, seconds: float) -> float:
    c0, t0 = _machine.ticks_cpu_s(pid), time.monotonic()
    time.sleep(seconds)
    return 100.0 * (_machine.ticks_cpu_s(pid) - c0) / (time.monotonic() - t0)


def remote_idle(seconds: float = 5.0) -> dict[str, float]:
    """Idle CPU of the server (CPU 0) with both simulators in their own process (CPU 1)."""
    import httpx

    sims = subprocess.Popen(["taskset", "-c", "1", PY, "-c", SIMS], cwd=ROOT,
                            stdout=subprocess.PIPE, text=True)
    server = None
    try:
        assert sims.stdout is not None
        rbe, angler = sims.stdout.readline().split()
        with tempfile.TemporaryDirectory() as tmp:
            cfg = Path(tmp) / "arms.toml"
            cfg.write_text(CONFIG.format(rbe=rbe, angler=angler))
            port = free_port()
            server = subprocess.Popen(
                ["taskset", "-c", "0", str(ROOT / ".venv" / "bin" / "armserver"), "serve",
                 "--config", str(cfg), "--port", str(port)], cwd=ROOT,
                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            url = f"http://127.0.0.1:{port}/api/v1/health"
            deadline = time.monotonic() + 60
            while time.monotonic() < deadline:
                try:
                    if httpx.get(url, timeout=1).json().get("status") == "ok":
                        break
                except (httpx.HTTPError, ValueError):
                    pass
                time.sleep(0.5)
            else:
                raise RuntimeError("the server with socket:// simulators did not come up")
            time.sleep(2)
            rate0 = _seq(port)
            t0 = time.monotonic()
            server_cpu = idle_cpu(server.pid, seconds)
            sims_cpu_hint = idle_cpu(sims.pid, 1.0)
            rate = (_seq(port) - rate0) / (time.monotonic() - t0)
            return {"server_cpu_pct": round(server_cpu, 1), "sims_cpu_pct": round(sims_cpu_hint, 1),
                    "rbe3001_samples_per_s": round(rate, 1)}
    finally:
        for p in (server, sims):
            if p is not None:
                p.terminate()
                p.wait(10)


def _telemetry(base: str) -> dict[str, int]:
    """The rbe3001's telemetry counts (`ArmDetail.telemetry`): published, dropped."""
    import httpx

    return dict(httpx.get(f"{base}/api/v1/arms/rbe3001", timeout=10).json()["telemetry"])


def _seq(port: int) -> int:
    import httpx

    r = httpx.get(f"http://127.0.0.1:{port}/api/v1/arms/rbe3001/state", timeout=5)
    return int(r.json()["seq"])


def _num(text: str, after: str) -> float | None:
    if after not in text:
        return None
    return float(text.split(after, 1)[1].split()[0])


def parse(path: Path) -> dict[str, Any]:
    """The figures of a measure.py run from its printed lines (a partial run still counts)."""
    out: dict[str, Any] = {"ws": [], "rest": []}
    if not path.exists():
        return out
    for line in path.read_text().splitlines():
        kind, _, body = line.partition(" ")
        if kind in ("WS", "REST"):
            out[kind.lower()].append(json.loads(body))
        elif kind == "RTT":
            out["rtt"] = json.loads(body)
        elif kind == "DROPPED":
            out["dropped"] = json.loads(body)
    return out


def _measure(harness: Path, venv: Path) -> list[str]:
    return ["taskset", "-c", "1", str(venv / "bin" / "python"), str(harness / "measure.py"),
            "--duration", os.environ.get("DUR", "8")]


def run_armserver(out: Path, harness: Path, venv: Path, ws_steps: str, rest: bool,
                  rtt: bool, idle: bool) -> None:
    """armserver's side of run.sh (same commands, same pinning), for what it did not measure:
    run.sh stops at its first failure (pypot's WebSocket steps can time out under load), and
    it does not go to 1,000 clients."""
    if not (ws_steps or rest or rtt or idle):
        return
    port = free_port()
    server = subprocess.Popen(["taskset", "-c", "0", str(ROOT / ".venv" / "bin" / "armserver"),
                               "serve", "--port", str(port)], cwd=ROOT,
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    base = f"http://127.0.0.1:{port}"
    try:
        _wait_ok(base)
        time.sleep(2)
        if idle:
            c = idle_cpu(server.pid, 5.0)
            (out / "armserver-idle.txt").write_text(
                f"IDLE  armserver server CPU {c:.1f} % of a core (both simulated arms polled, "
                "no clients)\n")
        only = ",".join(k for k, on in (("ws", bool(ws_steps)), ("rest", rest)) if on)
        if only:
            cmd = _measure(harness, venv) + [
                "--server-pid", str(server.pid), "--http", base,
                "--ws", f"ws://127.0.0.1:{port}/api/v1/arms/rbe3001/telemetry?rate=30",
                "--ws-clients", ws_steps or "1", "--only", only,
                "--state-route", "/api/v1/arms/rbe3001/state"]
            before = _telemetry(base)
            with open(out / "armserver-extra.txt", "a") as f:
                subprocess.run(cmd, stdout=f, check=False)
                after = _telemetry(base)
                # every client got every sample: none lost to a backlog bound (the server's
                # own count; the harness counts messages, not samples)
                f.write("DROPPED " + json.dumps({
                    "clients": ws_steps, "published": after["published"] - before["published"],
                    "dropped": after["dropped"] - before["dropped"]}) + "\n")
        if rtt:
            with open(out / "armserver-rtt.txt", "w") as f:
                subprocess.run(["taskset", "-c", "1", str(venv / "bin" / "python"),
                                str(harness / "rtt_armserver.py"), base, "200"],
                               stdout=f, check=False)
    finally:
        server.terminate()
        server.wait(10)


def run_pypot(out: Path, harness: Path, venv: Path, only: str) -> None:
    """pypot's side of run.sh for the parts (`only`: rest, rtt) it did not reach: run.sh stops
    at pypot's first failed WebSocket step."""
    hp, wp = free_port(), free_port()
    with open(out / "pypot-extra.log", "w") as log:
        server = subprocess.Popen(["taskset", "-c", "0", str(venv / "bin" / "python"),
                                   "pypot_server.py", str(hp), str(wp)], cwd=harness,
                                  stdout=log, stderr=subprocess.STDOUT)
    try:
        deadline = time.monotonic() + 60
        while "READY" not in (out / "pypot-extra.log").read_text():
            if time.monotonic() > deadline:
                raise RuntimeError("pypot did not come up")
            time.sleep(0.5)
        cmd = _measure(harness, venv) + ["--server-pid", str(server.pid),
                                          "--http", f"http://127.0.0.1:{hp}",
                                          "--ws", f"ws://127.0.0.1:{wp}/", "--only", only]
        with open(out / "pypot-extra.txt", "a") as f:
            subprocess.run(cmd, stdout=f, check=False)
    finally:
        server.terminate()
        server.wait(10)


def _wait_ok(base: str) -> None:
    import httpx

    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        try:
            if httpx.get(base + "/api/v1/health", timeout=1).status_code == 200:
                return
        except httpx.HTTPError:
            pass
        time.sleep(0.5)
    raise RuntimeError(f"armserver at {base} did not come up")


def table(out: Path, remote: dict[str, float] | None) -> list[tuple[str, str, str, str, str]]:
    pypot = parse(out / "pypot.txt")
    p_extra = parse(out / "pypot-extra.txt")
    pypot["rest"] = pypot["rest"] or p_extra["rest"]
    pypot.setdefault("rtt", p_extra.get("rtt"))
    arm = parse(out / "armserver.txt")
    extra = parse(out / "armserver-extra.txt")
    arm["ws"] += [w for w in extra["ws"] if w["clients"] not in {a["clients"] for a in arm["ws"]}]
    arm["rest"] = arm["rest"] or extra["rest"]
    idle_file = out / "armserver-idle.txt"
    idle = _num(idle_file.read_text(), "server CPU") if idle_file.exists() else None
    rtt_file = out / "armserver-rtt.txt"
    rtt = json.loads(rtt_file.read_text().strip().splitlines()[-1]) if rtt_file.exists() else {}
    rows: list[tuple[str, str, str, str, str]] = []

    def met(ok: bool) -> str:
        return "met" if ok else "NOT met"

    if idle is not None:
        rows.append(("server CPU, nothing connected (sims in-process)", "2.9 % (README)",
                     f"{idle:.1f} %", "<= 15 %", met(idle <= 15)))
    if remote is not None:
        c = remote["server_cpu_pct"]
        rows.append(("server CPU, nothing connected (sims behind socket://)", "-",
                     f"{c:.1f} % ({remote['rbe3001_samples_per_s']:.0f} rbe3001 samples/s)",
                     "<= 8 %", met(c <= 8)))
    p_raw = [r for r in pypot["rest"] if r["client"] == "raw"]
    a_raw = [r for r in arm["rest"] if r["client"] == "raw"]
    if p_raw and a_raw:
        p, a = max(p_raw, key=lambda r: r["req_per_s"]), a_raw[0]
        ratio = a["req_per_s"] / p["req_per_s"]
        rows.append(("REST state, 50 raw keep-alive clients",
                     f"{p['req_per_s']:,.0f} req/s, p99 {p['lat_ms_p99']} ms",
                     f"{a['req_per_s']:,.0f} req/s, p99 {a['lat_ms_p99']} ms "
                     f"({ratio:.2f}x, {a['errors']} errors)",
                     ">= 1.5x, p99 <= pypot's",
                     met(ratio >= 1.5 and a["lat_ms_p99"] <= p["lat_ms_p99"])))
    for a in sorted(arm["ws"], key=lambda r: r["clients"]):
        p = next((r for r in pypot["ws"] if r["clients"] == a["clients"]), None)
        pv = (f"{p['msgs_per_s_per_client_mean']} msg/s, gap p99 {p['gap_ms_p99']} ms, "
              f"{p['server_cpu_pct']} % CPU") if p else "-"
        ok = a["msgs_per_s_per_client_min"] >= 29 and a["gap_ms_p99"] < 40
        big = a["clients"] >= 1000
        lost = ""
        if big and "dropped" in extra:  # the server's count over the extra steps
            d = extra["dropped"]
            ok = ok and d["dropped"] == 0
            lost = f", {d['dropped']} of {d['published']:,} samples lost"
        rows.append((f"WebSocket, {a['clients']} clients at 30 msg/s", pv,
                     f"{a['msgs_per_s_per_client_mean']} msg/s (min "
                     f"{a['msgs_per_s_per_client_min']}), gap p99 {a['gap_ms_p99']} ms, "
                     f"{a['server_cpu_pct']} % CPU{lost}",
                     "every sample, gap p99 < 40 ms" if big else "-",
                     met(ok) if big else ("ok" if ok else "short")))
    if "estop_seen_ms" in rtt:
        e = rtt["estop_seen_ms"]
        rows.append(("estop to a sample showing it", "-",
                     f"p50 {e['p50']} ms, p99 {e['p99']} ms", "p99 < 3 ms", met(e["p99"] < 3)))
    if "goal_first_move_ms" in rtt:
        g = rtt["goal_first_move_ms"]
        pr = pypot.get("rtt") or {}
        rows.append(("Dynamixel goal to the first sample that moved",
                     f"goal seen p50 {pr['rtt_ms_p50']} ms, p99 {pr['rtt_ms_p99']} ms"
                     if pr else "-",
                     f"p50 {g['p50']} ms, p99 {g['p99']} ms ({g['timeouts']} timeouts)",
                     "p99 < 8 ms", met(g["p99"] < 8 and not g["timeouts"])))
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("out", type=Path, help="the harness's output directory")
    ap.add_argument("--harness", type=Path, default=ROOT.parent / "shared" / "peers")
    ap.add_argument("--venv", type=Path, default=Path(os.environ.get(
        "PEERS_VENV", Path.home() / ".cache" / "armserver-peers" / "venv")))
    ap.add_argument("--clients", default="1000",
                    help="WebSocket steps to measure on armserver beyond the harness's")
    ap.add_argument("--no-remote", action="store_true",
                    help="skip the idle measurement with the simulators in their own process")
    a = ap.parse_args(argv)
    a.out.mkdir(parents=True, exist_ok=True)
    arm = parse(a.out / "armserver.txt")
    extra = parse(a.out / "armserver-extra.txt")
    done = {w["clients"] for w in arm["ws"] + extra["ws"]}
    wanted = [int(n) for n in a.clients.split(",") if n]
    if not (a.out / "armserver.txt").exists():  # run.sh stopped before armserver's turn
        wanted = sorted({1, 10, 100, 300, *wanted})
    rtt_file = a.out / "armserver-rtt.txt"
    run_armserver(a.out, a.harness, a.venv,
                  ws_steps=",".join(str(n) for n in wanted if n not in done),
                  rest=not (arm["rest"] or extra["rest"]),
                  rtt=not (rtt_file.exists() and "goal_first_move_ms" in rtt_file.read_text()),
                  idle=not (a.out / "armserver-idle.txt").exists())
    pypot = parse(a.out / "pypot.txt")
    p_extra = parse(a.out / "pypot-extra.txt")
    only = ",".join(k for k, missing in (("rest", not (pypot["rest"] or p_extra["rest"])),
                                         ("rtt", "rtt" not in pypot and "rtt" not in p_extra))
                    if missing)
    if only:
        run_pypot(a.out, a.harness, a.venv, only)
    remote = None if a.no_remote else remote_idle()
    if remote is not None:
        (a.out / "armserver-remote-idle.json").write_text(json.dumps(remote))
    rows = table(a.out, remote)
    print(f"\nat the end: {_machine.describe()}\n")
    print("| measure | pypot 5.0.2 | armserver | target | |")
    print("|---|---|---|---|---|")
    for r in rows:
        print("| " + " | ".join(r) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
