"""`armserver teleop` against a real uvicorn server of two simulated OpenManipulator-X arms
(config/teleop_omx.toml): run as a process, it takes the follower's lease, starts the session,
prints its figures, the follower follows the leader, and Ctrl-C (SIGINT) stops the session
(the follower holding, its lease released) with exit code 0; refusals exit 1 with the code on
stderr."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path

import httpx
import numpy as np
import pytest
from _wait import wait_until

from app.cli import main
from tests._serve import clean_env
from tests.conftest import LiveServer, make_settings, serve_live

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "config" / "teleop_omx.toml"
TOL = 8 * 2 * np.pi / 4096
GOAL = [0.5, -0.4, 0.3, 0.6]


@pytest.fixture()
def pair() -> Iterator[LiveServer]:
    with serve_live(make_settings(config=str(CONFIG))) as live:
        yield live


class Lines:
    """A process's output lines, read as they come by a thread."""

    def __init__(self, stream: object) -> None:
        self.lines: list[str] = []
        self._thread = threading.Thread(target=self._read, args=(stream,), daemon=True)
        self._thread.start()

    def _read(self, stream: object) -> None:
        for ln in stream:  # type: ignore[attr-defined]
            self.lines.append(ln.rstrip("\n"))

    def text(self) -> str:
        return "\n".join(self.lines)


def test_teleop_from_the_shell_until_ctrl_c(pair: LiveServer, tmp_path: Path) -> None:
    leader = pair.app.state.services["leader"]
    follower = pair.app.state.services["follower"]
    env = clean_env()
    err = tmp_path / "teleop.err"  # (a file: an unread pipe fills and blocks the CLI)
    with err.open("wb") as errors:
        proc = subprocess.Popen(
            [sys.executable, "-c", "from app.cli import run; run()", "teleop", "--leader",
             "leader", "--follower", "follower", "--rate", "50", "--every", "0.2", "--url",
             pair.url], cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=errors, text=True)
    out = Lines(proc.stdout)
    try:
        wait_until(lambda: any(ln.startswith("teleop t") for ln in out.lines) or
                   proc.poll() is not None, 60.0,  # a process's start on a busy machine
                   what="the session started")
        assert proc.poll() is None, err.read_text(errors="replace")
        assert "leader -> follower at 50 Hz (joints)" in out.text()
        with httpx.Client(base_url=pair.url, timeout=30) as c:
            # the follower's lease is the CLI's: a move of it from here is refused
            r = c.post("/api/v1/arms/follower/move/joints", json={"positions": GOAL})
            assert r.status_code == 409 and r.json()["code"] == "leased", r.text
            r = c.post("/api/v1/arms/leader/move/joints", json={"positions": GOAL,
                                                                  "wait": True})
            assert r.status_code == 200, r.text
            wait_until(lambda: np.allclose(follower.positions, GOAL, atol=TOL),
                       what="the follower at the leader's goal")
            wait_until(lambda: any(ln.startswith("running") and " Hz  latency p50 " in ln
                                   and "commands" in ln for ln in out.lines),
                       what="a line of figures")
            proc.send_signal(signal.SIGINT)
            assert proc.wait(timeout=30) == 0, err.read_text(errors="replace")
            wait_until(lambda: any(ln.startswith("stopped: stopped by") for ln in out.lines),
                       what="the stop said")
            sessions = c.get("/api/v1/teleop").json()
            assert [t["status"] for t in sessions] == ["ended"]
            # the follower holds where it is, and its lease went with the CLI
            here = np.array(follower.positions)
            r = c.post("/api/v1/arms/leader/move/joints", json={"positions": [0.0, -0.2, 0.2,
                                                                              0.4],
                                                                  "wait": True})
            assert r.status_code == 200, r.text
            np.testing.assert_allclose(follower.positions, here, atol=TOL)
            r = c.post("/api/v1/arms/follower/move/joints", json={"positions": GOAL})
            assert r.status_code == 202, r.text
        assert leader.positions is not None
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(timeout=10)


def test_teleop_refusals_from_the_shell(pair: LiveServer,
                                        capsys: pytest.CaptureFixture[str]) -> None:
    url = ["--url", pair.url]
    rc = main(["teleop", "--leader", "nope", "--follower", "follower", *url])
    _out, err = capsys.readouterr()
    assert rc == 1 and json.loads(err)["code"] == "unknown_arm"
    rc = main(["teleop", "--leader", "leader", "--follower", "follower", "--rate", "500",
               *url])
    _out, err = capsys.readouterr()
    assert rc == 1 and json.loads(err)["code"] == "invalid_request"
    rc = main(["teleop", "--leader", "leader", "--follower", "leader", *url])
    _out, err = capsys.readouterr()
    assert rc == 1 and json.loads(err)["code"] == "invalid_request"
