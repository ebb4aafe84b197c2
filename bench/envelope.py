"""How fast the safety envelope checks a trajectory (app/safety/envelope.py).

Run: ``python bench/envelope.py``. For both arms, with 4 keep-out zones and a floor, prints

- the check alone (body points of every joint origin and the tip through kinematics.chain, then
  the zone and floor test over (time, body point, zone)): trajectory points per millisecond;
- a whole planned move's check as the executor runs it (sampling the ruckig trajectory at the
  control rate, then the check), and the plan time for comparison;
- a pass-through command's straight joint-space path check.

Best of 5 runs each; no asserts (figures depend on the machine and its load).
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from app import schemas as s  # noqa: E402
from app.arms.loading import load_profile  # noqa: E402
from app.config import KeepOutBox, SafetySettings  # noqa: E402
from app.service import ArmService  # noqa: E402
from kinematics.trajectory import time_grid  # noqa: E402

N_POINTS = (1_000, 10_000, 100_000)
ZONES = 4


def best(fn: Callable[[], object], runs: int = 5) -> float:
    out = []
    for _ in range(runs):
        t0 = time.perf_counter()
        fn()
        out.append(time.perf_counter() - t0)
    return min(out)


def far_zones(n: int) -> list[KeepOutBox]:
    """Zones nowhere near the arm: the check must look at every point (the worst case)."""
    return [KeepOutBox.model_validate({"name": f"z{i}", "min": {"x": 5 + i, "y": 5, "z": 5},
                                       "max": {"x": 5.5 + i, "y": 5.5, "z": 5.5}})
            for i in range(n)]


def near_zones(svc: ArmService, q: np.ndarray, n: int) -> list[KeepOutBox]:
    """Small zones inside the bounding box of every body point's path: no pair of (body point,
    zone) can be skipped, so every point goes through the full test (the worst case)."""
    p = svc.safety.points(q)
    lo, hi = p.min(axis=(0, 1)), p.max(axis=(0, 1))
    out = []
    for i in range(n):
        c = lo + (hi - lo) * (0.2 + 0.15 * i)
        out.append(KeepOutBox.model_validate(
            {"name": f"n{i}", "min": dict(zip("xyz", (c - 0.002).tolist(), strict=True)),
             "max": dict(zip("xyz", (c + 0.002).tolist(), strict=True))}))
    return out


def bench_arm(arm: str) -> None:
    svc = ArmService(load_profile(arm))
    m = svc.model
    svc.safety.apply(SafetySettings(zones=far_zones(ZONES), floor_z=-5.0), "stored")
    rng = np.random.default_rng(0)
    print(f"\n{arm}: {len(svc.safety.bodies)} body points ({', '.join(svc.safety.bodies)})")
    for n in N_POINTS:
        q = rng.uniform(m.lower, m.upper, size=(n, m.n))
        t = np.arange(n) * 0.01
        dt = best(lambda q=q, t=t: svc.safety.first_hit(q, t))
        print(f"  check alone   {n:>7} points: {dt * 1e3:8.2f} ms  "
              f"{n / dt / 1e3:8.0f} points/ms  (zones away from the path)")
    for n in N_POINTS:
        q = rng.uniform(m.lower, m.upper, size=(n, m.n))
        t = np.arange(n) * 0.01
        svc.safety.apply(SafetySettings(zones=near_zones(svc, q, ZONES), floor_z=-5.0),
                         "stored")
        dt = best(lambda q=q, t=t: svc.safety.first_hit(q, t))
        print(f"  check alone   {n:>7} points: {dt * 1e3:8.2f} ms  "
              f"{n / dt / 1e3:8.0f} points/ms  (every zone within the path's reach: the "
              "full test, worst case)")
    svc.safety.apply(SafetySettings(zones=far_zones(ZONES), floor_z=-5.0), "stored")
    q0 = m.lower + 0.1 * (m.upper - m.lower)
    q1 = m.upper - 0.1 * (m.upper - m.lower)
    start = (q0, np.zeros(m.n), np.zeros(m.n))
    req = s.MoveJoints(positions=q1.tolist())
    plan = svc.motion._plan_joint_from(start, q1, req, True)
    ctl = 1.0 / svc.profile.link.control_hz
    k = time_grid(plan.traj.duration, ctl).size
    t_plan = best(lambda: svc.motion._plan_joint_from(start, q1, req, True))
    t_check = best(lambda: svc.safety.check_trajectory(plan.traj, ctl))
    print(f"  a full-range joint move ({plan.traj.duration:.2f} s, {k} setpoints at "
          f"{svc.profile.link.control_hz:g} Hz): plan + check {t_plan * 1e3:.2f} ms, of "
          f"which the check (sampling included) {t_check * 1e3:.2f} ms")
    t_path = best(lambda: svc.safety.check_joint_path(q0, q1))
    print(f"  pass-through path check, full range: {t_path * 1e3:.2f} ms")



def main() -> None:
    print(f"safety envelope check, {ZONES} zones + a floor, best of 5")
    for arm in ("rbe3001", "angler"):
        bench_arm(arm)

if __name__ == "__main__":
    main()
