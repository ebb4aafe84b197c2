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

ROOT = Path(__file__).resolve().parent.parent
PY = str(ROOT / ".venv" / "bin" / "python")

#: Serves both simulated devices on TCP (one process), prints the two ports, runs until killed.
SIMS = """
import asyncio, sys
from app.config import load_profile
from app.devices.factory import make_sim_device
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


def cpu_seconds(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def idle_cpu(pid: int, seconds: float) -> float:
    c0, t0 = cpu_seconds(pid), time.monotonic()
    time.sleep(seconds)
    return 100.0 * (cpu_seconds(pid) - c0) / (time.monotonic() - t0)


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
            port = _free_port()
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


def _seq(port: int) -> int:
    import httpx

    r = httpx.get(f"http://127.0.0.1:{port}/api/v1/arms/rbe3001/state", timeout=5)
    return int(r.json()["seq"])


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _num(text: str, after: str) -> float | None:
    if after not in text:
        return None
    return float(text.split(after, 1)[1].split()[0])


def table(out: Path, remote: dict[str, float] | None) -> list[tuple[str, str, str, str, str]]:
    pypot: dict[str, Any] = json.loads((out / "pypot.json").read_text())
    arm: dict[str, Any] = json.loads((out / "armserver.json").read_text())
    idle = _num((out / "armserver-idle.txt").read_text(), "server CPU")
    rtt = json.loads((out / "armserver-rtt.txt").read_text().strip().splitlines()[-1])
    rows: list[tuple[str, str, str, str, str]] = []

    def met(ok: bool) -> str:
        return "met" if ok else "NOT met"

    rows.append(("server CPU, nothing connected (sims in-process)", "2.9 % (README)",
                 f"{idle:.1f} %", "<= 15 %", met(idle is not None and idle <= 15)))
    if remote is not None:
        c = remote["server_cpu_pct"]
        rows.append(("server CPU, nothing connected (sims behind socket://)", "-",
                     f"{c:.1f} % ({remote['rbe3001_samples_per_s']:.0f} rbe3001 samples/s)",
                     "<= 8 %", met(c <= 8)))
    p_raw = [r for r in pypot.get("rest", []) if r["client"] == "raw"]
    a_raw = [r for r in arm.get("rest", []) if r["client"] == "raw"]
    if p_raw and a_raw:
        p, a = max(p_raw, key=lambda r: r["req_per_s"]), a_raw[0]
        ratio = a["req_per_s"] / p["req_per_s"]
        rows.append(("REST state, 50 raw keep-alive clients",
                     f"{p['req_per_s']:,.0f} req/s, p99 {p['lat_ms_p99']} ms",
                     f"{a['req_per_s']:,.0f} req/s, p99 {a['lat_ms_p99']} ms "
                     f"({ratio:.2f}x, {a['errors']} errors)",
                     ">= 1.5x, p99 <= pypot's",
                     met(ratio >= 1.5 and a["lat_ms_p99"] <= p["lat_ms_p99"])))
    for a in arm.get("ws", []):
        p = next((r for r in pypot.get("ws", []) if r["clients"] == a["clients"]), None)
        pv = (f"{p['msgs_per_s_per_client_mean']} msg/s, gap p99 {p['gap_ms_p99']} ms, "
              f"{p['server_cpu_pct']} % CPU") if p else "-"
        ok = a["msgs_per_s_per_client_min"] >= 29 and a["gap_ms_p99"] < 40
        rows.append((f"WebSocket, {a['clients']} clients at 30 msg/s", pv,
                     f"{a['msgs_per_s_per_client_mean']} msg/s (min "
                     f"{a['msgs_per_s_per_client_min']}), gap p99 {a['gap_ms_p99']} ms, "
                     f"{a['server_cpu_pct']} % CPU",
                     "1,000 clients: 30 msg/s, gap p99 < 40 ms" if a["clients"] >= 1000 else "-",
                     met(ok) if a["clients"] >= 1000 else ("ok" if ok else "short")))
    e = rtt["estop_seen_ms"]
    rows.append(("estop to a sample showing it", "-", f"p50 {e['p50']} ms, p99 {e['p99']} ms",
                 "p99 < 3 ms", met(e["p99"] < 3)))
    g = rtt["goal_first_move_ms"]
    pr = pypot.get("rtt") or {}
    rows.append(("Dynamixel goal to the first sample that moved",
                 f"p50 {pr.get('rtt_ms_p50', '-')} ms, p99 {pr.get('rtt_ms_p99', '-')} ms"
                 if pr else "-",
                 f"p50 {g['p50']} ms, p99 {g['p99']} ms ({g['timeouts']} timeouts)",
                 "p99 < 8 ms", met(g["p99"] < 8 and not g["timeouts"])))
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("out", type=Path, help="the harness's output directory")
    ap.add_argument("--no-remote", action="store_true",
                    help="skip the idle measurement with the simulators in their own process")
    a = ap.parse_args(argv)
    remote = None if a.no_remote else remote_idle()
    if remote is not None:
        (a.out / "armserver-remote-idle.json").write_text(json.dumps(remote))
    rows = table(a.out, remote)
    print(f"\nload average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores at the end\n")
    print("| measure | pypot 5.0.2 | armserver | target | |")
    print("|---|---|---|---|---|")
    for r in rows:
        print("| " + " | ".join(r) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
