"""README "Teleoperation and replay", the block after `<!-- README-TELEOP-BY-HAND -->`, run as
written (in a shell, on a free port instead of 8000): `armserver serve` on the two simulated
OpenManipulator-X arms, the world's hand taking hold of the leader, `armserver teleop
--free-leader --load-supported` in the background, the hand moving the leader by curl, the
follower where the hand put the leader, and Ctrl-C ending the CLI with exit code 0."""

from __future__ import annotations

import json
import os
import re
import shlex
import signal
import subprocess
import sys
import threading
import urllib.request
from pathlib import Path
from typing import Any

import numpy as np
from _serve import free_port
from _wait import wait_until

ROOT = Path(__file__).resolve().parents[1]
MARKER = "<!-- README-TELEOP-BY-HAND -->"
TOL = 8 * 2 * np.pi / 4096


def readme_block(marker: str = MARKER) -> list[str]:
    """The commands of the block after `marker`: continuation lines joined, trailing comments
    dropped."""
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    after = text[text.index(marker):]
    body = after.split("```sh\n", 1)[1].split("```", 1)[0]
    joined = re.sub(r"\\\n\s*", "", body)
    return [re.sub(r"\s+#\s.*$", "", ln).strip() for ln in joined.splitlines() if ln.strip()]


def local(cmd: str, port: int) -> str:
    """The command on this port, `armserver` as this interpreter's `python -m app.cli`."""
    cmd = cmd.replace("localhost:8000", f"127.0.0.1:{port}")
    if cmd.startswith("armserver "):
        cmd = f"{shlex.quote(sys.executable)} -m app.cli " + cmd[len("armserver "):]
        cmd += f" --port {port}" if " serve " in cmd else f" --url http://127.0.0.1:{port}"
    return cmd


class Background:
    """A command run in the background (`&`), its output lines read as they come."""

    def __init__(self, cmd: str, env: dict[str, str]) -> None:
        self.proc = subprocess.Popen(shlex.split(cmd), cwd=ROOT, env=env, text=True,
                                     stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
        self.lines: list[str] = []
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for ln in self.proc.stdout:
            self.lines.append(ln.rstrip("\n"))

    def stop(self, sig: int) -> int:
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
        return self.proc.wait(timeout=30)


def stop_all(jobs: list[Background]) -> None:
    """End the background commands, the last started first (SIGTERM, then SIGKILL)."""
    for job in reversed(jobs):
        try:
            job.stop(signal.SIGTERM)
        except subprocess.TimeoutExpired:
            job.proc.kill()


def healthy(port: int) -> bool:
    try:
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/api/v1/health", timeout=1) as r:
            return bool(r.status == 200)
    except OSError:
        return False


def test_the_readme_block_runs_as_written() -> None:
    cmds = readme_block()
    assert [c.split()[0] for c in cmds] == ["armserver", "curl", "armserver", "curl", "curl",
                                            "curl"]
    port = free_port()
    env = {k: v for k, v in os.environ.items()
           if not k.startswith("ARMSERVER_") or k == "ARMSERVER_DATA_DIR"}
    jobs: list[Background] = []
    try:
        goals = []
        last: Any = None
        for cmd in cmds:
            run = local(cmd.rstrip("&").strip(), port)
            if cmd.endswith("&"):
                job = Background(run, env)
                jobs.append(job)
                if " serve " in run:
                    wait_until(lambda: healthy(port) or job.proc.poll() is not None,
                               timeout=30, what="the server up")
                    assert job.proc.poll() is None, "\n".join(job.lines)
                else:
                    wait_until(lambda job=job: any(ln.startswith("teleop t")
                                                   for ln in job.lines)
                               or job.proc.poll() is not None, timeout=60,  # a start
                               what="the session started")  # on a busy machine
                    assert job.proc.poll() is None, "\n".join(job.lines)
                    assert "leader by hand" in job.lines[0], job.lines
                continue
            out = subprocess.run(run, shell=True, cwd=ROOT, env=env, capture_output=True,
                                 text=True, timeout=60)
            assert out.returncode == 0, (run, out.stderr)
            last = json.loads(out.stdout)
            if "/world/hand" in run:
                assert last["moving"] is False, last
                goals.append(last["positions"])

        def follower_there() -> bool:
            out = subprocess.run(local(cmds[-1], port), shell=True, cwd=ROOT, env=env,
                                 capture_output=True, text=True, timeout=60)
            return bool(np.allclose(json.loads(out.stdout)["positions"], goals[-1], atol=TOL))
        # the hold (where the leader was: nothing moved), then the two moves
        assert len(goals) == 3 and last["positions"] is not None
        wait_until(follower_there, what="the follower where the hand put the leader")
        teleop = jobs[1]
        wait_until(lambda: any(ln.startswith("running") and "latency p50" in ln
                               for ln in teleop.lines), what="a line of figures")
        assert teleop.stop(signal.SIGINT) == 0, "\n".join(teleop.lines)
        assert any(ln.startswith("stopped: stopped by") for ln in teleop.lines), teleop.lines
    finally:
        stop_all(jobs)
