"""Angler visiting sequence: origin -> target -> origin for each target, with both IK cases.

As in the project report: the client solves the inverse kinematics itself (POST
kinematics/inverse with `ik_case`), then moves in joint space, the joints interpolated linearly
from where they are to the solution (POST move/joints; `--steps N` sends N evenly spaced joint
waypoints instead of one move).

- `dx_zero`: the x carriage stays at 0 and theta3 alone reaches x (|x| <= r);
- `dx_used`: theta3 is kept (the current one, or the target's own) and the x carriage moves.

    python examples/angler_visit.py --url http://127.0.0.1:8000 [--quick] [--steps 3]
"""

from __future__ import annotations

import os
import sys
from collections.abc import Sequence

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from _common import dist, fail, fmt, log, parser  # noqa: E402

from app import schemas as s  # noqa: E402
from app.client import ArmClient, ArmServerError, Unreachable  # noqa: E402

ARM = "angler"
HOME = [0.0, 0.0, 0.0, 0.05]  # the profile's home joints (dx, dy, theta3, dz), m and rad
#: (x, y, z) m, IK case, theta3 to keep for dx_used (None: the current one).
TARGETS: list[tuple[tuple[float, float, float], str, float | None]] = [
    ((0.050, 0.100, 0.020), "dx_zero", None),
    ((0.030, 0.120, 0.000), "dx_used", None),
    ((-0.060, 0.140, 0.040), "dx_zero", None),
    ((0.120, 0.040, -0.020), "dx_used", -0.6),  # |x| > r: only dx_used reaches it
]
TOLERANCE = 0.004  # m, measured tip vs target once a motion is done
#: Speed fraction of the profile's joint limits (the x and y carriages: 0.01 m/s, what an
#: MX-28 at its velocity limit turns an 8 mm lead at).
SPEED = 1.0


def solve(c: ArmClient, p: Sequence[float], case: str, theta3: float | None,
          q_now: Sequence[float]) -> s.IKSolution:
    """The within-limits IK solution of `case` nearest the current joints."""
    res = c.inverse(ARM, *p, ik_case=case, theta3=theta3)  # type: ignore[arg-type]
    ok = [sol for sol in res.solutions if sol.within_limits]
    if not ok:
        fail(f"{p} ({case}): no solution within limits: "
             f"{[sol.violations for sol in res.solutions]}")
    return min(ok, key=lambda sol: sum((a - b) ** 2 for a, b in zip(sol.positions, q_now,
                                                                        strict=True)))


def go(c: ArmClient, label: str, p: Sequence[float], case: str, theta3: float | None,
       steps: int, speed: float) -> None:
    q0 = c.state(ARM).positions
    if case == "dx_used" and theta3 is None:
        theta3 = q0[2]
    sol = solve(c, p, case, theta3, q0)
    q1 = sol.positions
    log(f"  {label:<8} {case:<7} target ({p[0] * 1000:+6.1f}, {p[1] * 1000:+6.1f}, "
        f"{p[2] * 1000:+6.1f}) mm  IK branch {sol.branch}: {fmt(q1)}")
    last = None
    for k in range(1, steps + 1):
        qk = [a + (b - a) * k / steps for a, b in zip(q0, q1, strict=True)]
        last = c.move_joints(ARM, qk, speed=speed, wait=(k == steps))
    assert last is not None
    if last.status != "done":
        fail(f"{label}: motion {last.id} ended {last.status}: {last.reason}")
    st = c.state(ARM)
    err = dist(st.tip, p)
    log(f"  {label:<8} arrived: joints {fmt(st.positions)} tip {fmt(st.tip)} error "
        f"{err * 1000:.1f} mm [{last.id}, {steps} joint segment(s)]")
    if err > TOLERANCE:
        fail(f"{label}: tip {err * 1000:.1f} mm from the target")
    if case == "dx_zero" and abs(st.positions[0]) > 0.002:
        fail(f"{label}: dx_zero case but dx = {st.positions[0]:.4f} m")
    if case == "dx_used" and abs(st.positions[2] - (theta3 or 0.0)) > 0.01:
        fail(f"{label}: dx_used case but theta3 = {st.positions[2]:.3f} rad, not {theta3}")


def main(argv: list[str] | None = None) -> int:
    p = parser(__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true", help="one target per IK case")
    p.add_argument("--steps", type=int, default=1, help="joint waypoints per move (default 1)")
    p.add_argument("--speed", type=float, default=SPEED, help="speed fraction (default 1.0)")
    a = p.parse_args(argv)
    targets = TARGETS[:2] if a.quick else TARGETS
    with ArmClient(a.url, token=a.token, timeout=30.0) as c:
        try:
            detail = c.arm(ARM)
            log(f"arm {detail.name}: {detail.description}; r = {detail.geometry['r']} m, "
                f"h = {detail.geometry['h']} m")
            origin = c.forward(ARM, HOME).tip
            o = (origin.x, origin.y, origin.z)
            log(f"origin: home joints {fmt(HOME)} -> tip {fmt(origin)}")
            m = c.move_joints(ARM, HOME, speed=a.speed, wait=True)
            log(f"at origin ({m.status}): tip {fmt(c.state(ARM).tip)}")
            for i, (target, case, theta3) in enumerate(targets, 1):
                log(f"target {i}/{len(targets)} with ik_case {case}")
                if case == "dx_used" and abs(target[0]) > detail.geometry["r"]:
                    try:
                        c.inverse(ARM, *target, ik_case="dx_zero")
                    except Unreachable as exc:
                        log(f"  dx_zero cannot reach it ({exc.code}): {exc.detail}")
                go(c, "target", target, case, theta3, a.steps, a.speed)
                go(c, "origin", o, case, None, a.steps, a.speed)
        except ArmServerError as exc:
            fail(f"server refused: {exc.code}: {exc.detail}")
    log(f"angler visit done: {len(targets)} targets visited")
    return 0


if __name__ == "__main__":
    sys.exit(main())
