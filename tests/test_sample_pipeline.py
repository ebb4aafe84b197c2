"""The sample pipeline's cost rules (issue 12), as behaviour: one encoding per sample shared by
every subscriber and the state route, no task per read in the owner loop and the links, and
simulators that skip work at rest while producing the same bytes. No timing is asserted."""

from __future__ import annotations

import asyncio
import json
import threading
from collections import deque

import numpy as np
import pytest
from _wait import wait_for

from app.arms.loading import load_profile
from app.arms.rbe3001.driver import Rbe3001Driver
from app.arms.rbe3001.sim import CYCLE_S, Rbe3001Firmware
from app.device.factory import make_sim_device
from app.links.serial import SerialLink
from app.links.sim import SimLink
from app.sim.serve import serve_tcp
from app.telemetry.hub import TelemetryHub
from protocol import rbe3001 as rb


def _sample(seq: int) -> dict[str, object]:
    return {"seq": seq, "time": 1.0, "positions": [0.1 * seq, np.float64(0.5)], "estop": False}


# ------------------------------------------------------------------ the hub


def test_subscribers_share_one_encoding_and_one_message() -> None:
    hub = TelemetryHub("arm")
    a, b = hub.subscribe(), hub.subscribe()
    for k in range(1, 6):
        hub.publish(_sample(k))
    ma, mb = a.take_message(), b.take_message()
    assert ma is not None and ma is mb  # built once, shared
    msg = json.loads(ma)
    assert msg["type"] == "telemetry" and msg["arm"] == "arm" and msg["dropped"] == 0
    assert [s["seq"] for s in msg["samples"]] == [1, 2, 3, 4, 5]
    assert msg["samples"][0]["positions"] == [0.1, 0.5]  # numpy scalars encoded as numbers
    assert a.take_message() is None  # nothing new
    # the state route's bytes are the same encoding as the stream's
    assert hub.latest_bytes == json.dumps(msg["samples"][-1], separators=(",", ":")).encode()
    assert hub.latest_json == hub.latest_bytes.decode()


def test_take_message_until_keeps_later_samples_for_the_next_batch() -> None:
    hub = TelemetryHub("arm")
    sub = hub.subscribe()
    for k in (1, 2, 3):
        hub.publish(_sample(k))
    # publish times 10, 20, 30 s: a batch cut at 25 s holds samples 1 and 2, and 3 waits
    hub._stamps = deque([10.0, 20.0, 30.0], maxlen=hub._stamps.maxlen)
    first = json.loads(sub.take_message(until=25.0) or "{}")
    assert [s["seq"] for s in first["samples"]] == [1, 2]
    assert sub.take_message(until=25.0) is None
    second = json.loads(sub.take_message(until=31.0) or "{}")
    assert [s["seq"] for s in second["samples"]] == [3]


def test_backlog_bound_counts_drops_per_subscriber() -> None:
    hub = TelemetryHub("arm", backlog=50)
    slow = hub.subscribe(backlog=5)
    fast = hub.subscribe()
    for k in range(1, 13):
        hub.publish(_sample(k))
    samples, _, dropped = slow.take()
    assert [json.loads(s)["seq"] for s in samples] == [8, 9, 10, 11, 12] and dropped == 7
    assert hub.dropped_total == 7  # what the subscribers were told, all together
    msg = json.loads(fast.take_message() or "{}")
    assert len(msg["samples"]) == 12 and msg["dropped"] == 0
    for k in range(13, 20):
        hub.publish(_sample(k))
    msg = json.loads(slow.take_message() or "{}")
    assert [s["seq"] for s in msg["samples"]] == [15, 16, 17, 18, 19] and msg["dropped"] == 2
    assert hub.dropped_total == 9
    assert fast.take_message() is not None and hub.dropped_total == 9  # fast lost nothing


def test_a_larger_backlog_grows_the_shared_log() -> None:
    hub = TelemetryHub("arm", backlog=4)
    sub = hub.subscribe(backlog=10)
    for k in range(1, 11):
        hub.publish(_sample(k))
    samples, _, dropped = sub.take()
    assert len(samples) == 10 and dropped == 0


async def test_publish_from_another_thread_is_gap_free_and_wakes_a_waiter() -> None:
    hub = TelemetryHub("arm", backlog=100_000)
    hub.publish(_sample(0))
    sub = hub.subscribe()
    assert sub.initial is not None and json.loads(sub.initial)["seq"] == 0

    def publisher() -> None:
        for k in range(1, 20_001):
            hub.publish(_sample(k))

    waiting = asyncio.ensure_future(sub.wait(5.0))
    await asyncio.sleep(0)
    t = threading.Thread(target=publisher)
    t.start()
    assert await waiting is True
    seqs: list[int] = []
    while t.is_alive() or sub.pending:
        samples, _, dropped = sub.take()
        assert dropped == 0
        seqs += [json.loads(s)["seq"] for s in samples]
        await asyncio.sleep(0.001)
    t.join()
    assert seqs == list(range(1, 20_001))


async def test_wait_times_out_without_a_sample() -> None:
    hub = TelemetryHub("arm")
    sub = hub.subscribe()
    assert await sub.wait(0.01) is False
    hub.event("estop", latched=True)
    assert await sub.wait(0.01) is True
    assert '"event":"estop"' in sub.take_events()[0]


# ------------------------------------------------------------------ no task per read


class _TaskCounter:
    """Counts the tasks created on the running loop (the loop's own task factory hook)."""

    def __init__(self) -> None:
        self.count = 0

    def __call__(self, loop, coro, **kwargs):  # type: ignore[no-untyped-def]
        self.count += 1
        return asyncio.Task(coro, loop=loop, **kwargs)


async def _polls_without_tasks(driver: Rbe3001Driver) -> None:
    await driver.start()
    assert await driver.wait_connected(10.0)
    loop = asyncio.get_running_loop()
    counter = _TaskCounter()
    published0 = driver.hub.published
    loop.set_task_factory(counter)
    try:  # (wait_for creates no task: it polls with asyncio.sleep)
        await wait_for(lambda: driver.hub.published - published0 >= 10, what="10 polls")
    finally:
        loop.set_task_factory(None)
    assert driver.hub.published - published0 >= 10  # answered polls, each a sample
    assert counter.count == 0  # asyncio.wait_for made one per read


async def test_owner_loop_and_sim_link_poll_without_creating_tasks() -> None:
    profile = load_profile("rbe3001")
    driver = Rbe3001Driver(profile, SimLink(make_sim_device(profile)), TelemetryHub("rbe3001"))
    try:
        await _polls_without_tasks(driver)
    finally:
        await driver.close()


async def test_serial_link_polls_without_creating_tasks() -> None:
    profile = load_profile("rbe3001")
    server = await serve_tcp(make_sim_device(profile))
    link = SerialLink(f"socket://127.0.0.1:{server.port}")
    driver = Rbe3001Driver(profile, link, TelemetryHub("rbe3001"))
    try:
        await _polls_without_tasks(driver)
    finally:
        await driver.close()
        await server.close()


async def test_a_request_wakes_the_idle_owner_loop_before_its_next_poll() -> None:
    base = load_profile("rbe3001")  # polled every 5 s: the owner loop idles between polls
    profile = base.model_copy(update={"link": base.link.model_copy(update={"poll_hz": 0.2})})
    driver = Rbe3001Driver(profile, SimLink(make_sim_device(profile)), TelemetryHub("rbe3001"))
    await driver.start()
    try:
        assert await driver.wait_connected(10.0)
        await wait_for(lambda: driver.hub.published >= 1, what="the first poll done")  # idle now
        polls = driver.stats["polls"]
        reply = await driver.status()  # served at once, not after the next poll
        assert isinstance(reply, rb.StatusReply) and driver.stats["polls"] == polls
    finally:
        await driver.close()


# ------------------------------------------------------------------ derived values at rest


def test_a_sample_at_rest_reuses_derived_values_that_equal_a_fresh_computation() -> None:
    profile = load_profile("rbe3001")
    driver = Rbe3001Driver(profile, SimLink(make_sim_device(profile)), TelemetryHub("rbe3001"))
    q, qd, tau = np.array([0.1, 0.6, 0.3]), np.zeros(3), np.array([0.01, -0.2, 0.05])
    driver._publish(q, qd, tau, stale=False)
    first = driver.hub.latest
    driver._publish(q.copy(), qd.copy(), tau.copy(), stale=False)
    second = driver.hub.latest
    assert first is not None and second is not None and second["seq"] == first["seq"] + 1
    assert second["tip"] is first["tip"] and second["tip_force"] is first["tip_force"]
    np.testing.assert_allclose([second["tip"][k] for k in "xyz"], driver.model.fk(q))
    q2 = q + 0.05
    driver._publish(q2, qd, tau, stale=False)
    third = driver.hub.latest
    assert third is not None
    np.testing.assert_allclose([third["tip"][k] for k in "xyz"], driver.model.fk(q2))


# ------------------------------------------------------------------ simulators at rest


class _AlwaysStepping(Rbe3001Firmware):
    """The firmware sim with its rest shortcut off: every cycle computed."""

    def _still(self) -> bool:
        return False


def test_rbe3001_sim_at_rest_answers_the_same_bytes_as_stepping_every_cycle() -> None:
    profile = load_profile("rbe3001")
    lazy, full = Rbe3001Firmware(profile), _AlwaysStepping(profile)
    status = rb.encode_command(rb.Status())
    goal = rb.encode_command(rb.SetPid((rb.JointSetpoint(300.0, 0, 0),
                                        rb.JointSetpoint(500.0, 0, 0),
                                        rb.JointSetpoint(-200.0, 0, 0))))
    t, skipped = 100.0, 0
    for k in range(3000):  # 6 s at 500 Hz: a move, settling, a long rest, a second move
        t += 0.002
        packet = goal if k in (10, 2000) else status
        c0 = lazy.cycles
        assert lazy.receive(packet, t) == full.receive(packet, t), k
        skipped += lazy._rest is not None and lazy.cycles > c0
    assert lazy.cycles == full.cycles and lazy.q == full.q
    # the controller's running means of the error, taken on through the skipped cycles
    assert lazy._integral == full._integral and lazy._last_error == full._last_error
    assert skipped > 500  # it did rest (and skip) for a good part of the run
    assert t - 100.0 > 1000 * CYCLE_S


@pytest.mark.parametrize("name", ["rbe3001", "angler"])
def test_state_route_bytes_are_the_hub_encoding(name: str) -> None:
    hub = TelemetryHub(name)
    hub.publish({"seq": 1, "tip": {"x": 0.1, "y": -0.0, "z": 1e-17}, "motion": None})
    assert hub.latest_bytes == b'{"seq":1,"tip":{"x":0.1,"y":-0.0,"z":1e-17},"motion":null}'


# ------------------------------------------------------------------ the state route


async def test_state_fast_path_answers_the_published_bytes_and_leaves_errors_alone() -> None:
    from conftest import make_settings, running_client


    settings = make_settings(operator_tokens="op-token", viewer_tokens="view-token")
    async with running_client(settings) as (app, client):
        hub = app.state.services["rbe3001"].hub
        ok = {"authorization": "Bearer view-token"}
        r = await client.get("/api/v1/arms/rbe3001/state", headers=ok)
        layer, ours = app.middleware_stack, []  # built by the first request
        while layer is not None:
            if type(layer).__module__.startswith("app."):
                ours.append(type(layer).__name__)
            layer = getattr(layer, "app", None)
        # outside every other layer but HEAD's (HEAD as GET: app/web/middleware.py)
        assert ours[:2] == ["HeadAsGet", "StateFastPath"], ours
        assert ours.count("StateFastPath") == 1, ours
        assert r.status_code == 200 and r.headers["content-type"] == "application/json"
        body = json.loads(r.content)
        assert body["seq"] <= hub.latest["seq"] and set(body) == set(hub.latest)
        # the same request down the full stack (an Origin sends it there) answers the same
        full = await client.get("/api/v1/arms/rbe3001/state",
                                headers={**ok, "origin": "http://testserver"})
        assert full.status_code == 200 and full.headers["content-type"] == "application/json"
        assert set(json.loads(full.content)) == set(body)
        # errors still come from the regular route, with their codes
        r = await client.get("/api/v1/arms/rbe3001/state")
        assert r.status_code == 401 and r.json()["code"] == "unauthorized"
        r = await client.get("/api/v1/arms/rbe3001/state",
                             headers={"authorization": "Bearer wrong"})
        assert r.status_code == 401 and r.json()["code"] == "unauthorized"
        r = await client.get("/api/v1/arms/nope/state", headers=ok)
        assert r.status_code == 404 and r.json()["code"] == "unknown_arm"
        r = await client.get("/api/v1/arms/" + "x" * 65 + "/state", headers=ok)
        assert r.status_code in (404, 422) and "code" in r.json()
        r = await client.post("/api/v1/arms/rbe3001/state", headers=ok)
        assert r.status_code == 405
        # the OpenAPI document still shows the response model
        doc = (await client.get("/openapi.json")).json()
        ok200 = doc["paths"]["/api/v1/arms/{arm}/state"]["get"]["responses"]["200"]
        assert ok200["content"]["application/json"]["schema"]["$ref"].endswith("/Sample")


async def test_estop_fast_path_latches_on_the_head_of_a_request_the_route_accepts() -> None:
    from conftest import make_settings, running_client

    settings = make_settings(operator_tokens="op-token", viewer_tokens="view-token")
    async with running_client(settings) as (app, client):
        svc = app.state.services["rbe3001"]
        await client.get("/api/v1/health")  # builds the middleware stack
        layer = app.middleware_stack
        while type(layer).__name__ != "StateFastPath":  # (below Starlette's error layer)
            layer = layer.app

        def scope(path: str, *headers: tuple[bytes, bytes]) -> dict[str, object]:
            return {"type": "http", "method": "POST", "path": path,
                    "headers": [(b"host", b"armserver.test"), *headers]}

        async def latched_by(sc: dict[str, object]) -> bool:
            await layer._press_estop(sc)  # the head alone: nothing below it runs
            for _ in range(50):  # the press crosses into the control loop
                if svc.guard.estop:
                    return True
                await asyncio.sleep(0.01)
            return False

        ok = (b"authorization", b"Bearer view-token")
        path = "/api/v1/arms/rbe3001/estop"
        # requests the route would not take as they are: left to the full stack
        assert not await latched_by(scope(path))  # no token
        assert not await latched_by(scope(path, (b"authorization", b"Bearer wrong")))
        assert not await latched_by(scope(path, ok, (b"origin", b"http://evil.example")))
        assert not await latched_by(scope(path, ok, (b"content-length", b"5")))
        assert not await latched_by(scope("/api/v1/arms/nope/estop", ok))
        assert not await latched_by(scope("/api/v1/arms/rbe3001/stop", ok))
        # a viewer's press with an empty body latches before any layer below has run
        assert await latched_by(scope(path, ok, (b"content-length", b"0")))
        # the route's press of the same request finds the latch set and answers as before;
        # the hold was commanded once for the latch
        r = await client.post(path, headers={"authorization": "Bearer view-token"})
        assert r.status_code == 200 and r.json() == {"estop": True}
        r = await client.post("/api/v1/arms/rbe3001/move/joints",
                              json={"positions": [0.1, 0.1, 0.1]},
                              headers={"authorization": "Bearer op-token"})
        assert r.status_code == 409 and r.json()["code"] == "estop_latched"
        r = await client.delete(path, headers={"authorization": "Bearer op-token"})
        assert r.status_code == 200 and r.json() == {"estop": False}
        # through the whole stack, the fast path and the route press once each
        r = await client.post(path, headers={"authorization": "Bearer view-token"})
        assert r.status_code == 200 and svc.guard.estop


async def test_state_fast_path_keeps_an_open_servers_host_check() -> None:
    from conftest import make_settings, running_client

    async with running_client(make_settings()) as (_, client):
        r = await client.get("/api/v1/arms/rbe3001/state", headers={"host": "127.0.0.1:8000"})
        assert r.status_code == 200 and "positions" in r.json()
        r = await client.get("/api/v1/arms/rbe3001/state", headers={"host": "evil.example"})
        assert r.status_code == 400 and r.json()["code"] == "bad_host"


async def test_an_estop_latch_shows_at_once_in_a_sample_of_the_latest_reading() -> None:
    """Issue 12 (estop to a sample showing it): the latch publishes the latest reading again
    with `estop: true` before any new reading (the poll it asks for follows), so a client
    sees it without waiting a device round trip; the sample's numbers are the reading's."""
    from app.service import ArmService

    base = load_profile("rbe3001")  # polled every 10 s: no scheduled poll gets in between
    profile = base.model_copy(update={"link": base.link.model_copy(update={"poll_hz": 0.1})})
    svc = ArmService(profile)
    await svc.start()
    try:
        assert await svc.driver.wait_connected(10.0)
        await wait_for(lambda: svc.hub.published >= 1, what="the first reading out")
        seen: list[tuple[dict[str, object], int]] = []
        svc.hub.add_listener(lambda s: seen.append((dict(s), svc.driver.stats["polls"])))
        last = json.loads(svc.hub.latest_bytes)
        polls, requests = svc.driver.stats["polls"], svc.driver.stats["requests"]
        assert last["estop"] is False
        assert (await svc.latch_estop()).estop is True
        first, polls_then = seen[0]
        assert first["estop"] is True and polls_then == polls  # before any new reading
        assert first["seq"] == last["seq"] + 1  # gap-free
        for key in ("positions", "velocities", "torques", "tip", "stale"):
            assert first[key] == last[key], key
        # the hold (one SET_PID) went to the device, no poll ahead of it
        assert svc.driver.stats["requests"] == requests + 1
        assert svc.driver.stats["polls"] == polls
        assert all(s["estop"] is True for s, _ in seen)
        await svc.latch_estop()  # a press on a latched estop publishes nothing more
        n = len(seen)
        await asyncio.sleep(0.05)  # under test: nothing is published for 50 ms
        assert len(seen) == n
    finally:
        await svc.close()


async def test_a_pass_through_write_is_followed_by_a_poll() -> None:
    """A register written through the Dynamixel pass-through (a goal, the LED) shows in a
    sample one bus round trip later, not at the next scheduled poll (issue 12: goal to the
    first sample that moved)."""
    from app.device.factory import make_driver
    from protocol import mx28

    base = load_profile("angler")  # polled every 10 s
    profile = base.model_copy(update={"link": base.link.model_copy(update={"poll_hz": 0.1})})
    hub = TelemetryHub("angler")
    driver = make_driver(profile, hub, SimLink(make_sim_device(profile)))
    await driver.start()
    try:
        assert await driver.wait_connected(10.0)
        await wait_for(lambda: hub.published >= 1, what="the first sample out")
        sub = hub.subscribe()
        published = hub.published
        await driver.write_register(1, mx28.TABLE["led"], 1)  # type: ignore[attr-defined]
        assert await sub.wait(5.0)  # half the poll period: only the write's poll explains it
        assert hub.published == published + 1
    finally:
        await driver.close()


def test_a_batch_cut_before_the_newest_samples_never_reaches_past_the_log() -> None:
    hub = TelemetryHub("arm", backlog=5)
    sub = hub.subscribe()
    for k in range(1, 21):
        hub.publish(_sample(k))
    # log holds 16..20; cut after sample 18: the batch is 16..18 and 4..15 are dropped
    hub._stamps = deque([1.0, 2.0, 3.0, 4.0, 5.0], maxlen=5)
    msg = json.loads(sub.take_message(until=3.5) or "{}")
    assert [s["seq"] for s in msg["samples"]] == [16, 17, 18] and msg["dropped"] == 15
    msg = json.loads(sub.take_message() or "{}")
    assert [s["seq"] for s in msg["samples"]] == [19, 20] and msg["dropped"] == 0
