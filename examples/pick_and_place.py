"""RBE3001 pick-and-place: for each colour, pick its object off the table and drop it in its bin.

The cycle of the design specification, per colour: open the claw, approach from above (joint
path to a point 5 cm over the object), descend in a straight line, close the claw, lift in a
straight line, carry to the colour's bin (joint path), release, return home. Every step logs
the arm's measured tip (GET /state) and, while the claw holds, the tip force.

Object and bin positions (m, base frame) were chosen from the forward kinematics of in-limit
joints and are checked with POST kinematics/inverse before anything moves.

    python examples/pick_and_place.py --url http://127.0.0.1:8000 [--quick]
"""

from __future__ import annotations

import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from _common import dist, fail, fmt, log, parser  # noqa: E402

from app.client import ArmClient, ArmServerError  # noqa: E402

ARM = "rbe3001"
HOME = [0.0, 0.6, 0.3]  # the profile's home joints, rad: tip at (197, 0, 99) mm
APPROACH_DZ = 0.05  # approach and lift height above an object, m
#: colour -> (object on the table, its bin), m. Objects at base (+-0.38, 0) rad, shoulder ~0.16,
#: elbow ~-0.1; bins to the sides, 10-12 cm up.
TASKS = {
    "red": ((0.200, 0.080, 0.030), (0.100, 0.180, 0.100)),
    "green": ((0.220, 0.000, 0.030), (0.020, 0.210, 0.120)),
    "blue": ((0.200, -0.080, 0.030), (0.100, -0.180, 0.100)),
}
#: How far the measured tip may be from a target when a motion reports done, m.
TOLERANCE = 0.006


def check_reachable(c: ArmClient, name: str, p: tuple[float, float, float]) -> None:
    sols = c.inverse(ARM, *p).solutions
    ok = [sol for sol in sols if sol.within_limits]
    if not ok:
        fail(f"{name} {p} has no IK solution within the joint limits: "
             f"{[sol.violations for sol in sols]}")
    log(f"  {name:<14} {fmt_xyz(p)}: {len(ok)}/{len(sols)} IK solutions within limits, "
        f"e.g. {fmt(ok[0].positions)} rad")


def fmt_xyz(p: tuple[float, float, float]) -> str:
    return f"({p[0] * 1000:+7.1f}, {p[1] * 1000:+7.1f}, {p[2] * 1000:+7.1f}) mm"


def report(c: ArmClient, step: str, target: tuple[float, float, float] | None = None,
           holding: bool = False, note: str = "") -> None:
    st = c.state(ARM)
    line = f"    {step:<26} tip {fmt(st.tip)}"
    if target is not None:
        err = dist(st.tip, target)
        line += f"  error {err * 1000:5.1f} mm"
        if err > TOLERANCE:
            fail(f"{step}: tip {fmt(st.tip)} is {err * 1000:.1f} mm from {fmt_xyz(target)}")
    if st.gripper is not None:
        line += f"  claw {st.gripper:.2f}"
    if holding and st.tip_force is not None:
        f = st.tip_force
        line += f"  tip force ({f.x:+.2f}, {f.y:+.2f}, {f.z:+.2f}) N"
    log(line + note)


def move(c: ArmClient, step: str, p: tuple[float, float, float], path: str,
         holding: bool = False, speed: float = 1.0) -> None:
    m = c.move_pose(ARM, *p, path=path, speed=speed, wait=True)  # type: ignore[arg-type]
    if m.status != "done":
        fail(f"{step}: motion {m.id} ended {m.status}: {m.reason}")
    report(c, step, p, holding, f"  [{m.id}, {m.planned_duration:.2f} s planned]")


def cycle(c: ArmClient, colour: str, obj: tuple[float, float, float],
          bin_: tuple[float, float, float]) -> None:
    above = (obj[0], obj[1], obj[2] + APPROACH_DZ)
    log(f"{colour}: object at {fmt_xyz(obj)}, bin at {fmt_xyz(bin_)}")
    c.gripper(ARM, 0.0)
    report(c, "open claw")
    move(c, "approach (joint path)", above, "joint")
    move(c, "descend (line)", obj, "line", speed=0.5)
    c.gripper(ARM, 1.0)
    time.sleep(0.2)
    report(c, "close claw", obj, holding=True)
    move(c, "lift (line)", above, "line", holding=True, speed=0.5)
    move(c, f"carry to {colour} bin (joint)", bin_, "joint", holding=True)
    c.gripper(ARM, 0.0)
    report(c, "release", bin_)
    m = c.move_joints(ARM, HOME, wait=True)
    if m.status != "done":
        fail(f"return home: motion {m.id} ended {m.status}: {m.reason}")
    report(c, "return home")
    log(f"{colour}: placed")


def main(argv: list[str] | None = None) -> int:
    p = parser(__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true", help="one colour only")
    p.add_argument("--colours", nargs="+", choices=list(TASKS), default=list(TASKS))
    a = p.parse_args(argv)
    colours = a.colours[:1] if a.quick else a.colours
    with ArmClient(a.url, token=a.token, timeout=30.0) as c:
        try:
            detail = c.arm(ARM)
            log(f"arm {detail.name}: {detail.description}; joints "
                f"{[(j.name, j.min, j.max) for j in detail.joints]}")
            if detail.estop:
                fail("the emergency stop is latched; release it first")
            log("checking every point with kinematics/inverse:")
            for colour in colours:
                obj, bin_ = TASKS[colour]
                check_reachable(c, f"{colour} object", obj)
                check_reachable(c, f"{colour} above", (obj[0], obj[1], obj[2] + APPROACH_DZ))
                check_reachable(c, f"{colour} bin", bin_)
            m = c.move_joints(ARM, HOME, wait=True)
            report(c, f"home ({m.status})")
            for colour in colours:
                obj, bin_ = TASKS[colour]
                cycle(c, colour, obj, bin_)
        except ArmServerError as exc:
            fail(f"server refused: {exc.code}: {exc.detail}")
    log(f"pick and place done: {len(colours)} objects placed")
    return 0


if __name__ == "__main__":
    sys.exit(main())
