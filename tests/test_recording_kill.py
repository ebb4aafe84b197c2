"""A server killed with SIGKILL in the middle of an episode (a real `armserver serve`
subprocess): the dataset loads with every episode finished before, the killed one absent; the
restarted server finds the dataset and appends to it."""

from __future__ import annotations

import os
import signal
import time
from pathlib import Path

import numpy as np

from tests._http import HTTP
from tests._lerobot import check_dataset
from tests._serve import Served, clean_env, start

API = "/api/v1"


def _serve(data: Path, log: Path) -> Served:
    return start(log, "--log-level", "warning", env=clean_env(ARMSERVER_DATA_DIR=str(data)))


def _record(srv: Served, frames: int, stop: bool = True) -> dict:
    url = srv.url
    r = HTTP.post(f"{url}{API}/recordings/k/episodes", timeout=10)
    assert r.status_code == 201, r.text
    deadline = time.monotonic() + 30
    cur = None
    while True:
        assert time.monotonic() < deadline, \
            f"the episode did not record {frames} frames: {cur}; {srv.tail()}"
        rec = HTTP.get(f"{url}{API}/recordings/k", timeout=5).json()
        cur = rec["current"]
        # (an episode that ended on its own is not waited for)
        assert cur is not None, f"the episode ended: {rec['last_error']}; {srv.tail()}"
        if cur["frames"] >= frames:
            break
        time.sleep(0.05)
    if not stop:
        return cur
    r = HTTP.post(f"{url}{API}/recordings/k/episodes/stop", timeout=60)
    assert r.status_code == 200, r.text
    return r.json()


def test_kill_9_mid_episode_keeps_the_earlier_episodes_and_a_restart_appends(
        tmp_path: Path) -> None:
    log = tmp_path / "server.log"
    srv = _serve(tmp_path, log)
    try:
        url = srv.url
        arms = [a["name"] for a in HTTP.get(f"{url}{API}/arms", timeout=5).json()]
        cams = [c["name"] for c in HTTP.get(f"{url}{API}/cameras", timeout=5).json()][:1]
        r = HTTP.post(f"{url}{API}/recordings", json={"name": "k", "arms": arms,
                                                        "cameras": cams, "fps": 10}, timeout=10)
        assert r.status_code == 201, r.text
        _record(srv, 6)
        done = _record(srv, 4)
        assert done["episodes"] == 2
        _record(srv, 8, stop=False)
        os.kill(srv.proc.pid, signal.SIGKILL)
        srv.proc.wait(timeout=10)
    finally:
        srv.stop()
    root = tmp_path / "recordings" / "k"
    read = check_dataset(root)
    assert [e["length"] for e in read.episodes] == [e["length"] for e in done["episode_list"]]
    assert read.info["total_frames"] == done["frames"]

    srv = _serve(tmp_path, log)
    try:
        listed = HTTP.get(f"{srv.url}{API}/recordings", timeout=5).json()
        assert [(x["id"], x["episodes"]) for x in listed] == [("k", 2)]
        after = _record(srv, 5)
        assert after["episodes"] == 3
        srv.proc.send_signal(signal.SIGTERM)
        srv.ended(20)
    finally:
        srv.stop()
    read = check_dataset(root)
    assert read.info["total_episodes"] == 3
    assert np.array_equal(read.frames["index"], np.arange(after["frames"]))
    assert not any((root / ".partial").glob("*"))
