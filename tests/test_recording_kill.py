"""A server killed with SIGKILL in the middle of an episode (a real `armserver serve`
subprocess): the dataset loads with every episode finished before, the killed one absent; the
restarted server finds the dataset and appends to it."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import httpx
import numpy as np

from tests._lerobot import check_dataset

API = "/api/v1"


def _port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _serve(data: Path, log: Path) -> tuple[subprocess.Popen[str], str]:
    """A server on `data`, its output to the file `log` (a pipe nobody reads while the test
    runs could fill and stop the server's logging thread, and the arm's with it)."""
    port = _port()
    env = {k: v for k, v in os.environ.items() if not k.startswith("ARMSERVER_")}
    env["ARMSERVER_DATA_DIR"] = str(data)
    with log.open("a") as out:
        proc = subprocess.Popen([sys.executable, "-c", "from app.cli import run; run()",
                                 "serve", "--port", str(port), "--log-level", "warning"],
                                env=env, stdout=out, stderr=subprocess.STDOUT, text=True)
    url = f"http://127.0.0.1:{port}"
    deadline = time.monotonic() + 30
    while True:
        assert time.monotonic() < deadline, f"armserver serve did not start: {_tail(log)}"
        assert proc.poll() is None, _tail(log)
        try:
            arms = httpx.get(f"{url}{API}/arms", timeout=2).json()
            if all(not httpx.get(f"{url}{API}/arms/{a['name']}/state", timeout=2).json()["stale"]
                   for a in arms):
                return proc, url
        except httpx.TransportError:
            pass
        time.sleep(0.1)


def _tail(log: Path) -> str:
    """The server's last lines of output, for a failure's message."""
    return "the server said:\n" + "\n".join(log.read_text().splitlines()[-30:])


def _record(url: str, log: Path, frames: int, stop: bool = True) -> dict:
    r = httpx.post(f"{url}{API}/recordings/k/episodes", timeout=10)
    assert r.status_code == 201, r.text
    deadline = time.monotonic() + 30
    cur = None
    while True:
        assert time.monotonic() < deadline, \
            f"the episode did not record {frames} frames: {cur}; {_tail(log)}"
        rec = httpx.get(f"{url}{API}/recordings/k", timeout=5).json()
        cur = rec["current"]
        # (an episode that ended on its own is not waited for)
        assert cur is not None, f"the episode ended: {rec['last_error']}; {_tail(log)}"
        if cur["frames"] >= frames:
            break
        time.sleep(0.05)
    if not stop:
        return cur
    r = httpx.post(f"{url}{API}/recordings/k/episodes/stop", timeout=60)
    assert r.status_code == 200, r.text
    return r.json()


def test_kill_9_mid_episode_keeps_the_earlier_episodes_and_a_restart_appends(
        tmp_path: Path) -> None:
    log = tmp_path / "server.log"
    proc, url = _serve(tmp_path, log)
    try:
        arms = [a["name"] for a in httpx.get(f"{url}{API}/arms", timeout=5).json()]
        cams = [c["name"] for c in httpx.get(f"{url}{API}/cameras", timeout=5).json()][:1]
        r = httpx.post(f"{url}{API}/recordings", json={"name": "k", "arms": arms,
                                                        "cameras": cams, "fps": 10}, timeout=10)
        assert r.status_code == 201, r.text
        _record(url, log, 6)
        done = _record(url, log, 4)
        assert done["episodes"] == 2
        _record(url, log, 8, stop=False)
        os.kill(proc.pid, signal.SIGKILL)
        proc.communicate(timeout=10)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    root = tmp_path / "recordings" / "k"
    read = check_dataset(root)
    assert [e["length"] for e in read.episodes] == [e["length"] for e in done["episode_list"]]
    assert read.info["total_frames"] == done["frames"]

    proc, url = _serve(tmp_path, log)
    try:
        listed = httpx.get(f"{url}{API}/recordings", timeout=5).json()
        assert [(x["id"], x["episodes"]) for x in listed] == [("k", 2)]
        after = _record(url, log, 5)
        assert after["episodes"] == 3
    finally:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.communicate(timeout=20)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.communicate()
    read = check_dataset(root)
    assert read.info["total_episodes"] == 3
    assert np.array_equal(read.frames["index"], np.arange(after["frames"]))
    assert not any((root / ".partial").glob("*"))
