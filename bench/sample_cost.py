"""What one arm's sample costs the server (issue 27): CPU per sample and per arm at its poll rate.

    python bench/sample_cost.py [--model rbe3001] [--seconds 10] [--moving] [--subscribe HZ]
                                [--eager] [--profile 25] [--io thread|asyncio]
    python bench/sample_cost.py --compare [--models rbe3001,angler,openmanipulator_x]

Serves the arm type's simulated hardware with `armserver sim MODEL --listen tcp://...` in
another process, and in this one runs the arm as the server does (`ArmService` over a
`socket://` serial link, on a plain asyncio loop like the control thread's), with nobody
subscribed. Prints the samples it published, this process's CPU time per sample (µs) and per
arm at the poll rate (% of a core; the issue's goal: 3 %, 60 µs a sample at 500 Hz).
`--moving`: the arm moves back and forth all along (joint moves between a quarter and three
quarters of each joint's range), so no two readings repeat; `--subscribe HZ`: one subscriber
takes every sample, in messages at HZ (a dashboard); `--eager`: the tip, tip velocity and tip
force computed at every poll as before issue 27 (the hub's deriver off), for a before/after
ratio from one run.
`--publish-only` measures instead, for each arm type, the publishing step alone (the driver's
`_publish` of 2000 distinct readings, a moving arm's, on a simulated link; CPU time, so less
sensitive to a loaded machine): eager as before issue 27, lazy with no reader, and lazy with a
reader taking every 10 samples (a 50 Hz client of a 500 Hz arm).
`--floor` measures what any server pays for the round trip alone against the same simulator
(rbe3001 only): a STATUS request written and its 64-byte reply read at 500 Hz, once with
asyncio streams and a timer (what the owner task's machinery cannot go below), once with a
blocking socket on one thread, and once with the same loop in C (bench/floor.c, built with
the system's `cc` where there is one): the least any implementation pays, the kernel's part
(the loopback's TCP and the wake-ups) alone.
`--io thread|asyncio` picks the serial link (`[link] io`: the link on a thread of its own,
the default, or the asyncio link); `--compare` runs each of `--models` (default: the three arm
types) with both, back to back, and prints each figure with the load average and the ratio.
`--profile N` runs the window under cProfile and prints the N costliest functions (cProfile
slows what it measures: read its shares, not its times).

The machine's other load shows in the figures: on a shared machine compare runs made back to
back (ratios), not figures from different days.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import cProfile
import os
import pstats
import shutil
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import _machine  # noqa: E402

from app.arms.loading import load_profile  # noqa: E402
from app.config import homed_at_start  # noqa: E402
from app.runtime import gc_policy  # noqa: E402
from app.service import ArmService  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent


def _port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


async def _move(svc: ArmService) -> None:
    from app import schemas as s

    lo, hi = svc.model.lower, svc.model.upper
    targets = [lo + 0.25 * (hi - lo), lo + 0.75 * (hi - lo)]
    k = 0
    while True:
        record = await svc.move_joints(s.MoveJoints(positions=targets[k % 2].tolist(),
                                                    speed=0.5, wait=True))
        await record.wait()  # (the route waits for `wait`; the facade answers at the start)
        k += 1


async def _read(svc: ArmService, hz: float) -> None:
    sub = svc.hub.subscribe()
    try:
        while True:
            await asyncio.sleep(1.0 / hz)
            sub.take_message()
    finally:
        sub.close()


async def run(model: str, port: int, seconds: float, prof: cProfile.Profile | None,
              moving: bool, subscribe: float, eager: bool, io: str = "thread") -> float:
    """Runs the window; prints and returns the CPU time a sample, s."""
    base = load_profile(model).model_dump()
    base["link"].update(kind="serial", address=f"socket://127.0.0.1:{port}", io=io)
    for joint in base["joints"]:  # the simulator powers on at its known zero: no calibration
        if "zero_known" in joint:
            joint["zero_known"] = True
    from app.arms.loading import check_profile

    profile = homed_at_start(check_profile(base))
    svc = ArmService(profile)
    if eager:
        svc.hub.deriver = None
    await svc.start()
    # the server's garbage-collection policy (app/web/factory.py): the objects of the start-up
    # frozen, the young generations collected on its timer; without it CPython's own count
    # (allocations less deallocations) stays near zero while the telemetry log turns over,
    # and a collection of a growing young generation comes at random (issue 27)
    collector = gc_policy.Collector(gc_policy.moving({profile.name: svc}))
    collector.start()
    tasks: list[asyncio.Task[None]] = []
    try:
        deadline = time.monotonic() + 30
        while svc.hub.published < 100:  # noqa: ASYNC110 - a bench, polling its own arm
            if time.monotonic() > deadline:
                raise RuntimeError("the arm did not come up")
            await asyncio.sleep(0.05)
        if moving:
            tasks.append(asyncio.create_task(_move(svc)))
        if subscribe:
            tasks.append(asyncio.create_task(_read(svc, subscribe)))
        await asyncio.sleep(1.0)  # past the set-up
        await _handed_over(svc)
        n0, c0, t0 = _made(svc), os.times(), time.monotonic()
        th0 = _thread_cpu()
        if prof is not None:
            prof.enable()
        await asyncio.sleep(seconds)
        await _handed_over(svc)
        if prof is not None:
            prof.disable()
        c1 = os.times()
        th1 = _thread_cpu()
        n, wall = _made(svc) - n0, time.monotonic() - t0
        user, system = c1.user - c0.user, c1.system - c0.system
        cpu = user + system
    finally:
        for t in tasks:
            t.cancel()
        for r in await asyncio.gather(*tasks, return_exceptions=True):
            if isinstance(r, Exception):
                print(f"(the arm's task failed: {r!r})")
        await collector.close()
        await svc.close()
    rate = n / wall
    per = cpu / n
    how = ", ".join(w for w, on in (("moving", moving), (f"a reader at {subscribe:g} Hz",
                                                          bool(subscribe)),
                                     ("eager (before issue 27)", eager)) if on) or "at rest"
    print(f"{model} ({how}, io={io}): {n} samples in {wall:.1f} s ({rate:.0f}/s, poll_hz "
          f"{profile.link.poll_hz:.0f}); CPU {1e6 * per:.0f} µs a sample, "
          f"({1e6 * user / n:.0f} user, {1e6 * system / n:.0f} system), "
          f"{100 * cpu / wall:.1f} % of a core for this arm; {_machine.describe()}",
          flush=True)
    split = sorted(((th1[k] - th0.get(k, 0.0), k) for k in th1), reverse=True)
    print("  by thread: " + ", ".join(f"{name} {1e6 * c / n:.0f} µs" for c, name in split
                                      if c > 0), flush=True)
    return per


def _made(svc: ArmService) -> int:
    """The samples made so far: those published and the replies the link's thread has read
    ahead that the owner task has not yet taken (each becomes a sample). An arm at rest that
    nobody reads hands its replies over every 100 ms (app/links/threaded.py IDLE_BATCH_S):
    counting the published ones alone put up to a batch (50 samples) at either end of the
    window out of it (494/s in an 8 s window, when the poll rate was 500)."""
    prefetched = getattr(svc.driver.link, "prefetched", 0)
    return svc.hub.published + (prefetched if isinstance(prefetched, int) else 0)


async def _handed_over(svc: ArmService) -> None:
    """Returns just after the link's next hand-over of samples (at most IDLE_BATCH_S away):
    the poll thread's rounds in C (app/links/_restpoll.c) hold an arm at rest's replies until
    its batch is due, where `_made` cannot count them; a window from one hand-over to another
    holds every sample read in it (within 2 ms)."""
    first = _made(svc)
    deadline = time.monotonic() + 1.0
    while _made(svc) == first and time.monotonic() < deadline:  # noqa: ASYNC110 - a bench
        await asyncio.sleep(0.002)


def _thread_cpu() -> dict[str, float]:
    """CPU time (s) of each of this process's threads, by Python thread name
    (`_machine.threads_cpu_s`: the scheduler's count, not the ticks of /stat)."""
    names = {t.native_id: t.name for t in threading.enumerate()}
    out: dict[str, float] = {}
    for tid, s in _machine.threads_cpu_s().items():
        name = names.get(tid, f"thread {tid}")
        out[name] = out.get(name, 0.0) + s
    return out


async def publish_only() -> None:
    for name in ("rbe3001", "angler", "openmanipulator_x"):
        figures = []
        for mode in ("eager", "unread", "read"):
            svc = ArmService(homed_at_start(load_profile(name)))
            if mode == "eager":
                svc.hub.deriver = None
            await svc.start()
            try:
                while svc.hub.published < 5:  # noqa: ASYNC110 - a bench, polling its own arm
                    await asyncio.sleep(0.01)
                drv = svc.driver
                q0 = (svc.model.lower + svc.model.upper) / 2
                qd = np.full(svc.model.n, 0.1)
                tau = None if drv.torques_raw is None else np.full(svc.model.n, 0.05)
                sub = svc.hub.subscribe() if mode == "read" else None
                n = 2000
                c0 = time.process_time()
                for i in range(n):
                    drv._publish(q0 + 1e-5 * i, qd, tau, False)
                    if sub is not None and i % 10 == 9:
                        sub.take_message()
                figures.append(1e6 * (time.process_time() - c0) / n)
                if sub is not None:
                    sub.close()
            finally:
                await svc.close()
        print(f"{name}: publishing a moving arm's sample: eager {figures[0]:.0f} µs, lazy and "
              f"unread {figures[1]:.0f} µs, lazy read in tens {figures[2]:.0f} µs")


async def _floor_asyncio(port: int, n: int) -> tuple[float, float]:
    from protocol import rbe3001 as rb

    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    packet = rb.ReplyMatcher().request(rb.Status())
    loop = asyncio.get_running_loop()
    slot, c0 = loop.time(), os.times()
    for _ in range(n):
        slot += 0.002
        if (wait := slot - loop.time()) > 0:
            await asyncio.sleep(wait)
        writer.write(packet)
        await reader.readexactly(64)
    c1 = os.times()
    writer.close()
    return (c1.user - c0.user) / n, (c1.system - c0.system) / n


def _floor_blocking(port: int, n: int) -> tuple[float, float]:
    from protocol import rbe3001 as rb

    packet = rb.ReplyMatcher().request(rb.Status())
    with socket.create_connection(("127.0.0.1", port)) as sock:
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        slot, c0 = time.monotonic(), os.times()
        for _ in range(n):
            slot += 0.002
            if (wait := slot - time.monotonic()) > 0:
                time.sleep(wait)
            sock.sendall(packet)
            got = b""
            while len(got) < 64:
                got += sock.recv(64 - len(got))
        c1 = os.times()
    return (c1.user - c0.user) / n, (c1.system - c0.system) / n


def _wait_listening(port: int, timeout: float = 30.0) -> None:
    deadline = time.monotonic() + timeout
    while True:
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=1):
                return
        except OSError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.1)


def _floor_compiled(port: int, n: int) -> tuple[float, float] | str:
    """`_floor_blocking`'s loop in C (bench/floor.c, built here with the system's `cc`): what
    a server in any language pays at least; or why it could not run."""
    from protocol import rbe3001 as rb

    cc = shutil.which("cc") or shutil.which("gcc")
    if cc is None:
        return "no C compiler (`cc`) on this machine"
    packet = rb.ReplyMatcher().request(rb.Status())
    with tempfile.TemporaryDirectory() as folder:
        exe = str(Path(folder) / "floor")
        built = subprocess.run([cc, "-O2", "-o", exe, str(ROOT / "bench" / "floor.c")],
                               capture_output=True, text=True)
        if built.returncode != 0:
            return f"bench/floor.c did not build: {built.stderr.strip()[:200]}"
        ran = subprocess.run([exe, str(port), str(n), packet.hex(), "64"],
                             capture_output=True, text=True)
        if ran.returncode != 0:
            return f"bench/floor.c failed: {ran.stderr.strip()[:200]}"
    user, system = (float(v) * 1e-6 for v in ran.stdout.split())
    return user, system


def floor(port: int, seconds: float) -> None:
    n = int(500 * seconds)
    for how, got in (("asyncio streams", asyncio.run(_floor_asyncio(port, n))),
                     ("blocking socket", _floor_blocking(port, n)),
                     ("blocking socket in C", _floor_compiled(port, n))):
        if isinstance(got, str):
            print(f"round trip alone, {how}: not measured: {got}")
            continue
        user, system = got
        print(f"round trip alone, {how}: {1e6 * (user + system):.0f} µs a poll ({1e6 * user:.0f}"
              f" user, {1e6 * system:.0f} system), {5e4 * (user + system):.1f} % of a "
              "core at 500 Hz")


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--model", default="rbe3001")
    p.add_argument("--seconds", type=float, default=10.0)
    p.add_argument("--profile", type=int, default=0, metavar="N")
    p.add_argument("--moving", action="store_true")
    p.add_argument("--subscribe", type=float, default=0.0, metavar="HZ")
    p.add_argument("--eager", action="store_true")
    p.add_argument("--publish-only", action="store_true")
    p.add_argument("--floor", action="store_true")
    p.add_argument("--io", choices=("thread", "asyncio"), default="thread")
    p.add_argument("--compare", action="store_true")
    p.add_argument("--pin", action="store_true",
                   help="this process (the server's side) on the first CPU, the simulator on "
                        "the others, as the issue measured")
    p.add_argument("--models", default="rbe3001,angler,openmanipulator_x")
    args = p.parse_args()
    if args.publish_only:
        asyncio.run(publish_only())
        return 0
    if args.compare:
        return compare(args.models.split(","), args.seconds, args.moving, args.subscribe,
                       args.pin)
    with _simulator(args.model, args.pin) as port:
        if args.floor:
            floor(port, args.seconds)
            return 0
        prof = cProfile.Profile() if args.profile else None
        asyncio.run(run(args.model, port, args.seconds, prof, args.moving, args.subscribe,
                        args.eager, args.io))
        if prof is not None:
            pstats.Stats(prof).sort_stats("tottime").print_stats(args.profile)
    return 0


@contextlib.contextmanager
def _simulator(model: str, pin: bool = False) -> Iterator[int]:
    """`armserver sim MODEL` on a loopback port, in its own process: its port. `pin`: this
    process (the server's side) on the first CPU, the simulator on the others, as the issue
    measured (and bench/lab.py --pin, bench/peers.py)."""
    port = _port()
    env = {k: v for k, v in os.environ.items() if not k.startswith("ARMSERVER_")}
    sim = subprocess.Popen([sys.executable, "-m", "app.cli", "sim", model, "--listen",
                            f"tcp://127.0.0.1:{port}"], cwd=ROOT, env=env,
                           stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    cpus = sorted(os.sched_getaffinity(0))
    pinned = pin and len(cpus) > 1
    if pinned:
        os.sched_setaffinity(sim.pid, set(cpus[1:]))
        os.sched_setaffinity(0, {cpus[0]})
    try:
        _wait_listening(port)
        yield port
    finally:
        if pinned:
            os.sched_setaffinity(0, set(cpus))
        sim.terminate()
        sim.wait(10)


def compare(models: list[str], seconds: float, moving: bool, subscribe: float,
            pin: bool = False) -> int:
    """Each model with the asyncio link, then the thread link, then both again (A B B A), a
    fresh simulator each: CPU a sample and the ratio thread / asyncio of the means."""
    rows = []
    for model in models:
        per: dict[str, list[float]] = {"asyncio": [], "thread": []}
        for io in ("asyncio", "thread", "thread", "asyncio"):
            with _simulator(model, pin) as port:
                per[io].append(asyncio.run(run(model, port, seconds, None, moving, subscribe,
                                               False, io)))
        a, t = (sum(per[k]) / len(per[k]) for k in ("asyncio", "thread"))
        rows.append((model, a, t))
    print("\n| arm | asyncio link, µs a sample | thread link | thread / asyncio |")
    print("|---|---|---|---|")
    for model, a, t in rows:
        print(f"| {model} | {1e6 * a:.0f} | {1e6 * t:.0f} | {t / a:.2f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
