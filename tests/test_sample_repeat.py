"""A poll reply byte for byte the last one (an arm at rest) is published as the last sample
again, with its own read time and the next seq, without parsing, converting and checking the
same bytes (issue 27: app/device/owner.py `_repeat`, app/links/threaded.py `take_repeats`; a
run of them published in one step: `TelemetryHub.publish_run`).

What a subscriber sees must not change: each test runs the arm type's simulator over a real
loopback socket and the thread link, and compares the samples of a driver that repeats with
those of one that takes the full path for every reply (`repeat_samples = False`), value for
value; and shows that whatever a sample is made from and changes while the replies repeat (a
tare, a new zero, a move) shows in the next sample as the full path would show it."""

from __future__ import annotations

import asyncio
import contextlib
import json
import time
from collections.abc import AsyncIterator

import numpy as np
import pytest
from _tcp import serving
from _wait import wait_for

from app.arms.dynamixel.driver import DynamixelDriver
from app.arms.loading import load_profile
from app.arms.openmanipulator_x.driver import OmxDriver
from app.arms.rbe3001.driver import Rbe3001Driver
from app.device.driver import Driver
from app.device.factory import make_sim_device
from app.links.threaded import ThreadLink
from app.sim.serve import serve_tcp
from app.telemetry.hub import TelemetryHub
from protocol import rbe3001 as rb

DRIVERS = {"rbe3001": Rbe3001Driver, "angler": DynamixelDriver,
           "openmanipulator_x": OmxDriver}


@contextlib.asynccontextmanager
async def arm(name: str, repeat: bool = True) -> AsyncIterator[Driver]:
    """A driver over a ThreadLink to the arm type's simulator on a loopback socket."""
    profile = load_profile(name)
    server = await serve_tcp(make_sim_device(profile))
    driver = DRIVERS[name](profile, ThreadLink(f"socket://127.0.0.1:{server.port}"),
                           TelemetryHub(name))
    driver.repeat_samples = repeat
    await driver.start()
    try:
        assert await driver.wait_connected(10.0), f"never connected: {driver.link.last_error}"
        yield driver
    finally:
        await driver.close()
        await server.close()


def _take(sub) -> list[dict]:
    samples, _events, dropped = sub.take()
    assert dropped == 0
    return [json.loads(s) for s in samples]


def _values(sample: dict) -> str:
    """What a sample says besides its seq and time, as one comparable string."""
    return json.dumps({k: v for k, v in sample.items() if k not in ("seq", "time")},
                      sort_keys=True)


async def _rest_samples(driver: Driver, n: int) -> list[dict]:
    """`n` or more consecutive samples of the arm at rest (after the set-up's first polls)."""
    await wait_for(lambda: driver.stats["polls"] > 50, what="the first polls")
    latest_before = driver.hub.latest["time"]  # (a loaded machine may leave it 0.3 s old)
    sub = driver.hub.subscribe()
    try:
        seq = driver.hub.latest["seq"]
        await wait_for(lambda: driver.hub.latest["seq"] >= seq + n, what=f"{n} samples")
        samples = _take(sub)
        after = time.time()
    finally:
        sub.close()
    seqs = [s["seq"] for s in samples]
    assert seqs == list(range(seqs[0], seqs[0] + len(seqs)))  # none lost, none twice
    times = [s["time"] for s in samples]
    assert all(b > a for a, b in zip(times, times[1:], strict=False))  # each its own read time
    # the subscription starts at the latest sample, and none is stamped in the future
    assert latest_before <= times[0] and times[-1] <= after
    return samples


#: What the scripted board answers to STATUS number n: REPLIES[(n // RUN) % 3], each a run of
#: RUN equal replies (an arm at rest, then a small step: within the jump check's bound).
RUN = 15
REPLIES = [rb.encode_reply(rb.StatusReply((100.0 + 3 * k, -50.0, 20.0), (0.0, 1.5 * k, 0.0),
                                          (0.25, 0.5 + 0.01 * k, 0.125)))
           for k in range(3)]


@contextlib.asynccontextmanager
async def scripted_board() -> AsyncIterator[int]:
    """A loopback TCP board that answers the n-th STATUS of each connection with
    REPLIES[(n // RUN) % 3] (the set-up's STATUS is n = 0): two drivers get the same replies
    in the same order. Its port."""

    async def handle(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        n = 0
        with contextlib.suppress(asyncio.IncompleteReadError, ConnectionError):
            while True:
                packet = await reader.readexactly(rb.PACKET_SIZE)
                assert int.from_bytes(packet[:4], "little") == rb.CommandId.STATUS
                writer.write(REPLIES[(n // RUN) % 3])
                n += 1
        writer.close()

    async with serving(handle) as port:
        yield port


@pytest.mark.usefixtures("poll_rest")
async def test_the_same_replies_give_the_same_samples_seq_by_seq():
    """Replies that repeat in runs, the same to both drivers: each sample (seq n answers the
    n-th poll) of the driver that repeats equals, value for value, the full path's."""
    profile = load_profile("rbe3001")
    drivers: list[Driver] = []
    async with scripted_board() as port, contextlib.AsyncExitStack() as stack:
        for repeat in (True, False):
            d = Rbe3001Driver(profile, ThreadLink(f"socket://127.0.0.1:{port}"),
                              TelemetryHub("rbe3001"))
            d.repeat_samples = repeat
            await d.start()
            stack.push_async_callback(d.close)
            drivers.append(d)
        subs = [d.hub.subscribe() for d in drivers]  # (before the first sample: every seq)
        for sub in subs:
            stack.callback(sub.close)
        for d in drivers:
            assert await d.wait_connected(10.0), d.link.last_error
        await wait_for(lambda: min(d.hub.latest["seq"] for d in drivers) > 8 * RUN,
                       what="eight runs of replies")
        fast, full = ({s["seq"]: s for s in _take(sub)} for sub in subs)
        common = sorted(fast.keys() & full.keys())
        assert common[0] == 1 and len(common) > 8 * RUN
        # the three replies give the same three samples both ways, in the same order
        assert {_values(fast[n]) for n in common} == {_values(full[n]) for n in common}
        assert len({_values(fast[n]) for n in common}) == 3

        def runs(samples: dict[int, dict]) -> list[str]:
            out: list[str] = []
            for n in common:
                if not out or out[-1] != _values(samples[n]):
                    out.append(_values(samples[n]))
            return out

        assert runs(fast) == runs(full)[:len(runs(fast))] or \
            runs(full) == runs(fast)[:len(runs(full))]
        # seq n answers the board's n-th STATUS only if no reply was read without a sample
        # (a read-ahead reply dropped for a request, a late reply after a timeout: a loaded
        # machine's); then value for value, seq by seq
        if all(d.link.stats["dropped"] == 0 and d.stats["poll_failures"] == 0
               for d in drivers):
            for n in common:
                assert _values(fast[n]) == _values(full[n]), n
        assert drivers[0].stats["repeats"] > 4 * RUN and drivers[1].stats["repeats"] == 0
        for d in drivers:
            assert d.stats["corrupt"] == 0


@pytest.mark.parametrize("name", ["angler", "openmanipulator_x"])
async def test_repeated_replies_give_the_samples_the_full_path_gives(name):
    async with arm(name, repeat=True) as fast, arm(name, repeat=False) as full:
        fast_samples = await _rest_samples(fast, 60)
        full_samples = await _rest_samples(full, 60)
        assert fast.stats["repeats"] > 30  # most of them went the short way ...
        assert full.stats["repeats"] == 0  # ... and none of the reference's
        # the same replies (two simulators at rest, powered on alike): the same samples,
        # derived fields (tip, tip velocity, tip force) included
        assert {_values(s) for s in fast_samples} == {_values(s) for s in full_samples}
        assert len({_values(s) for s in fast_samples}) == 1
        assert fast_samples[-1]["tip"] is not None
        # (a reply late under a loaded machine is a failed poll, not a wrong value)
        assert fast.stats["corrupt"] == 0 and full.stats["corrupt"] == 0


@pytest.mark.usefixtures("poll_rest")
async def test_a_tare_and_a_new_zero_at_rest_show_in_the_next_samples():
    async with arm("rbe3001") as driver:
        before = await _rest_samples(driver, 30)
        assert driver.stats["repeats"] > 0
        torques = before[-1]["torques"]
        assert torques is not None and any(abs(t) > 1e-9 for t in torques)
        # a tare (the service's: a new array, on the owner task's loop, as here)
        driver.torque_tare = np.array(driver.torques_raw, dtype=float)
        repeats = driver.stats["repeats"]
        after = await _rest_samples(driver, 30)
        assert all(s["torques"] == [0.0, 0.0, 0.0] for s in after)
        assert after[0]["tip_force"] != before[-1]["tip_force"]
        # a new zero for the base joint: the positions in the new units from the next sample
        q0 = after[-1]["positions"][0]
        driver.set_home(0, q0 + 0.25)
        moved = await _rest_samples(driver, 30)
        assert all(s["positions"][0] == pytest.approx(q0 + 0.25, abs=1e-9) for s in moved)
        assert moved[0]["tip"] != after[-1]["tip"]
        assert driver.stats["repeats"] > repeats + 20  # the short way again, after each change
        assert driver.stats["corrupt"] == 0


@pytest.mark.usefixtures("poll_rest")
async def test_a_move_takes_the_full_path_and_the_rest_after_it_the_short_one():
    async with arm("rbe3001") as driver:
        await _rest_samples(driver, 10)
        sub = driver.hub.subscribe()
        try:
            polls, repeats = driver.stats["polls"], driver.stats["repeats"]
            await driver.set_pid([(300.0, 0, 0), (200.0, 0, 0), (100.0, 0, 0)])
            ticks = 4096 / (2 * np.pi)
            await wait_for(lambda: np.allclose(np.asarray(driver.positions) * ticks,
                                               [300, 200, 100], atol=15), what="the move")
            moving = driver.stats["polls"] - polls - (driver.stats["repeats"] - repeats)
            await wait_for(lambda: driver.stats["repeats"] > repeats + 20,
                           what="repeats once at rest")
            samples = _take(sub)
        finally:
            sub.close()
        assert moving > 10  # the changing replies, each parsed
        seqs = [s["seq"] for s in samples]
        assert seqs == list(range(seqs[0], seqs[0] + len(seqs)))
        base = [s["positions"][0] for s in samples]
        assert base[-1] > base[0]
        # (a reply late under a loaded machine is a failed poll, not a wrong value)
        assert driver.stats["corrupt"] == 0


def test_a_run_published_in_one_step_reads_as_each_copy_published_in_turn():
    """`publish_run` (a batch of repeated replies, app/device/owner.py `_repeat`) against
    `publish` of each copy in turn, on two arm hubs of the same arm: the same log for
    subscribers taking at every moment and rate (messages up to a time, takes, the latest
    sample and its bytes for `GET /state`), derived fields included, and whole samples for a
    listener (an estop's wait)."""
    from app.arms import model_for
    from app.telemetry.arm_hub import ArmHub

    profile = load_profile("rbe3001")
    model = model_for(profile)
    q = np.array([0.1, -0.4, 0.7])
    inputs = (q, np.zeros(3), np.array([0.05, -0.02, 0.01]))
    base = {"seq": 0, "time": 0.0, "positions": q.tolist(), "velocities": [0.0] * 3,
            "torques": inputs[2].tolist(), "tip": None, "tip_velocity": None,
            "tip_force": None, "gripper": None, "motion": None, "estop": False, "link": "up",
            "stale": False, "faults": [], "homed": [True] * 3, "calibrated": [True] * 3}
    state = {"estop": False}

    def stamp(sample: dict) -> None:
        sample["estop"] = state["estop"]
        sample["motion"] = {"id": "m1", "status": "done", "progress": 1.0}

    hubs = [ArmHub("rbe3001", stamp) for _ in range(2)]
    for h in hubs:
        h.derive_with(lambda: model)
    subs = [[h.subscribe() for _ in range(3)] for h in hubs]  # three readers each
    seen: list[list[dict]] = [[], []]
    runs = [[(1, 10.0)], [(2, 10.002), (3, 10.004), (4, 10.004)], [(5, 10.01)],
            [(k, 10.01 + 0.002 * k) for k in range(6, 16)]]
    for i, run in enumerate(runs):
        state["estop"] = i == 2  # the arm's own state changes between runs
        hubs[0].publish_run(dict(base), run, inputs)
        for seq, t in run:
            hubs[1].publish(dict(base, seq=seq, time=t), inputs)
        # readers at different moments: one takes after every run, one at the end, one reads
        # a message up to now after the second run
        for k in range(2):
            samples, _events, dropped = subs[k][0].take()
            assert dropped == 0
            seen[k] += [json.loads(s) for s in samples]
        if i == 1:
            assert subs[0][1].take_message(time.monotonic() + 1) == \
                subs[1][1].take_message(time.monotonic() + 1)
        assert hubs[0].latest_bytes == hubs[1].latest_bytes  # GET /state's body
    assert seen[0] == seen[1]
    assert [s["seq"] for s in seen[0]] == list(range(1, 16))
    assert seen[0][-1]["tip"] is not None and seen[0][-1]["tip_force"] is not None
    assert [s["estop"] for s in seen[0]][3:5] == [False, True]
    assert subs[0][2].take_message() == subs[1][2].take_message()
    assert hubs[0].published == hubs[1].published == 15
    # with a listener every copy is published whole, one by one, as `publish` does
    got: list[dict] = []
    remove = hubs[0].add_listener(got.append)
    hubs[0].publish_run(dict(base), [(16, 11.0), (17, 11.002)], inputs)
    remove()
    assert [s["seq"] for s in got] == [16, 17] and all(s["tip"] is not None for s in got)
    for pair in subs:
        for sub in pair:
            sub.close()


def test_a_run_nobody_subscribes_to_is_kept_out_of_the_collectors_sight():
    """While an arm's hub has no subscriber, `publish_run` keeps each copy but the last as its
    (seq, time) pair: a tuple of two numbers, which CPython's collector stops tracking at its
    first collection, not an object of its own a sample (a lab worker's 16 arms at rest: 32,000
    of them, most of what each full collection walked, issue 27). Nobody reads those: a
    subscriber's range begins after it came, however long its backlog. What is read is what
    `publish` of each copy gives: the latest, and every sample a subscriber takes."""
    import gc

    from app.arms import model_for
    from app.telemetry.arm_hub import ArmHub

    model = model_for(load_profile("rbe3001"))
    q = np.array([0.2, -0.3, 0.5])
    inputs = (q, np.zeros(3), np.array([0.01, 0.02, -0.03]))
    base = {"seq": 0, "time": 0.0, "positions": q.tolist(), "velocities": [0.0] * 3,
            "torques": inputs[2].tolist(), "tip": None, "tip_velocity": None,
            "tip_force": None, "gripper": None, "motion": None, "estop": False, "link": "up",
            "stale": False, "faults": [], "homed": [True] * 3, "calibrated": [True] * 3}
    hubs = [ArmHub("rbe3001", lambda sample: None) for _ in range(2)]
    for h in hubs:
        h.derive_with(lambda: model)
    runs = [[(k, 20.0 + 0.002 * k) for k in range(first, first + n)]
            for first, n in ((1, 1), (2, 50), (52, 10), (62, 49))]
    for run in runs:
        hubs[0].publish_run(dict(base), run, inputs)
        for seq, t in run:
            hubs[1].publish(dict(base, seq=seq, time=t), inputs)
    assert hubs[0].published == hubs[1].published == 110
    gc.collect()
    tracked = [e for e in hubs[0]._log if gc.is_tracked(e)]
    assert len(tracked) == len(runs), len(tracked)  # each run's last copy, the latest of its time
    assert sum(gc.is_tracked(e) for e in hubs[1]._log) == 110  # (one object a sample)
    assert hubs[0].latest_bytes == hubs[1].latest_bytes
    # a subscriber from here on, with a backlog longer than the log, takes none of the pairs
    # and reads each copy as it comes, as from `publish`
    subs = [h.subscribe(backlog=4 * h.backlog) for h in hubs]
    assert [sub.take()[0] for sub in subs] == [[], []]
    assert subs[0].initial == subs[1].initial  # (the latest, whole)
    run = [(111, 21.0), (112, 21.002)]
    hubs[0].publish_run(dict(base), run, inputs)
    for seq, t in run:
        hubs[1].publish(dict(base, seq=seq, time=t), inputs)
    taken = [[json.loads(s) for s in sub.take()[0]] for sub in subs]
    assert taken[0] == taken[1] and [s["seq"] for s in taken[0]] == [111, 112]
    assert all(s["tip"] is not None for s in taken[0])
    for sub in subs:
        sub.close()
