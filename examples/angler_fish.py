"""Angler fishing: land every magnetic target in the bin of its colour (issue 25).

The angler's lab with sort_colors.py's program (`nextColor()`, `detectColor()` through the
camera's detections route): the magnet on the winch is lowered onto the largest target of the
colour until it touches its top (a target sticks to the magnet), raised, carried over that
colour's bin and lowered into it, where the bin's rim strips the target off. The camera is
calibrated first if it is not (the magnet on four table points, its mark found in the frames).

Against `make run` (the simulated angler, its world and its simulated camera):

    python examples/angler_fish.py [--url http://127.0.0.1:8000]

The x and y carriages are slow (ball screws on MX-28s: a few mm/s), so a landing takes a while.
"""

from __future__ import annotations

import os
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from _common import fail, log, parser  # noqa: E402
from _sorting import check_sorted, lab_from_world  # noqa: E402

from app.client import ArmClient, ArmServerError  # noqa: E402

ARM = "angler"
#: A target's thickness, m (the lab's steel washers).
TARGET_HEIGHT = 0.005
#: Height the magnet is raised to above a target or a bin's rim, m (the winch is quick).
APPROACH = 0.02
#: Table points (x, y) m the magnet visits to calibrate the camera (near the targets, so the
#: carriages travel little).
CALIBRATION = [(-0.05, 0.05), (0.05, 0.05), (0.05, 0.1), (-0.05, 0.1)]


def main(argv: list[str] | None = None) -> int:
    p = parser(__doc__.splitlines()[0])
    p.add_argument("--arm", default=ARM)
    p.add_argument("--camera", default=None, help="camera name (default: the arm's name)")
    p.add_argument("--colors", nargs="+", default=None,
                   help="colours to land (default: every bin's colour)")
    p.add_argument("--recalibrate", action="store_true")
    p.add_argument("--speed", type=float, default=1.0, help="fraction of the arm's limits")
    a = p.parse_args(argv)
    camera = a.camera or a.arm
    with ArmClient(a.url, token=a.token, timeout=120.0) as c:
        try:
            if c.arm(a.arm).estop:
                fail("the emergency stop is latched; release it first")
            with c.hold_lease(a.arm):
                lab = lab_from_world(c, a.arm, camera, "magnet", TARGET_HEIGHT, a.speed,
                                     APPROACH)
                log(f"bins: {', '.join(f'{b.name} ({b.color})' for b in lab.bins)}; table at "
                    f"z = {lab.table_z * 1000:.1f} mm")
                if a.recalibrate or not c.camera(camera).calibrated:
                    log(f"calibrating camera {camera}: the magnet on {len(CALIBRATION)} points")
                    lab.calibrate(CALIBRATION, lab.table_z + 0.001)
                colors = a.colors or list(dict.fromkeys(b.color for b in lab.bins))
                landed = lab.run(colors)
                log(f"landed {landed} target(s)")
        except ArmServerError as exc:
            fail(f"server refused: {exc.code}: {exc.detail}")
        log("where everything is now (the world route):")
        if not check_sorted(c, a.arm, lab.bins):
            fail("some targets are not in their bins")
    log("landed: every target is in its bin")
    return 0


if __name__ == "__main__":
    sys.exit(main())
