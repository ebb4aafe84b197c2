"""The lab's sorting programs end to end (issue 25): examples/sort_colors.py and
examples/angler_fish.py run as a user runs them (subprocesses with `--url`) against a real
server (uvicorn on a loopback port) with its simulated arms, worlds and cameras. A random scene
is laid out through the world route first; the programs find the objects through the camera's
detections only; at the end every object is in the bin of its colour (the world route).

The two run at the same time (different arms). The rbe3001 program calibrates its camera
itself (the tip on table points, found in the frames). The angler's camera is calibrated here
beforehand from its view's own homography, to spare the slow carriages a calibration round
(the same calibration code runs in the rbe3001 program), and its scene has one target per
colour.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np

from app.arms.loading import load_profile
from app.client import ArmClient
from app.sim.camera import SimView
from app.sim.world import World, random_objects
from tests.conftest import make_settings, serve_live

ROOT = Path(__file__).resolve().parent.parent
#: The longest either program may take, s (about 50 s and 60 s on an idle laptop).
TIMEOUT_S = 400


def _objects(arm: str, seed: int, n: int) -> list[dict[str, object]]:
    """`n` objects in three colours at random places of the arm's object region."""
    world = World(load_profile(arm))
    objects = random_objects(world, seed=seed, n=n, colors=("red", "green", "blue"))
    return [{"id": o.id, "kind": o.kind, "color": o.color,
             "position": {"x": o.position[0], "y": o.position[1], "z": 0.0}}
            for o in objects]


def _env() -> dict[str, str]:
    env = {k: v for k, v in os.environ.items()
           if k not in ("ARMSERVER_TOKEN", "ARMSERVER_URL")}
    env["PYTHONPATH"] = str(ROOT)
    return env


def test_sort_colors_and_angler_fish_sort_a_random_scene() -> None:
    with serve_live(make_settings()) as server, ArmClient(server.url, timeout=30.0) as c:
        # four on the rbe3001 (every colour, two for one bin), two on the angler (the two
        # programs run at once; the angler's slower axes set the test's time)
        for arm, seed, n in (("rbe3001", 11, 4), ("angler", 12, 2)):
            bins = [b.model_dump(mode="json") for b in c.world(arm).bins]
            laid = c.set_world(arm, {"objects": _objects(arm, seed, n), "bins": bins})
            assert len(laid.objects) == n and not any(o.held for o in laid.objects)
        view = SimView.default_for(load_profile("angler"))
        hom = view.table_homography()
        pts = [(x, y) for x in (-0.06, 0.06) for y in (0.03, 0.12)]
        pairs = []
        for x, y in pts:
            u, v, w = hom @ np.array([x, y, 1.0])
            pairs.append(((float(u / w), float(v / w)), (x, y, view.table_z)))
        c.calibrate_camera("angler", pairs, arm="angler")

        procs = {name: subprocess.Popen(
            [sys.executable, str(ROOT / "examples" / name), "--url", server.url],
            cwd=ROOT, env=_env(), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
            for name in ("sort_colors.py", "angler_fish.py")}
        outs = {}
        for name, proc in procs.items():
            try:
                outs[name] = proc.communicate(timeout=TIMEOUT_S)[0]
            except subprocess.TimeoutExpired:
                for p in procs.values():
                    p.kill()
                raise
            assert proc.returncode == 0, f"{name} failed:\n{outs[name]}"
        assert "calibrating camera rbe3001" in outs["sort_colors.py"]
        assert "placed 4 object(s)" in outs["sort_colors.py"]
        assert "landed 2 target(s)" in outs["angler_fish.py"]
        for arm in ("rbe3001", "angler"):
            w = c.world(arm)
            bins = {b.color: b for b in w.bins}
            for o in w.objects:
                b = bins[o.color]
                assert not o.held
                assert b.min.x <= o.position.x <= b.max.x, (arm, o)
                assert b.min.y <= o.position.y <= b.max.y, (arm, o)
                assert o.position.z < b.max.z, (arm, o)
