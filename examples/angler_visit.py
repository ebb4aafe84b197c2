"""Angler visiting sequence: origin -> target -> origin for each target, with both IK cases.

As in the design document: the origin is every joint at 0 (dx = dy = theta3 = dz = 0); the
client solves the inverse kinematics itself (POST kinematics/inverse with `ik_case`), then
moves in joint space, the joints interpolated linearly from where they are to the solution
(POST move/joints; `--steps N` sends N evenly spaced joint waypoints instead of one move).

- `dx_zero`: the x carriage stays at 0 and theta3 alone reaches x (|x| <= r);
- `dx_used`: the design's second case, theta3 = -90 deg for x > 0 (+90 deg for x < 0), and
  the x carriage stands r short of the target (dx = x -/+ r).

    python examples/angler_visit.py --url http://127.0.0.1:8000 [--quick] [--steps 3]
"""

from __future__ import annotations

import math
import os
import sys
from collections.abc import Sequence

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from _common import dist, fail, fmt, log, parser  # noqa: E402

from app import schemas as s  # noqa: E402
from app.client import ArmClient, ArmServerError, Unreachable  # noqa: E402

ARM = "angler"
ORIGIN = [0.0, 0.0, 0.0, 0.0]  # the design's origin: every joint (dx, dy, theta3, dz) at 0
#: (x, y, z) m and IK case. dx_used takes the design's theta3 (-90 deg for x > 0, +90 for
#: x < 0), so its y is the y carriage's own: within its +-75 mm.
TARGETS: list[tuple[tuple[float, float, float], str]] = [
    ((0.050, 0.100, 0.020), "dx_zero"),
    ((0.090, 0.030, 0.000), "dx_used"),
    ((-0.060, 0.140, 0.040), "dx_zero"),
    ((0.120, 0.040, -0.020), "dx_used"),  # |x| > r: only dx_used reaches it
]
TOLERANCE = 0.004  # m, measured tip vs target once a motion is done
#: Speed fraction of the profile's joint limits. The x and y carriages are held to 6 mm/s
#: (45 rpm on the 8 mm lead): an MX-28 turns at most about 55 rpm at 12 V with no load
#: (e-manual MX-28(2.0), "Specifications"), 7.3 mm/s, and less under load.
SPEED = 1.0


def design_theta3(x: float) -> float:
    """The design's dx_used theta3: -90 deg for x > 0 (and x = 0), +90 deg for x < 0."""
    return math.pi / 2 if x < 0 else -math.pi / 2


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


def move(c: ArmClient, q1: Sequence[float], steps: int, speed: float) -> s.Motion:
    """Joint space from where the arm is to `q1`, in `steps` evenly spaced waypoints."""
    q0 = c.state(ARM).positions
    last = None
    for k in range(1, steps + 1):
        qk = [a + (b - a) * k / steps for a, b in zip(q0, q1, strict=True)]
        last = c.move_joints(ARM, qk, speed=speed, wait=(k == steps))
    assert last is not None
    return last


def go(c: ArmClient, label: str, p: Sequence[float], case: str, steps: int,
       speed: float) -> None:
    q0 = c.state(ARM).positions
    theta3 = design_theta3(p[0]) if case == "dx_used" else None
    sol = solve(c, p, case, theta3, q0)
    q1 = sol.positions
    log(f"  {label:<8} {case:<7} target ({p[0] * 1000:+6.1f}, {p[1] * 1000:+6.1f}, "
        f"{p[2] * 1000:+6.1f}) mm  IK branch {sol.branch}: {fmt(q1)}"
        + (f", theta3 {math.degrees(theta3):+.0f} deg (design)" if theta3 is not None else ""))
    last = move(c, q1, steps, speed)
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
    if theta3 is not None and abs(st.positions[2] - theta3) > 0.01:
        fail(f"{label}: dx_used case but theta3 = {st.positions[2]:.3f} rad, not {theta3}")


def to_origin(c: ArmClient, steps: int, speed: float) -> None:
    m = move(c, ORIGIN, steps, speed)
    if m.status != "done":
        fail(f"origin: motion {m.id} ended {m.status}: {m.reason}")
    st = c.state(ARM)
    log(f"  origin   arrived: joints {fmt(st.positions)} tip {fmt(st.tip)} [{m.id}]")
    if max(abs(v) for v in st.positions) > 0.002:
        fail(f"origin: joints {fmt(st.positions)}, not every joint at 0")


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
            origin = c.forward(ARM, ORIGIN).tip
            log(f"origin: every joint at 0 {fmt(ORIGIN)} -> tip {fmt(origin)}")
            to_origin(c, a.steps, a.speed)
            for i, (target, case) in enumerate(targets, 1):
                log(f"target {i}/{len(targets)} with ik_case {case}")
                if case == "dx_used" and abs(target[0]) > detail.geometry["r"]:
                    try:
                        c.inverse(ARM, *target, ik_case="dx_zero")
                    except Unreachable as exc:
                        log(f"  dx_zero cannot reach it ({exc.code}): {exc.detail}")
                go(c, "target", target, case, a.steps, a.speed)
                to_origin(c, a.steps, a.speed)
        except ArmServerError as exc:
            fail(f"server refused: {exc.code}: {exc.detail}")
    log(f"angler visit done: {len(targets)} targets visited")
    return 0


if __name__ == "__main__":
    sys.exit(main())
