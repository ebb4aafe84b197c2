"""One sort cycle on the simulator: from asking the camera for a colour to the object lying in
its bin, as examples/sort_colors.py does it (app/sim/world.py, app/sim/camera.py, the camera's
detections route, the planner's moves and the claw).

    python bench/sort_cycle.py [--cycles 5] [--arm rbe3001] [--speed 1.0]

`armserver serve` in a subprocess (simulated arms and cameras). The camera is calibrated first
if it is not (not timed). Each cycle lays out one object at a random place of the table's
object region through the world route (not timed), then times detectColor() + pick + place
(and the look that finds none left) and checks through the world route that it landed. Prints
each cycle and the median; figures, not asserts: run it on a quiet machine.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "examples"))

from _server import server  # noqa: E402
from _sorting import lab_from_world  # noqa: E402

from app.arms.loading import load_profile  # noqa: E402
from app.client import ArmClient  # noqa: E402
from app.sim.world import World, random_objects  # noqa: E402

#: Per arm: the end effector, the objects' height (m), the approach height (m), calibration
#: points (x, y) m (as the examples have them).
ARMS = {
    "rbe3001": ("claw", 0.025, 0.05,
                [(0.12, -0.12), (0.12, 0.12), (0.25, 0.1), (0.25, -0.1), (0.18, 0.0)]),
    "angler": ("magnet", 0.005, 0.02, [(-0.05, 0.05), (0.05, 0.05), (0.05, 0.1), (-0.05, 0.1)]),
}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cycles", type=int, default=5)
    ap.add_argument("--arm", choices=list(ARMS), default="rbe3001")
    ap.add_argument("--speed", type=float, default=1.0)
    a = ap.parse_args()
    effector, height, approach, points = ARMS[a.arm]
    layouts = random_objects(World(load_profile(a.arm)), seed=42, n=max(1, a.cycles),
                             colors=("red", "green", "blue"))
    times: list[float] = []
    with server() as srv, ArmClient(srv.url, timeout=120.0) as c, c.hold_lease(a.arm):
        lab = lab_from_world(c, a.arm, a.arm, effector, height, a.speed, approach)
        if not c.camera(a.arm).calibrated:
            t = time.perf_counter()
            lab.calibrate(points, lab.table_z + (0.0 if effector == "claw" else 0.001))
            print(f"calibration (not counted): {time.perf_counter() - t:.1f} s")
        bins = [b.model_dump(mode="json") for b in c.world(a.arm).bins]
        for i, o in enumerate(layouts[:a.cycles]):
            c.set_world(a.arm, {"objects": [{"id": o.id, "kind": o.kind, "color": o.color,
                                             "position": {"x": o.position[0],
                                                          "y": o.position[1], "z": 0.0}}],
                                "bins": bins})
            lab.fresh_frame()  # a frame of the new scene (not timed)
            t = time.perf_counter()
            placed = lab.run([o.color])
            dt = time.perf_counter() - t
            landed = c.world(a.arm).objects[0]
            b = next(b for b in lab.bins if b.color == o.color)
            ok = placed == 1 and b.holds(landed.position.x, landed.position.y, 0.0)
            times.append(dt)
            print(f"cycle {i + 1}: {o.color:<5} from ({o.position[0] * 1000:+6.1f}, "
                  f"{o.position[1] * 1000:+6.1f}) mm: {dt:6.2f} s "
                  f"{'in its bin' if ok else 'NOT in its bin'}")
    print(f"{a.arm}: one sort cycle (detect, pick, place) median {statistics.median(times):.2f} s"
          f" over {len(times)}, min {min(times):.2f} s, max {max(times):.2f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
