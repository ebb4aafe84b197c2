"""README's demonstration shown by hand, the block after `<!-- README-DEMO-BY-HAND -->`, run as
written (in a shell, on a free port instead of 8000): `armserver serve` on the two simulated
OpenManipulator-X arms, the world's hand holding the leader, `armserver call leader torque off
--load-supported`, a recording's episode while the hand moves the arm, and the torque on
again. The episode is read as LeRobot's: its state and its action both end where the hand left
the arm (the action is not the goal the servos held before the torque went off)."""

from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path
from typing import Any

import numpy as np
from _serve import free_port
from _wait import wait_until
from test_teleop_readme import ROOT, Background, healthy, local, readme_block, stop_all

from tests._lerobot import check_dataset

MARKER = "<!-- README-DEMO-BY-HAND -->"
TOL = 8 * 2 * np.pi / 4096  # the XM430's settle tolerance (8 ticks), rad


def test_the_readme_block_runs_as_written(tmp_path: Path) -> None:
    cmds = readme_block(MARKER)
    assert [c.split()[0] for c in cmds] == ["armserver", "curl", "armserver", "curl", "curl",
                                            "curl", "curl", "armserver"]
    port = free_port()
    env = {k: v for k, v in os.environ.items() if not k.startswith("ARMSERVER_")}
    env["ARMSERVER_DATA_DIR"] = str(tmp_path / "data")
    jobs: list[Background] = []
    answers: list[Any] = []
    try:
        for cmd in cmds:
            run = local(cmd.rstrip("&").strip(), port)
            if cmd.endswith("&"):
                job = Background(run, env)
                jobs.append(job)
                wait_until(lambda: healthy(port) or job.proc.poll() is not None,
                           timeout=30, what="the server up")
                assert job.proc.poll() is None, "\n".join(job.lines)
                continue
            out = subprocess.run(run, shell=True, cwd=ROOT, env=env, capture_output=True,
                                 text=True, timeout=60)
            assert out.returncode == 0, (run, out.stdout, out.stderr)
            answers.append(json.loads(out.stdout))
    finally:
        stop_all(jobs)
    held, off, _made, _started, moved, stopped, on = answers
    assert held["moving"] is False and off == {"arm": "leader", "on": False}
    assert moved == {"positions": [0.4, -0.3, 0.2, 0.5], "speed": 0.8, "moving": False}
    assert on == {"arm": "leader", "on": True}
    read = check_dataset(Path(stopped["path"]))
    state = read.frames["observation.state"][:, :4].astype(float)
    action = read.frames["action"][:, :4].astype(float)
    # from where the hand held the arm to where it left it, at the hand's speed; the last frame
    # at most one period before the stop (the hand had arrived before it)
    bound = 0.8 / 25 + 2 * TOL
    assert float(np.max(np.abs(state[-1] - moved["positions"]))) < bound, state[-1]
    assert float(np.max(np.abs(action[-1] - moved["positions"]))) < bound, action[-1]
    assert float(np.max(np.abs(action - state))) < bound
    assert float(np.max(np.abs(state[0] - held["positions"]))) < bound
