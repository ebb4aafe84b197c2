"""Record a run from the telemetry WebSocket: a CSV of every sample and a PNG plot.

Subscribes to `WS /api/v1/arms/{arm}/telemetry` (batched at `--rate` messages a second, every
sample kept) for `--seconds`, or, with `--demo`, while it drives the arm through a short
sequence of moves of its own (rbe3001: a rectangle in a vertical plane with straight lines;
angler: a few joint moves), and writes:

- CSV: seq, time (unix s), t (s from the first sample), one column per joint (rad / m),
  tip_x, tip_y, tip_z (m), motion status;
- PNG (matplotlib, Agg): joint positions against time, and the tip path from above (x-y)
  and seen along x (y-z).

    python examples/record.py --url http://127.0.0.1:8000 --arm rbe3001 --demo \
        --csv run.csv --png docs/recorded_run.png
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import csv
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from _common import fail, fmt, log, parser  # noqa: E402

from app import schemas as s  # noqa: E402
from app.client import ArmServerError, AsyncArmClient  # noqa: E402

#: Demo sequences: (kind, target, path) in metres / radians.
DEMO: dict[str, list[tuple[str, tuple[float, ...], str]]] = {
    "rbe3001": [
        ("pose", (0.200, 0.060, 0.080), "joint"),
        ("pose", (0.200, -0.060, 0.080), "line"),
        ("pose", (0.200, -0.060, 0.160), "line"),
        ("pose", (0.200, 0.060, 0.160), "line"),
        ("pose", (0.200, 0.060, 0.080), "line"),
        ("joints", (0.0, 0.6, 0.3), "joint"),
    ],
    "angler": [
        ("joints", (0.0, 0.0, 0.0, 0.05), "joint"),
        ("joints", (0.0, 0.01, -0.8, 0.08), "joint"),
        ("joints", (0.0, 0.01, 0.8, 0.03), "joint"),
        ("joints", (0.0, 0.0, 0.0, 0.05), "joint"),
    ],
}


async def demo(c: AsyncArmClient, arm: str, quick: bool = False) -> None:
    """Queue the arm's demo moves and wait for the last; fail if any does not end done."""
    motions = []
    steps = DEMO[arm][:2] + DEMO[arm][-1:] if quick else DEMO[arm]
    for kind, target, path in steps:
        if kind == "pose":
            m = await c.move_pose(arm, *target, path=path, speed=0.6)  # type: ignore[arg-type]
        else:
            m = await c.move_joints(arm, target, speed=0.6)
        log(f"queued {kind} {path} -> {fmt(target)} as {m.id} ({m.planned_duration:.2f} s)")
        motions.append(m)
    for m in motions:
        end = await c.wait_motion(arm, m.id, timeout=60.0)
        log(f"{end.id} {end.status}" + (f": {end.reason}" if end.reason else ""))
        if end.status != "done":
            fail(f"demo motion {end.id} ended {end.status}")


async def record(c: AsyncArmClient, arm: str, rate: float, out: list[s.Sample],
                 stats: dict[str, int]) -> None:
    async for msg in c.telemetry_messages(arm, rate=rate):
        if isinstance(msg, s.EventMessage):
            log(f"event {msg.event} {msg.data}")
            continue
        stats["messages"] += 1
        stats["dropped"] += msg.dropped
        for smp in msg.samples:  # the first batch may repeat the sample sent on connect
            if out and smp.seq <= out[-1].seq:
                stats["repeated"] += 1
                continue
            out.append(smp)


def write_csv(path: Path, samples: list[s.Sample], names: list[str]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    t0 = samples[0].time
    with path.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["seq", "time", "t", *names, "tip_x", "tip_y", "tip_z", "motion"])
        for smp in samples:
            w.writerow([smp.seq, f"{smp.time:.6f}", f"{smp.time - t0:.6f}",
                        *(f"{q:.6f}" for q in smp.positions),
                        f"{smp.tip.x:.6f}", f"{smp.tip.y:.6f}", f"{smp.tip.z:.6f}",
                        smp.motion.status if smp.motion else ""])


def plot(path: Path, arm: str, samples: list[s.Sample], names: list[str],
         kinds: list[str]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t0 = samples[0].time
    t = [smp.time - t0 for smp in samples]
    tip = [(smp.tip.x * 1000, smp.tip.y * 1000, smp.tip.z * 1000) for smp in samples]
    fig = plt.figure(figsize=(13, 4.8), constrained_layout=True)
    ax_q, ax_top, ax_side = fig.subplots(1, 3, gridspec_kw={"width_ratios": [1.5, 1, 1]})
    for i, name in enumerate(names):
        unit = "rad" if kinds[i] == "revolute" else "m"
        ax_q.plot(t, [smp.positions[i] for smp in samples], label=f"{name} ({unit})")
    ax_q.set_xlabel("time, s")
    ax_q.set_ylabel("joint position")
    ax_q.set_title("joint positions")
    ax_q.legend(fontsize=8)
    views = ((ax_top, [p[0] for p in tip], [p[1] for p in tip], "x, mm", "y, mm",
              "tip path from above"),
             (ax_side, [p[1] for p in tip], [p[2] for p in tip], "y, mm", "z, mm",
              "tip path seen along x"))
    for ax, h, v, xl, yl, title in views:
        ax.plot(h, v, "-", lw=1.2)
        ax.plot(h[0], v[0], "go", label="start")
        ax.plot(h[-1], v[-1], "rs", label="end")
        ax.set_xlabel(xl)
        ax.set_ylabel(yl)
        ax.set_title(title)
        ax.set_aspect("equal", adjustable="datalim")
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=8)
    ax_q.grid(True, alpha=0.3)
    fig.suptitle(f"{arm}: recorded run, {len(samples)} samples (seq {samples[0].seq}.."
                 f"{samples[-1].seq}) over {t[-1]:.2f} s")
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)


async def run(a: argparse.Namespace) -> int:
    arm: str = a.arm
    async with AsyncArmClient(a.url, token=a.token, timeout=30.0) as c:
        try:
            detail = await c.arm(arm)
        except ArmServerError as exc:
            fail(f"{arm}: {exc.code}: {exc.detail}")
        names = [j.name for j in detail.joints]
        kinds = [j.kind for j in detail.joints]
        samples: list[s.Sample] = []
        stats = {"messages": 0, "dropped": 0, "repeated": 0}
        task = asyncio.create_task(record(c, arm, a.rate, samples, stats))
        started = time.monotonic()
        try:
            while not samples and time.monotonic() - started < 5.0:
                await asyncio.sleep(0.02)
            if a.demo:
                if arm not in DEMO:
                    fail(f"no demo for {arm}")
                await demo(c, arm, a.quick)
                await asyncio.sleep(0.3)
            else:
                await asyncio.sleep(a.seconds)
        except ArmServerError as exc:
            fail(f"server refused: {exc.code}: {exc.detail}")
        finally:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task
    if not samples:
        fail("no telemetry received")
    gaps = sum(1 for p, q in zip(samples, samples[1:], strict=False) if q.seq != p.seq + 1)
    log(f"recorded {len(samples)} samples in {stats['messages']} messages, seq "
        f"{samples[0].seq}..{samples[-1].seq}, {gaps} gaps, {stats['dropped']} dropped, "
        f"{stats['repeated']} repeated")
    write_csv(a.csv, samples, names)
    log(f"wrote {a.csv}")
    plot(a.png, arm, samples, names, kinds)
    log(f"wrote {a.png}")
    log("record done")
    return 0


def main(argv: list[str] | None = None) -> int:
    p = parser(__doc__.splitlines()[0])
    p.add_argument("--arm", default="rbe3001")
    p.add_argument("--seconds", type=float, default=3.0, help="how long to record without --demo")
    p.add_argument("--rate", type=float, default=20.0, help="telemetry messages per second")
    p.add_argument("--demo", action="store_true", help="drive a short demo while recording")
    p.add_argument("--quick", action="store_true", help="a shorter demo (3 moves)")
    p.add_argument("--csv", type=Path, default=Path("recorded_run.csv"))
    p.add_argument("--png", type=Path, default=Path("recorded_run.png"))
    return asyncio.run(run(p.parse_args(argv)))


if __name__ == "__main__":
    sys.exit(main())
