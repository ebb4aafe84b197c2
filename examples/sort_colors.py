"""Sort coloured objects into their bins: the design document's colour-sorting lab (issue 25).

The program, as the document writes it: `nextColor()` says which colour to look for next and
when to stop; `detectColor()` asks the camera (GET /cameras/{cam}/detections?color=...) whether
any large enough object of that colour lies on the table outside the bins, and where the
largest is; the arm picks it (approach from above, descend, close the claw, lift) and drops it
in that colour's bin; until no colour is left. The camera is calibrated first if it is not
(the tip on four table points, its mark found in the frames; POST /cameras/{cam}/calibration).

Against `make run` (the simulated rbe3001, its world and its simulated camera):

    python examples/sort_colors.py [--url http://127.0.0.1:8000] [--arm rbe3001]

The objects are found by the camera only; at the end the world route (the simulator's truth)
is read to report where every object is.
"""

from __future__ import annotations

import os
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from _common import fail, log, parser  # noqa: E402
from _sorting import check_sorted, lab_from_world  # noqa: E402

from app.client import ArmClient, ArmServerError  # noqa: E402

#: A ball's diameter and a block's edge, m (the lab's objects).
OBJECT_HEIGHT = 0.025
#: Table points (x, y) m the tip visits to calibrate the camera, per arm type (reachable at
#: table height, spread over the picture).
CALIBRATION = {
    "rbe3001": [(0.12, -0.12), (0.12, 0.12), (0.25, 0.1), (0.25, -0.1), (0.18, 0.0)],
    "openmanipulator_x": [(0.15, -0.1), (0.15, 0.1), (0.25, 0.08), (0.25, -0.08)],
}


def main(argv: list[str] | None = None) -> int:
    p = parser(__doc__.splitlines()[0])
    p.add_argument("--arm", default="rbe3001")
    p.add_argument("--camera", default=None, help="camera name (default: the arm's name, the "
                   "server's simulated camera of that arm)")
    p.add_argument("--colors", nargs="+", default=None,
                   help="colours to sort (default: every bin's colour)")
    p.add_argument("--recalibrate", action="store_true",
                   help="calibrate the camera even if it is calibrated")
    p.add_argument("--speed", type=float, default=1.0, help="fraction of the arm's limits")
    a = p.parse_args(argv)
    camera = a.camera or a.arm
    with ArmClient(a.url, token=a.token, timeout=60.0) as c:
        try:
            detail = c.arm(a.arm)
            if detail.estop:
                fail("the emergency stop is latched; release it first")
            model = detail.model if hasattr(detail, "model") else a.arm
            with c.hold_lease(a.arm):
                lab = lab_from_world(c, a.arm, camera, "claw", OBJECT_HEIGHT, a.speed)
                log(f"bins: {', '.join(f'{b.name} ({b.color})' for b in lab.bins)}; table at "
                    f"z = {lab.table_z * 1000:.1f} mm")
                if a.recalibrate or not c.camera(camera).calibrated:
                    points = CALIBRATION.get(model) or CALIBRATION.get(a.arm)
                    if points is None:
                        fail(f"no calibration points known for {a.arm}")
                        return 1
                    log(f"calibrating camera {camera}: the tip on {len(points)} table points")
                    lab.calibrate(points, lab.table_z)
                colors = a.colors or list(dict.fromkeys(b.color for b in lab.bins))
                placed = lab.run(colors)
                log(f"placed {placed} object(s)")
                c.gripper(a.arm, 0.0)
        except ArmServerError as exc:
            fail(f"server refused: {exc.code}: {exc.detail}")
        log("where everything is now (the world route):")
        if not check_sorted(c, a.arm, lab.bins):
            fail("some objects are not in their bins")
    log("sorted: every object is in its bin")
    return 0


if __name__ == "__main__":
    sys.exit(main())
