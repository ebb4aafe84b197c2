"""Replay a recorded joint trajectory (a CSV from examples/record.py) on an arm.

The recording is subsampled to `--points` evenly spaced samples (near-duplicates, where the
arm stood still, are skipped), checked with POST plan/joints, then sent as queued joint moves
(POST move/joints). With `--timed`, each move is given the recorded time between its
waypoints as its duration, so the replay keeps the run's pace where the limits allow.
Ends by comparing the arm's measured joints with the recording's last sample.

    python examples/replay.py run.csv --url http://127.0.0.1:8000 --arm rbe3001 --points 12
"""

from __future__ import annotations

import csv
import os
import sys
from pathlib import Path

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from _common import fail, fmt, log, parser  # noqa: E402

from app.client import ArmClient, ArmServerError  # noqa: E402

#: Waypoints closer than this (max joint difference, rad or m) are one waypoint.
MIN_STEP = 0.002
#: Final measured joints must be this close to the recording's last sample (rad or m).
TOLERANCE = 0.02


def read(path: Path, names: list[str]) -> list[tuple[float, list[float]]]:
    """(t s, joints) per row of a record.py CSV, for the arm's joint names."""
    with path.open(newline="") as f:
        rows = list(csv.DictReader(f))
    missing = [n for n in names if rows and n not in rows[0]]
    if not rows or missing:
        fail(f"{path}: no rows, or no columns for joints {missing}")
    return [(float(r["t"]), [float(r[n]) for n in names]) for r in rows]


def subsample(rows: list[tuple[float, list[float]]],
              points: int) -> list[tuple[float, list[float]]]:
    n = len(rows)
    idx = sorted({round(i * (n - 1) / max(points - 1, 1)) for i in range(points)})
    out: list[tuple[float, list[float]]] = []
    for i in idx:
        t, q = rows[i]
        if out and max(abs(a - b) for a, b in zip(q, out[-1][1], strict=True)) < MIN_STEP:
            continue
        out.append((t, q))
    if out[-1][1] != rows[-1][1]:
        out.append(rows[-1])
    return out


def main(argv: list[str] | None = None) -> int:
    p = parser(__doc__.splitlines()[0])
    p.add_argument("csv", type=Path)
    p.add_argument("--arm", default="rbe3001")
    p.add_argument("--points", type=int, default=12, help="waypoints to keep (default 12)")
    p.add_argument("--timed", action="store_true", help="use the recorded timing as durations")
    p.add_argument("--speed", type=float, default=0.6, help="speed fraction when not --timed")
    a = p.parse_args(argv)
    with ArmClient(a.url, token=a.token, timeout=30.0) as c:
        try:
            detail = c.arm(a.arm)
            names = [j.name for j in detail.joints]
            rows = read(a.csv, names)
            way = subsample(rows, a.points)
            log(f"{a.csv}: {len(rows)} samples over {rows[-1][0]:.2f} s -> {len(way)} waypoints")
            for i, (t, q) in enumerate(way):
                plan = c.plan_joints(a.arm, q)
                log(f"  waypoint {i:2d} t={t:6.2f} s joints {fmt(q)} tip {fmt(plan.target_tip)}")
            motions = []
            prev_t = way[0][0]
            for i, (t, q) in enumerate(way):
                duration = max(t - prev_t, 0.05) if (a.timed and i > 0) else None
                m = c.move_joints(a.arm, q, duration=duration,
                                  speed=1.0 if duration else a.speed)
                motions.append(m)
                prev_t = t
            log(f"sent {len(motions)} joint moves, {sum(m.planned_duration for m in motions):.2f}"
                " s planned")
            for m in motions:
                end = c.wait_motion(a.arm, m.id, timeout=120.0)
                if end.status != "done":
                    fail(f"{end.id} ended {end.status}: {end.reason}")
            st = c.state(a.arm)
            err = max(abs(x - y) for x, y in zip(st.positions, way[-1][1], strict=True))
            log(f"replayed: joints {fmt(st.positions)} tip {fmt(st.tip)}, largest joint error "
                f"{err:.4f} against the recording")
            if err > TOLERANCE:
                fail(f"final joints {err:.4f} from the recording's last sample")
        except ArmServerError as exc:
            fail(f"server refused: {exc.code}: {exc.detail}")
    log("replay done")
    return 0


if __name__ == "__main__":
    sys.exit(main())
