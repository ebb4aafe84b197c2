"""The classroom's figures (app/classroom/queue.py, app/classroom/audit.py), in-process over the
simulated arms.

Run: ``python bench/classroom.py``. Prints

- hand-offs per minute: students who claim their turn and release it at once, back to back on
  one arm (each hand-off stops the arm, brings it home at half speed and checks it);
- the wait of each queue position against its expected wait (position x (slot + one hand-off
  + the claim)), with students who hold their whole slot;
- audit writes per second under a burst of changing requests, and the telemetry publish rate
  and its worst gap with and without that burst (the writes go through the store's thread, so
  the sample rate should not move).

No asserts: the figures depend on the machine and its load.
"""

from __future__ import annotations

import asyncio
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import httpx

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from app.config import Settings  # noqa: E402
from app.web.factory import create_app  # noqa: E402

STUDENTS = 8
SLOT_S = 1.0
CLAIM_S = 2.0
ARM = "angler"


def settings() -> Settings:
    return Settings(config=None, data_dir=tempfile.mkdtemp(prefix="bench-classroom-"),
                    operator_tokens=",".join(f"s{i}:tok{i}" for i in range(STUDENTS)),
                    instructor_tokens="teach:tok-teach", viewer_tokens="", cors_origins="",
                    slot_s=SLOT_S, claim_s=CLAIM_S, lease_ttl_s=1.0)


def H(i: int | str) -> dict[str, str]:
    return {"Authorization": f"Bearer tok{i}" if isinstance(i, int) else f"Bearer {i}"}


async def wait_offer(c: httpx.AsyncClient, i: int, eid: str) -> dict[str, Any]:
    while True:
        e = (await c.get(f"/api/v1/arms/{ARM}/queue/{eid}", headers=H(i))).json()
        if e["status"] == "offered" and e["lease_id"]:
            return e  # type: ignore[no-any-return]
        await asyncio.sleep(0.02)


async def handoffs_per_minute(c: httpx.AsyncClient, app: Any, seconds: float = 20.0) -> None:
    q = app.state.classroom.queue(ARM)
    start_count = q.handoffs
    t0 = time.monotonic()
    turns = 0

    async def student(i: int) -> None:
        nonlocal turns
        while time.monotonic() - t0 < seconds:
            e = (await c.post(f"/api/v1/arms/{ARM}/queue", headers=H(i))).json()
            e = await wait_offer(c, i, e["id"])
            await c.put(f"/api/v1/arms/{ARM}/lease/{e['lease_id']}", headers=H(i))
            await c.delete(f"/api/v1/arms/{ARM}/lease/{e['lease_id']}", headers=H(i))
            turns += 1

    await asyncio.gather(*(student(i) for i in range(STUDENTS)))
    dt = time.monotonic() - t0
    n = q.handoffs - start_count
    print(f"hand-offs per minute: {60 * n / dt:.0f} ({n} hand-offs, {turns} turns in {dt:.1f} s, "
          f"claim + release at once)")


async def waits(c: httpx.AsyncClient, app: Any) -> None:
    while app.state.classroom.queue(ARM).handing_off or app.state.leases.held(ARM):  # noqa: ASYNC110
        await asyncio.sleep(0.05)
    t_join: dict[int, float] = {}
    waited: dict[int, float] = {}
    handoff_s: list[float] = []

    async def student(i: int) -> None:
        t_join[i] = time.monotonic()
        e = (await c.post(f"/api/v1/arms/{ARM}/queue", headers=H(i))).json()
        e = await wait_offer(c, i, e["id"])
        waited[i] = time.monotonic() - t_join[i]
        lease = e["lease_id"]
        while (await c.put(f"/api/v1/arms/{ARM}/lease/{lease}",  # noqa: ASYNC110
                           headers=H(i))).status_code == 200:
            await asyncio.sleep(0.2)  # holds the whole slot
        t_end = time.monotonic()
        q = app.state.classroom.queue(ARM)
        while (q.handing_off or q.last_handoff is None  # noqa: ASYNC110
               or q.last_handoff["time"] < time.time() - 5):
            await asyncio.sleep(0.01)
        handoff_s.append(time.monotonic() - t_end)

    tasks = []
    for i in range(STUDENTS):
        tasks.append(asyncio.create_task(student(i)))
        await asyncio.sleep(0.01)  # join in order
    await asyncio.gather(*tasks)
    per_turn = statistics.mean(waited[i + 1] - waited[i] for i in range(STUDENTS - 1))
    print(f"queue waits (slot {SLOT_S:g} s; measured turn {per_turn:.2f} s = slot + hand-off + "
          f"claim):")
    print("  position  waited s  expected s (position x measured turn)")
    for i in range(STUDENTS):
        print(f"  {i:8d}  {waited[i]:8.2f}  {i * per_turn:10.2f}")
    print(f"  expected from the slot alone (position x {SLOT_S:g} s) is a lower bound; the rest "
          f"is the hand-off home and the claim")


async def audit_rate(c: httpx.AsyncClient, app: Any, seconds: float = 5.0) -> None:
    hub = app.state.services["rbe3001"].hub
    store = app.state.store

    async def sample_stats() -> tuple[float, float]:
        sub = hub.subscribe()
        times: list[float] = []
        t0 = time.monotonic()
        while time.monotonic() - t0 < seconds:
            await sub.wait(0.5)
            samples, _, _ = sub.take()
            now = time.monotonic()
            times += [now] * len(samples)
        sub.close()
        gaps = [b - a for a, b in zip(times, times[1:], strict=False) if b > a]
        return len(times) / seconds, max(gaps) if gaps else 0.0

    rate0, gap0 = await sample_stats()
    stop = False
    sent = 0

    async def writer(method: str, path: str) -> None:
        nonlocal sent
        while not stop:
            await c.request(method, path, headers=H("tok-teach"))
            sent += 1

    # the same burst of requests the audit does not record (reads), for comparison: in-process
    # the requests and the telemetry share one event loop and, here, two cores
    tasks = [asyncio.create_task(writer("GET", "/api/v1/arms/angler/state")) for _ in range(8)]
    rate_r, gap_r = await sample_stats()
    stop = True
    await asyncio.gather(*tasks)
    stop, sent = False, 0
    w0 = store.audit_written
    t0 = time.monotonic()
    tasks = [asyncio.create_task(writer("POST", "/api/v1/arms/angler/stop")) for _ in range(8)]
    rate1, gap1 = await sample_stats()
    stop = True
    await asyncio.gather(*tasks)
    while store.health().pending:  # noqa: ASYNC110 - a thread's count, no event to wait on
        await asyncio.sleep(0.01)
    dt = time.monotonic() - t0
    print(f"audit: {(store.audit_written - w0) / dt:.0f} records written per second "
          f"({sent} requests, all recorded: {store.audit_written - w0 >= sent})")
    print(f"telemetry (rbe3001 samples per second, worst gap): idle {rate0:.0f}/s, "
          f"{gap0 * 1000:.0f} ms; during a burst of reads (not audited) {rate_r:.0f}/s, "
          f"{gap_r * 1000:.0f} ms; during the same burst of audited stops {rate1:.0f}/s, "
          f"{gap1 * 1000:.0f} ms")


async def main() -> None:
    app = create_app(settings())
    async with app.router.lifespan_context(app):
        await asyncio.sleep(1.0)
        transport = httpx.ASGITransport(app=app)
        async with httpx.AsyncClient(transport=transport, base_url="http://bench",
                                     timeout=30.0) as c:
            await handoffs_per_minute(c, app)
            await waits(c, app)
            await audit_rate(c, app)


if __name__ == "__main__":
    asyncio.run(main())
