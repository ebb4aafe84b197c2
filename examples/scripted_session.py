"""Issue-4 acceptance session, scripted: everything a lab client needs, checked end to end.

1. list the arms;
2. move each arm to a reachable pose and see the tip arrive, in GET /state and in telemetry;
3. ask for a pose out of reach and get 422 `unreachable`;
4. stop a running move (it ends `stopped`, the arm holds), then latch the emergency stop under
   another running move (it ends `stopped`, moves get 409 `estop_latched` until released);
5. receive numbered telemetry at a requested rate with no gaps in `seq`.

Exits 0 when every check passes; each check logs a line starting "ok".

    python examples/scripted_session.py --url http://127.0.0.1:8000
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import sys
import time
from collections.abc import AsyncIterator

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from _common import dist, fail, fmt, log, parser  # noqa: E402

from app import schemas as s  # noqa: E402
from app.client import ArmServerError, AsyncArmClient, EstopLatched, Unreachable  # noqa: E402

#: A reachable pose per arm model (m), within a short move of the home pose; other models use
#: the tip of the middle of their joint ranges.
POSES = {"rbe3001": (0.200, 0.050, 0.080), "angler": (0.030, 0.110, 0.020)}
#: Long moves for the stop and estop checks: (joints, duration s), per model.
LONG_MOVES = {"rbe3001": ([0.6, 0.9, 0.6], 3.0), "angler": ([0.0, 0.0, 1.2, 0.09], 3.0)}
TOLERANCE = 0.006  # m: measured tip vs target after a done motion
SPEED = 1.0  # fraction of the profile's speed limits


def ok(msg: str) -> None:
    log("ok  ", msg)


async def collect(c: AsyncArmClient, arm: str, rate: float | None,
                  out: list[s.TelemetryMessage | s.EventMessage]) -> None:
    async for msg in c.telemetry_messages(arm, rate=rate):
        out.append(msg)


@contextlib.asynccontextmanager
async def watching(c: AsyncArmClient, arm: str, rate: float | None = None
                   ) -> AsyncIterator[list[s.TelemetryMessage | s.EventMessage]]:
    """Collect telemetry messages in the background while the body runs."""
    msgs: list[s.TelemetryMessage | s.EventMessage] = []
    task = asyncio.create_task(collect(c, arm, rate, msgs))
    deadline = time.monotonic() + 5.0
    while not msgs and time.monotonic() < deadline:
        await asyncio.sleep(0.01)
    if not msgs:
        fail(f"{arm}: no telemetry within 5 s")
    try:
        yield msgs
    finally:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task


def samples_of(msgs: list[s.TelemetryMessage | s.EventMessage]) -> list[s.Sample]:
    return [smp for m in msgs if isinstance(m, s.TelemetryMessage) for smp in m.samples]


def events_of(msgs: list[s.TelemetryMessage | s.EventMessage]) -> list[s.EventMessage]:
    return [m for m in msgs if isinstance(m, s.EventMessage)]


async def reach(c: AsyncArmClient, arm: s.ArmDetail) -> None:
    name = arm.name
    if arm.model in POSES:
        target = POSES[arm.model]
    else:
        mid = [(j.min + j.max) / 2 for j in arm.joints]
        tip = (await c.forward(name, mid)).tip
        target = (tip.x, tip.y, tip.z)
    async with watching(c, name) as msgs:
        m = await c.move_pose(name, *target, speed=SPEED, wait=True)
        await asyncio.sleep(0.2)
    if m.status != "done":
        fail(f"{name}: move to {target} ended {m.status}: {m.reason}")
    st = await c.state(name)
    err = dist(st.tip, target)
    if err > TOLERANCE:
        fail(f"{name}: /state tip {fmt(st.tip)} is {err * 1000:.1f} mm from the target")
    ok(f"{name}: moved to {fmt(s.Vec3(x=target[0], y=target[1], z=target[2]))} "
       f"({m.id} {m.status}); /state tip {fmt(st.tip)}, {err * 1000:.1f} mm off")
    smp = samples_of(msgs)
    moving = [x for x in smp if x.motion is not None and x.motion.id == m.id
              and x.motion.status == "running"]
    # The arrival: the first sample of the final stretch that stays within the tolerance.
    k = len(smp)
    while k > 0 and dist(smp[k - 1].tip, target) <= TOLERANCE:
        k -= 1
    if not moving or k == len(smp):
        fail(f"{name}: telemetry did not show the move ({len(moving)} running samples) or the "
             f"tip at the target (last {fmt(smp[-1].tip)})")
    ok(f"{name}: telemetry showed {len(moving)} samples of {m.id} running and the tip arriving "
       f"at seq {smp[k].seq} ({fmt(smp[k].tip)}), staying to seq {smp[-1].seq}")


async def unreachable(c: AsyncArmClient, name: str) -> None:
    try:
        await c.move_pose(name, 2.0, 2.0, 2.0)
    except Unreachable as exc:
        if exc.status != 422 or exc.code != "unreachable":
            fail(f"{name}: expected 422 unreachable, got {exc.status} {exc.code}")
        ok(f"{name}: pose (2, 2, 2) m refused: {exc.status} {exc.code}: {exc.detail}")
        return
    except ArmServerError as exc:
        fail(f"{name}: expected 422 unreachable, got {exc.status} {exc.code}: {exc.detail}")
    fail(f"{name}: a pose out of reach was accepted")


async def running(c: AsyncArmClient, name: str, motion_id: str) -> s.Motion:
    deadline = time.monotonic() + 5.0
    while time.monotonic() < deadline:
        m = await c.motion(name, motion_id)
        if m.status == "running" and m.progress > 0.1:
            return m
        if m.status in ("done", "stopped", "failed"):
            fail(f"{name}: {motion_id} ended {m.status} before it could be stopped")
        await asyncio.sleep(0.02)
    fail(f"{name}: {motion_id} never ran")
    raise AssertionError


async def stop_and_estop(c: AsyncArmClient, arm: s.ArmDetail, home: list[float]) -> None:
    name = arm.name
    q, duration = LONG_MOVES.get(arm.model, ([(j.min + j.max) / 2 for j in arm.joints], 3.0))
    m = await c.move_joints(name, q, duration=duration)
    r = await running(c, name, m.id)
    res = await c.stop(name)
    end = await c.motion(name, m.id)
    await asyncio.sleep(0.3)
    a, b = (await c.state(name)).positions, None
    await asyncio.sleep(0.3)
    b = (await c.state(name)).positions
    drift = max(abs(x - y) for x, y in zip(a, b, strict=True))
    if m.id not in res.stopped or end.status != "stopped" or drift > 0.01:
        fail(f"{name}: stop: stopped={res.stopped}, {m.id} {end.status}, drift {drift:.4f}")
    ok(f"{name}: stop at progress {r.progress:.2f}: {m.id} {end.status} ({end.reason}); "
       f"the arm holds (drift {drift:.4f} in 0.3 s)")

    async with watching(c, name) as msgs:
        m = await c.move_joints(name, home, duration=duration)
        r = await running(c, name, m.id)
        await c.estop(name)
        end = await c.motion(name, m.id)
        try:
            await c.move_joints(name, home)
            fail(f"{name}: a move was accepted while the estop was latched")
        except EstopLatched as exc:
            ok(f"{name}: estop at progress {r.progress:.2f}: {m.id} {end.status} "
               f"({end.reason}); a move now gets {exc.status} {exc.code}")
        if end.status != "stopped":
            fail(f"{name}: estop left {m.id} {end.status}")
        state = await c.state(name)
        if not state.estop:
            fail(f"{name}: /state does not show the estop latched")
        released = await c.release_estop(name)
        await asyncio.sleep(0.1)
    names = [e.event for e in events_of(msgs)]
    if "estop" not in names or "estop_released" not in names:
        fail(f"{name}: telemetry events {names} lack estop / estop_released")
    ok(f"{name}: released (estop={released.estop}); telemetry events: {', '.join(names)}")
    m = await c.move_joints(name, home, speed=SPEED, wait=True)
    if m.status != "done":
        fail(f"{name}: move after release ended {m.status}: {m.reason}")
    ok(f"{name}: moves again after release ({m.id} {m.status})")


async def numbered(c: AsyncArmClient, name: str, rate: float, seconds: float) -> None:
    async with watching(c, name, rate) as msgs:
        start = len(msgs)
        await asyncio.sleep(seconds)
        batch = [m for m in msgs[start:] if isinstance(m, s.TelemetryMessage)]
    smp = [x for m in batch for x in m.samples]
    gaps = [(p.seq, q.seq) for p, q in zip(smp, smp[1:], strict=False) if q.seq != p.seq + 1]
    dropped = sum(m.dropped for m in batch)
    got = len(batch) / seconds
    if gaps or dropped:
        fail(f"{name}: seq gaps {gaps[:5]}, dropped {dropped}")
    if not rate * 0.5 <= got <= rate * 1.5:
        fail(f"{name}: asked for {rate} messages/s, got {got:.1f}")
    ok(f"{name}: {len(batch)} messages in {seconds:.1f} s ({got:.1f}/s for {rate:g}/s asked), "
       f"{len(smp)} samples seq {smp[0].seq}..{smp[-1].seq}, no gaps, 0 dropped")


async def run(url: str, token: str | None, quick: bool) -> int:
    async with AsyncArmClient(url, token=token, timeout=30.0) as c:
        try:
            health = await c.health()
            ok(f"health {health.status}: " + ", ".join(f"{k} {v.state}"
                                                     for k, v in health.arms.items()))
            arms = await c.arms()
            ok("arms: " + "; ".join(f"{a.name} ({a.model}, {a.link.kind} link, gripper "
                                    f"{a.capabilities.gripper})" for a in arms))
            details = [await c.arm(a.name) for a in arms]
            for d in details:
                if d.estop:
                    await c.release_estop(d.name)
                await reach(c, d)
            for d in details:
                await unreachable(c, d.name)
            first = details[0]
            home = (await c.state(first.name)).positions
            await stop_and_estop(c, first, home)
            for d in details[:1] if quick else details:
                await numbered(c, d.name, rate=20.0, seconds=1.5)
        except ArmServerError as exc:
            fail(f"server refused: {exc.status} {exc.code}: {exc.detail}")
    log("scripted session passed")
    return 0


def main(argv: list[str] | None = None) -> int:
    p = parser(__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true", help="rate check on the first arm only")
    a = p.parse_args(argv)
    return asyncio.run(run(a.url, a.token, a.quick))


if __name__ == "__main__":
    sys.exit(main())
