"""Teleoperation between two simulated OpenManipulator-X arms (config/teleop_omx.toml): the
rate a session holds and the latency from a leader sample to the follower's command, at each
rate asked, while the leader sweeps back and forth under planned moves.

    python bench/teleop.py [--seconds 5] [--rates 30,50,100]

Runs `armserver serve --config config/teleop_omx.toml` in a subprocess on a free loopback
port (the server's figures are its own) and prints, per rate: achieved Hz, latency p50 and
p99 (ms, as GET /api/v1/teleop reports them), commands, holds, and how far the follower ended
from the leader (rad, largest joint). Figures depend on the machine and what else runs on it:
quote them from a quiet machine.
"""

from __future__ import annotations

import argparse
import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import httpx

ROOT = Path(__file__).resolve().parent.parent
CONFIG = ROOT / "config" / "teleop_omx.toml"
API = "/api/v1"
POSES = ([0.6, -0.5, 0.4, 0.7], [-0.6, -0.2, 0.1, 0.4])


def serve() -> tuple[subprocess.Popen[bytes], str]:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    env = {k: v for k, v in os.environ.items() if not k.startswith("ARMSERVER_")}
    proc = subprocess.Popen(
        [sys.executable, "-c", "from app.cli import run; run()", "serve", "--config",
         str(CONFIG), "--port", str(port), "--log-level", "warning"],
        cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    url = f"http://127.0.0.1:{port}"
    deadline = time.monotonic() + 30.0
    while time.monotonic() < deadline:
        try:
            if httpx.get(url + API + "/health", timeout=1.0).json()["status"] == "ok":
                return proc, url
        except (httpx.HTTPError, KeyError, ValueError):
            pass
        time.sleep(0.1)
    proc.kill()
    raise RuntimeError("the server did not become healthy")


def run(c: httpx.Client, rate: float, seconds: float) -> dict[str, object]:
    r = c.post(f"{API}/teleop", json={"leader": "leader", "follower": "follower",
                                      "rate_hz": rate})
    r.raise_for_status()
    sid = r.json()["id"]
    end = time.monotonic() + seconds
    k = 0
    while time.monotonic() < end:
        c.post(f"{API}/arms/leader/move/joints",
               json={"positions": POSES[k % 2], "wait": True}).raise_for_status()
        k += 1
    figures = next(t for t in c.get(f"{API}/teleop").json() if t["id"] == sid)
    time.sleep(0.5)  # the follower's last steps
    lq = c.get(f"{API}/arms/leader/state").json()["positions"]
    fq = c.get(f"{API}/arms/follower/state").json()["positions"]
    c.delete(f"{API}/teleop/{sid}").raise_for_status()
    figures["end_error"] = max(abs(a - b) for a, b in zip(lq, fq, strict=True))
    figures["moves"] = k
    return dict(figures)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=5.0, help="per rate")
    ap.add_argument("--rates", default="30,50,100", help="rates to run, Hz, comma separated")
    args = ap.parse_args()
    proc, url = serve()
    try:
        with httpx.Client(base_url=url, timeout=60.0) as c:
            print(f"{'rate':>6} {'achieved':>9} {'p50 ms':>7} {'p99 ms':>7} {'commands':>9} "
                  f"{'holds':>6} {'moves':>6} {'end error rad':>14}")
            for rate in (float(x) for x in args.rates.split(",")):
                f = run(c, rate, args.seconds)
                lat = f["latency_ms"] or {"p50": float("nan"), "p99": float("nan")}
                assert isinstance(lat, dict)
                print(f"{rate:6.0f} {f['achieved_hz']:9.1f} {lat['p50']:7.2f} {lat['p99']:7.2f} "
                      f"{f['commands']:9d} {f['holds']:6d} {f['moves']:6d} "
                      f"{f['end_error']:14.5f}")
    finally:
        proc.terminate()
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()


if __name__ == "__main__":
    main()
