"""The MQTT bridge against a real Mosquitto (started here on a free loopback port) and the real
server (in process, or a real `armserver serve` subprocess where it must die).

What a lab screen relies on: the retained state and online flags a late subscriber gets at
once, `seq` gap-free on the telemetry topic, events at QoS 1, the server's last will when it is
killed, a broker killed and restarted mid-stream while REST and WebSocket keep serving and the
bridge resumes, and a broker that refuses our credentials reported in /api/v1/health.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import json
import logging
import os
import selectors
import signal
import socket
import time
from collections.abc import AsyncIterator, Callable
from pathlib import Path
from typing import Any

import httpx
import pytest
import websockets
from _deps import missing_message
from _mosquitto import MOSQUITTO, Broker, running_broker
from _serve import clean_env, start
from conftest import make_settings, running_client, serve_live

aiomqtt = pytest.importorskip("aiomqtt")

if MOSQUITTO is None:
    pytest.skip(missing_message("mosquitto") + "; the MQTT tests need a real broker",
                allow_module_level=True)

TIMEOUT = 15.0


@contextlib.asynccontextmanager
async def subscriber(broker: Broker, *topics: tuple[str, int], **kw: Any
                     ) -> AsyncIterator[aiomqtt.Client]:
    async with aiomqtt.Client("127.0.0.1", broker.port, **kw) as c:
        for topic, qos in topics:
            await c.subscribe(topic, qos=qos)
        yield c


async def collect(client: aiomqtt.Client, until: Callable[[dict[str, list[Any]]], bool],
                  timeout: float = TIMEOUT) -> dict[str, list[Any]]:
    """Messages by topic (payloads parsed as JSON) until `until(seen)` holds."""
    seen: dict[str, list[Any]] = {}
    async with asyncio.timeout(timeout):
        async for msg in client.messages:
            seen.setdefault(str(msg.topic), []).append(
                (json.loads(bytes(msg.payload)), msg.retain, msg.qos))  # type: ignore[arg-type]
            if until(seen):
                return seen
    raise AssertionError("unreachable")


async def wait_health(client: httpx.AsyncClient, state: str, timeout: float = TIMEOUT
                      ) -> dict[str, Any]:
    deadline = time.monotonic() + timeout
    while True:
        body = (await client.get("/api/v1/health")).json()
        if body.get("mqtt") and body["mqtt"]["state"] == state:
            return body["mqtt"]
        if time.monotonic() > deadline:
            raise AssertionError(f"bridge never {state}: {body.get('mqtt')}")
        await asyncio.sleep(0.05)


async def wait_published(client: httpx.AsyncClient, n: int = 20) -> None:
    """Until the bridge has published `n` messages: the flags and states are on the broker
    (retained), not still to come (a live delivery has no retain flag)."""
    await wait_health(client, "up")
    for _ in range(600):
        if (await client.get("/api/v1/health")).json()["mqtt"]["published"] >= n:
            return
        await asyncio.sleep(0.05)
    raise AssertionError("the bridge published nothing")


def seqs_of(messages: list[Any]) -> list[int]:
    return [s["seq"] for payload, _, _ in messages for s in payload["samples"]]


# ---------------------------------------------------------------- in process


async def test_late_subscriber_gets_retained_state_and_online_flags(tmp_path: Path) -> None:
    with running_broker(tmp_path) as broker:
        settings = make_settings(mqtt_url=broker.url, mqtt_rate=20.0)
        async with running_client(settings) as (_, client):
            up = await wait_health(client, "up")
            assert up["broker"] == broker.url and up["prefix"] == "armserver"
            await wait_published(client)
            async with subscriber(broker, ("armserver/+/state", 0), ("armserver/+/online", 1),
                                  ("armserver/server/online", 1)) as sub:
                want = {"armserver/server/online", "armserver/rbe3001/online",
                        "armserver/angler/online", "armserver/rbe3001/state",
                        "armserver/angler/state"}
                seen = await collect(sub, lambda s: want <= set(s))
            for topic in want:
                payload, retained, _ = seen[topic][0]
                assert retained, f"{topic} is not retained"
                if topic.endswith("/online"):
                    assert payload is True
            state = (await client.get("/api/v1/arms/rbe3001/state")).json()
            sample = seen["armserver/rbe3001/state"][0][0]
            assert set(sample) == set(state), "state topic is not the /state sample shape"
            assert len(sample["positions"]) == 3 and sample["link"] == "up"
            assert sample["seq"] <= state["seq"]
            health = (await client.get("/api/v1/health")).json()["mqtt"]
            assert health["connects"] == 1 and health["published"] > 0


async def test_telemetry_topic_is_every_sample_gap_free(tmp_path: Path) -> None:
    with running_broker(tmp_path) as broker:
        settings = make_settings(mqtt_url=broker.url, mqtt_rate=10.0)
        async with running_client(settings) as (app, client):
            await wait_health(client, "up")
            async with subscriber(broker, ("armserver/rbe3001/telemetry", 0)) as sub:
                seen = await collect(sub, lambda s: len(seqs_of(
                    s.get("armserver/rbe3001/telemetry", []))) >= 150)
            msgs = seen["armserver/rbe3001/telemetry"]
            for payload, retained, qos in msgs:
                assert payload["type"] == "telemetry" and payload["arm"] == "rbe3001"
                assert payload["dropped"] == 0 and not retained and qos == 0
            seqs = seqs_of(msgs)
            assert seqs == list(range(seqs[0], seqs[0] + len(seqs))), "seq has a gap"
            # batched at the bridge's rate, not one message per sample (poll rate 100 Hz)
            assert len(msgs) < len(seqs) / 3
            assert app.state.mqtt.status()["dropped_samples"] == 0


async def test_events_arrive_at_qos1(tmp_path: Path) -> None:
    with running_broker(tmp_path) as broker:
        settings = make_settings(mqtt_url=broker.url)
        async with running_client(settings) as (_, client):
            await wait_health(client, "up")
            async with subscriber(broker, ("armserver/+/events", 1)) as sub:
                assert (await client.post("/api/v1/arms/angler/estop")).status_code == 200
                assert (await client.delete("/api/v1/arms/angler/estop")).status_code == 200
                seen = await collect(sub, lambda s: len(s.get("armserver/angler/events", [])) >= 2)
            (latched, retained, qos), (released, _, qos2) = seen["armserver/angler/events"][:2]
            assert qos == 1 and qos2 == 1 and not retained
            assert latched["type"] == "event" and latched["arm"] == "angler"
            assert latched["event"] == "estop" and latched["data"] == {"latched": True}
            assert released["event"] == "estop_released"


async def test_online_flag_follows_the_link(tmp_path: Path) -> None:
    config = tmp_path / "arms.toml"
    config.write_text('[[arms]]\nprofile = "rbe3001"\n'
                      '[arms.link.faults]\ndisconnect_after_s = 1.0\nreconnect_after_s = 1.0\n')
    with running_broker(tmp_path) as broker:
        settings = make_settings(config=str(config), mqtt_url=broker.url, mqtt_rate=20.0)
        async with running_client(settings) as (_, client):
            await wait_published(client, 2)
            async with subscriber(broker, ("armserver/rbe3001/online", 1),
                                  ("armserver/rbe3001/events", 1)) as sub:
                seen = await collect(sub, lambda s: [p for p, _, _ in s.get(
                    "armserver/rbe3001/online", [])][-2:] == [False, True], timeout=20)
            flags = seen["armserver/rbe3001/online"]
            assert flags[0][0] is True and flags[0][1], "first a retained true"
            assert all(qos == 1 for _, _, qos in flags)
            events = [p["event"] for p, _, _ in seen.get("armserver/rbe3001/events", [])]
            assert "link_lost" in events


async def test_broker_refusing_our_credentials_is_reported(tmp_path: Path) -> None:
    with running_broker(tmp_path, users={"armserver": "right-pass"}) as broker:
        bad = make_settings(mqtt_url=f"mqtt://armserver:wrong-pass@127.0.0.1:{broker.port}")
        async with running_client(bad) as (_, client):
            health = await wait_health(client, "refused")
            for _ in range(3):  # it keeps trying (backoff), and keeps saying why it fails
                await asyncio.sleep(0.4)  # under test: still refused, 0.4 s on each time
                health = (await client.get("/api/v1/health")).json()["mqtt"]
                assert health["state"] == "refused", health
            assert "wrong-pass" not in json.dumps(health)
            assert health["broker"] == f"mqtt://armserver@127.0.0.1:{broker.port}"
            assert health["last_error"] and health["connects"] == 0
            body = (await client.get("/api/v1/health")).json()
            assert body["status"] == "ok", "a refusing broker does not degrade the arms"
            assert (await client.get("/api/v1/arms/rbe3001/state")).status_code == 200
        good = make_settings(mqtt_url=f"mqtt://armserver:right-pass@127.0.0.1:{broker.port}")
        async with running_client(good) as (_, client):
            await wait_health(client, "up")


async def test_a_refusal_that_swallows_the_cancel_still_lets_the_server_stop(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """Python 3.11's asyncio.wait_for, under aiomqtt's connect, returns its future's result when
    the future completed as the cancel came (CPython gh-86296): a CONNACK refusal arriving with
    the server's stop raised MqttCodeError instead of CancelledError, the bridge took it for
    one more refusal and retried for ever, and the lifespan's exit never returned (a clean
    clone's refused-credentials test hung 300 s). The connect here is that race, every time:
    it answers the cancel with the refusal."""
    entered = asyncio.Event()
    attempts = 0

    async def refused_as_the_cancel_comes(self: Any) -> Any:
        nonlocal attempts
        attempts += 1
        entered.set()
        try:
            await asyncio.get_running_loop().create_future()  # the CONNACK, never before the cancel
        except asyncio.CancelledError:
            raise aiomqtt.MqttCodeError(5, "Not authorized") from None
        raise AssertionError("unreachable")

    monkeypatch.setattr(aiomqtt.Client, "__aenter__", refused_as_the_cancel_comes)
    settings = make_settings(mqtt_url="mqtt://armserver:pass@127.0.0.1:1")
    async with asyncio.timeout(TIMEOUT):  # the stop's bound: before the fix, it never came
        async with running_client(settings) as (app, client):
            async with asyncio.timeout(TIMEOUT):
                await entered.wait()
            assert (await client.get("/api/v1/arms/rbe3001/state")).status_code == 200
    assert attempts == 1, "the bridge stopped at the swallowed cancel, not another connect"


async def test_a_broker_that_never_answers_costs_the_server_nothing() -> None:
    """A TCP peer that accepts and never answers CONNACK: the bridge times out and says so;
    the arms, REST and the WebSocket hub run as if there were no bridge."""
    silent = socket.create_server(("127.0.0.1", 0))
    accepted: list[socket.socket] = []
    silent.settimeout(0.05)
    port = silent.getsockname()[1]
    try:
        settings = make_settings(mqtt_url=f"mqtt://127.0.0.1:{port}")
        async with running_client(settings) as (app, client):
            # a backlog for the whole wait below (2 min at 500 Hz): this subscriber reads once
            sub = app.state.services["rbe3001"].hub.subscribe(backlog=60_000)
            # accept what the bridge opens, never answer it: for 2 s at least, and until it
            # has tried (bounded: 20 s)
            deadline = time.monotonic() + 20.0
            for k in itertools.count():
                with contextlib.suppress(OSError):
                    accepted.append(silent.accept()[0])
                if (k >= 40 and accepted) or time.monotonic() > deadline:
                    break
                await asyncio.sleep(0.05)
            seq0 = (await client.get("/api/v1/arms/rbe3001/state")).json()["seq"]
            health = await wait_health(client, "down", timeout=20)
            assert accepted, "the bridge never tried the broker"
            assert health["connects"] == 0 and "timed out" in health["last_error"].lower()
            seq1 = (await client.get("/api/v1/arms/rbe3001/state")).json()["seq"]
            assert seq1 > seq0
            samples, _, dropped = sub.take()
            sub.close()
            seqs = [json.loads(x)["seq"] for x in samples]
            assert dropped == 0 and seqs == list(range(seqs[0], seqs[0] + len(seqs)))
            move = await client.post("/api/v1/arms/rbe3001/move/joints",
                                     json={"positions": [0.1, 0.0, 0.0], "wait": True})
            assert move.json()["status"] == "done"
    finally:
        for c in accepted:
            c.close()
        silent.close()


async def test_without_url_there_is_no_bridge(app_client: httpx.AsyncClient) -> None:
    body = (await app_client.get("/api/v1/health")).json()
    assert body["mqtt"] is None


# ---------------------------------------------------------------- a real server process


def test_last_will_when_the_server_is_killed(tmp_path: Path) -> None:
    with running_broker(tmp_path) as broker:
        srv = start(tmp_path / "server.log",
                    env=clean_env(ARMSERVER_MQTT_URL=broker.url, ARMSERVER_MQTT_PREFIX="lab/b1"))
        proc = srv.proc
        try:
            async def scenario() -> list[bool]:
                async with subscriber(broker, ("lab/b1/server/online", 1)) as sub:
                    flags: list[bool] = []
                    async with asyncio.timeout(30):
                        async for msg in sub.messages:
                            flags.append(json.loads(bytes(msg.payload)))  # type: ignore[arg-type]
                            if flags[-1] is True and proc.poll() is None:
                                os.kill(proc.pid, signal.SIGKILL)
                                proc.wait(5)
                            elif flags[-1] is False:
                                break
                # a subscriber arriving now finds the will, retained
                async with subscriber(broker, ("lab/b1/server/online", 1)) as late:
                    async with asyncio.timeout(5):
                        async for msg in late.messages:
                            assert msg.retain
                            flags.append(json.loads(bytes(msg.payload)))  # type: ignore[arg-type]
                            break
                return flags

            flags = asyncio.run(scenario())
            assert flags[-3:] == [True, False, False], (flags, srv.tail())
            assert proc.returncode == -signal.SIGKILL
        finally:
            srv.stop()


def test_broker_killed_and_restarted_mid_stream(tmp_path: Path) -> None:
    broker = Broker(tmp_path).start()
    try:
        settings = make_settings(mqtt_url=broker.url, mqtt_rate=20.0)
        with serve_live(settings) as live:
            http = httpx.Client(base_url=live.url, timeout=10)

            def health() -> dict[str, Any]:
                return http.get("/api/v1/health").json()["mqtt"]

            def wait(state: str) -> dict[str, Any]:
                deadline = time.monotonic() + TIMEOUT
                while (h := health())["state"] != state:
                    assert time.monotonic() < deadline, f"bridge never {state}: {h}"
                    time.sleep(0.05)
                return h

            async def telemetry_seqs(seconds: float) -> list[int]:
                async with subscriber(broker, ("armserver/rbe3001/telemetry", 0)) as sub:
                    out: list[int] = []
                    with contextlib.suppress(TimeoutError):
                        async with asyncio.timeout(seconds):
                            async for msg in sub.messages:
                                body = json.loads(bytes(msg.payload))  # type: ignore[arg-type]
                                out += [s["seq"] for s in body["samples"]]
                    return out

            wait("up")
            before = asyncio.run(telemetry_seqs(1.0))
            assert before, "no telemetry before the broker died"

            broker.kill()
            down = wait("down")
            assert down["last_error"]
            # the server serves REST and WebSocket all the same, samples flowing
            s1 = http.get("/api/v1/arms/rbe3001/state").json()["seq"]

            async def ws_batch() -> list[int]:
                async with websockets.connect(
                        f"{live.ws_url}/api/v1/arms/rbe3001/telemetry?rate=20") as ws:
                    got: list[int] = []
                    while len(got) < 20:
                        msg = json.loads(await asyncio.wait_for(ws.recv(), 5))
                        if msg["type"] == "telemetry":
                            got += [s["seq"] for s in msg["samples"]]
                    return got

            got = asyncio.run(ws_batch())
            assert got[-1] > s1
            assert http.post("/api/v1/arms/rbe3001/move/joints",
                             json={"positions": [0.1, 0.0, 0.0], "wait": True}
                             ).json()["status"] == "done"

            broker.start()
            up = wait("up")
            assert up["connects"] == 2

            async def flags() -> list[Any]:
                async with subscriber(broker, ("armserver/+/online", 1),
                                      ("armserver/server/online", 1)) as sub:
                    seen = await collect(sub, lambda s: {"armserver/server/online",
                                                         "armserver/rbe3001/online"} <= set(s))
                return seen["armserver/server/online"] + seen["armserver/rbe3001/online"]

            assert all(p is True for p, _, _ in asyncio.run(flags()))
            after = asyncio.run(telemetry_seqs(1.0))
            # the broker lost its retained messages with it: the bridge published them again
            assert all(p is True and retained for p, retained, _ in asyncio.run(flags()))
            assert after and after[0] > got[-1]
            assert after == list(range(after[0], after[0] + len(after)))
            assert health()["dropped_samples"] > 0, "samples sent while down are counted"
    finally:
        broker.stop()


async def test_many_arms_publish_without_warnings(tmp_path: Path,
                                                  caplog: pytest.LogCaptureFixture) -> None:
    """Six arms: a tick's batch is two dozen publishes at once, which is what the bridge is
    for, not a backlog worth a warning per message in the server's log."""
    config = tmp_path / "lab.toml"
    config.write_text('[[arms]]\nprofile = "rbe3001"\nname = "lab"\ncount = 6\n')
    with running_broker(tmp_path) as broker:
        settings = make_settings(config=str(config), mqtt_url=broker.url, mqtt_rate=20.0)
        async with running_client(settings) as (_, client):
            await wait_published(client, 100)
            async with subscriber(broker, ("armserver/+/state", 0)) as sub:
                seen = await collect(sub, lambda s: len(s) == 6)
            assert set(seen) == {f"armserver/lab-{k}/state" for k in range(1, 7)}
    noisy = [r for r in caplog.records if r.levelno >= logging.WARNING and r.name == "mqtt"]
    assert not noisy, noisy[0].getMessage()


async def test_no_socket_writer_is_left_behind_after_a_tick(tmp_path: Path) -> None:
    """After each tick the loop watches the broker's socket for writing only while paho has
    something to write. aiomqtt adds its writer a loop iteration late; the tick had already
    written everything, and the writer added afterwards stayed, called for ever on a writable
    socket (100 % CPU in bench/mqtt.py)."""
    with running_broker(tmp_path) as broker:
        settings = make_settings(mqtt_url=broker.url, mqtt_rate=50.0)
        async with running_client(settings) as (app, client):
            await wait_published(client, 40)
            paho = app.state.mqtt._client._client
            fd = paho.socket().fileno()
            loop = asyncio.get_running_loop()
            selector = loop._selector  # type: ignore[attr-defined]
            looks = stale = 0
            for _ in range(50):  # a second: 50 ticks
                await asyncio.sleep(0.0193)  # under test: looks between the ticks, over a second
                key = selector.get_map().get(fd)
                looks += 1
                if key is not None and key.events & selectors.EVENT_WRITE and not paho.want_write():
                    stale += 1
            assert looks == 50 and stale == 0, f"a writer with nothing to write {stale} times"
            assert app.state.mqtt.status()["published"] > 80
