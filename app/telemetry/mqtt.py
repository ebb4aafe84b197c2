"""Lab-wide telemetry: a read-only bridge from the arms' telemetry hubs to an MQTT broker.

Started when `ARMSERVER_MQTT_URL` is set (API.md, "Lab-wide telemetry over MQTT"). Topics under
`{prefix}`:

- `{prefix}/{arm}/state`      retained, QoS 0: the latest sample, every 1/rate s
- `{prefix}/{arm}/telemetry`  QoS 0: every sample since the last message, the WebSocket message
                              shape (`{"type":"telemetry","arm",..,"samples",..,"dropped"}`)
- `{prefix}/{arm}/events`     QoS 1: each event, the WebSocket event shape
- `{prefix}/{arm}/online`     retained, QoS 1: `true` / `false` as the arm's link is up or not
- `{prefix}/server/online`    retained, QoS 1: `true`; `false` is our last will, and what we
                              publish ourselves on a clean shutdown

The bridge subscribes to each hub exactly as a WebSocket client does (`hub.subscribe()`, then
`take()` the encoded samples and events): the hub's bounded backlog is the bridge's buffer, so
the link task never waits for the broker and a broker that is down or slow costs the server
the samples it cannot send (counted, and reported in the next message's `dropped`), never
memory or time. One task does everything: connect (with capped exponential backoff), then every
1/rate s take what each hub has and publish it. The server subscribes to nothing.

The QoS 0 messages of a tick (telemetry and state, two per arm) go straight to paho's
outgoing queue as bytes, in one synchronous pass, not one aiomqtt coroutine each (a gathered
coroutine is a Task: two thirds of the bridge's CPU went there). Their bound is the tick: while
the broker has not taken the previous tick's last message, the next tick sends nothing and the
samples wait in the hub (bounded, counted); 5 s of that and the bridge reconnects. The QoS 1
messages (events, online flags: rare) go through aiomqtt, which waits for their PUBACKs.
What this takes of aiomqtt's and paho's internals (the paho client aiomqtt holds, the socket
writer aiomqtt adds late) is in app/doors/aiomqtt.py and app/doors/paho.py, nowhere else.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import socket
import time
import uuid
from collections import deque
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Literal

import aiomqtt
import paho.mqtt.client as mqtt
from aiomqtt.exceptions import MqttConnectError

from app.config.settings import parse_broker_url
from app.doors import aiomqtt as aiomqtt_door
from app.runtime.tasks import cancel_and_wait

if TYPE_CHECKING:
    from app.config import Settings
    from app.service import ArmService
    from app.telemetry.hub import Subscription

log = logging.getLogger(__name__)

#: Backoff between connection attempts, s: doubles from MIN up to MAX.
BACKOFF_MIN_S = 0.2
BACKOFF_MAX_S = 5.0
#: A tick's publishes that take longer than this mean the broker is stuck: reconnect.
PUBLISH_TIMEOUT_S = 5.0
#: Events kept for the broker while it is away (the oldest go first, counted).
EVENT_BUFFER = 256
#: Samples per arm kept while the broker is away (the hub drops the oldest beyond, counted).
SAMPLE_BUFFER = 2000

BridgeState = Literal["connecting", "up", "down", "refused"]


@dataclass
class _ArmOut:
    """What the bridge tracks for one arm."""

    svc: ArmService
    sub: Subscription
    topic: str
    online: bool | None = None  # last value published in this session (None: not yet)
    latest: str | None = None
    events: deque[str] = field(default_factory=lambda: deque(maxlen=EVENT_BUFFER))
    dropped: int = 0  # samples lost, to report in the next telemetry message
    state_sent: bool = False  # the retained state published in this session


class MqttBridge:
    """The bridge for one server's arms. `start()` in the lifespan, `close()` at its end."""

    def __init__(self, services: Mapping[str, ArmService], url: str, prefix: str = "armserver",
                 rate_hz: float = 10.0) -> None:
        self.broker = parse_broker_url(url)
        self.prefix = prefix.strip("/")
        self.period = 1.0 / rate_hz
        self.rate_hz = rate_hz
        self._services = services
        self._arms: list[_ArmOut] = []
        self._task: asyncio.Task[None] | None = None
        self._client: aiomqtt.Client | None = None
        self.identifier = f"armserver-{uuid.uuid4().hex[:12]}"
        # health
        self.state: BridgeState = "connecting"
        self.last_error: str | None = None
        self.connects = 0
        self.published = 0
        self.dropped_samples = 0
        self.dropped_events = 0
        #: CPU time (this thread's) spent in ticks: collect, build, queue, write (bench figure)
        self.tick_cpu_s = 0.0
        self.connected_since: float | None = None
        # the last tick's QoS 0 messages: the last one's info (written to the socket yet?),
        # since when it has waited, and the samples it carried (lost if the session ends first)
        self._pending: mqtt.MQTTMessageInfo | None = None
        self._pending_since = 0.0
        self._in_flight: list[tuple[_ArmOut, int]] = []

    # ------------------------------------------------------------ lifecycle

    def start(self) -> None:
        for name, svc in self._services.items():
            sub = svc.subscribe(SAMPLE_BUFFER)
            self._arms.append(_ArmOut(svc, sub, f"{self.prefix}/{name}"))
        self._task = asyncio.create_task(self._run(), name="mqtt-bridge")

    async def close(self) -> None:
        """Say goodbye (server and arms offline, retained) if connected, then stop."""
        task, self._task = self._task, None
        if task is None:
            return
        client = self._client
        if client is not None and self.state == "up":
            with contextlib.suppress(aiomqtt.MqttError, TimeoutError, OSError):
                async with asyncio.timeout(2.0):
                    await asyncio.gather(*(
                        client.publish(f"{a.topic}/online", b"false", qos=1, retain=True)
                        for a in self._arms))
                    await client.publish(self._server_topic, b"false", qos=1, retain=True)
        # again until it ends: a refusal arriving with the cancel ate it under aiomqtt's
        # asyncio.wait_for (CPython gh-86296), and one `await task` waited for ever (a clean
        # clone's test hung 300 s)
        await cancel_and_wait(task)
        for a in self._arms:
            a.sub.close()

    @property
    def _server_topic(self) -> str:
        return f"{self.prefix}/server/online"

    def status(self) -> dict[str, object]:
        """The bridge's state for /api/v1/health."""
        return {"state": self.state, "broker": self.broker.public, "prefix": self.prefix,
                "rate_hz": self.rate_hz, "last_error": self.last_error,
                "connects": self.connects, "published": self.published,
                "dropped_samples": self.dropped_samples, "dropped_events": self.dropped_events,
                "tick_cpu_s": round(self.tick_cpu_s, 6)}

    # ------------------------------------------------------------ the one task

    async def _run(self) -> None:
        backoff = BACKOFF_MIN_S
        while True:  # state stays what the last attempt found (refused, down) until one succeeds
            try:
                await self._session()
            except aiomqtt.MqttCodeError as exc:
                self._down(exc, refused=_is_refusal(exc))
            except (aiomqtt.MqttError, OSError, TimeoutError) as exc:
                self._down(exc, refused=False)
            except asyncio.CancelledError:
                raise
            except Exception as exc:  # a bug must not end the bridge: log, back off, retry
                log.exception("mqtt bridge failed")
                self._down(exc, refused=False)
            else:
                backoff = BACKOFF_MIN_S
            if self.connected_since is not None and time.monotonic() - self.connected_since > 5:
                backoff = BACKOFF_MIN_S  # a session that lasted starts the backoff afresh
            self.connected_since = None
            # keep the buffers bounded while the broker is away: count what we cannot keep
            await self._drain_while(backoff)
            backoff = min(BACKOFF_MAX_S, backoff * 2)

    def _down(self, exc: BaseException, refused: bool) -> None:
        was = self.state
        self.state = "refused" if refused else "down"
        self.last_error = f"{type(exc).__name__}: {exc}"[:300]
        aiomqtt_door.retrieve_disconnection(self._client)  # or asyncio logs it as an error
        self._client = None
        if self._pending is not None and not self._pending.is_published():
            self._lost_in_flight(self._in_flight)
        self._pending, self._in_flight = None, []
        for a in self._arms:
            a.online = None  # republish every flag and state on the next connect
            a.state_sent = False
        if was != self.state:
            log.warning("mqtt broker %s %s: %s", self.broker.public, self.state, self.last_error)

    async def _drain_while(self, seconds: float) -> None:
        loop = asyncio.get_running_loop()
        end = loop.time() + seconds
        while (left := end - loop.time()) > 0:
            await asyncio.sleep(min(left, self.period))
            for a in self._arms:
                self._collect(a, keep_samples=False)

    def _collect(self, a: _ArmOut, keep_samples: bool = True) -> list[str]:
        """Take the hub's pending samples and events for one arm; the samples (if kept)."""
        samples, events, lost = a.sub.take()
        a.dropped += lost
        self.dropped_samples += lost
        if samples:
            a.latest = samples[-1]
        if not keep_samples:
            a.dropped += len(samples)
            self.dropped_samples += len(samples)
            samples = []
        for e in events:
            if len(a.events) == a.events.maxlen:
                self.dropped_events += 1
            a.events.append(e)
        return samples

    async def _session(self) -> None:
        b = self.broker
        will = aiomqtt.Will(self._server_topic, b"false", qos=1, retain=True)
        tls = {"tls_params": aiomqtt.TLSParameters()} if b.tls else {}
        async with aiomqtt.Client(
            b.host, b.port, username=b.username, password=b.password, identifier=self.identifier,
            will=will, keepalive=10, timeout=PUBLISH_TIMEOUT_S,
            max_queued_outgoing_messages=10_000, **tls,  # type: ignore[arg-type]  # tls_params only
        ) as client:
            # a tick publishes up to 4 messages per arm at once: not a "concerning number of
            # pending calls" (aiomqtt warns, once per publish, above its threshold)
            client.pending_calls_threshold = 4 * len(self._arms) + EVENT_BUFFER * len(self._arms)
            self._client = client
            self.connects += 1
            self.state = "up"
            self.last_error = None
            self.connected_since = time.monotonic()
            log.info("mqtt: publishing to %s under %s/", b.public, self.prefix)
            await client.publish(self._server_topic, b"true", qos=1, retain=True)
            self.published += 1
            loop = asyncio.get_running_loop()
            next_tick = loop.time()
            while True:
                cpu = time.thread_time()
                async with asyncio.timeout(PUBLISH_TIMEOUT_S):
                    await self._tick(client)
                self.tick_cpu_s += time.thread_time() - cpu
                next_tick += self.period
                now = loop.time()
                if next_tick < now:  # fell behind (slow broker): do not burst
                    next_tick = now + self.period
                await asyncio.sleep(next_tick - now)

    async def _tick(self, client: aiomqtt.Client) -> None:
        pending = self._pending
        if pending is not None and not pending.is_published():
            # the broker has not taken the last tick's messages: leave the samples in the hubs
            # (bounded there, drops counted) rather than queue more in paho
            if time.monotonic() - self._pending_since > PUBLISH_TIMEOUT_S:
                raise TimeoutError(f"the broker took no message for {PUBLISH_TIMEOUT_S:g} s")
            return
        paho = aiomqtt_door.paho_client(client)  # QoS 0 needs no await
        qos1 = []
        sent: list[tuple[_ArmOut, int]] = []
        info: mqtt.MQTTMessageInfo | None = None
        count = 0
        for a in self._arms:
            samples = self._collect(a)
            online = a.svc.link_status().connected
            if online != a.online:
                qos1.append(client.publish(f"{a.topic}/online", b"true" if online else b"false",
                                           qos=1, retain=True, timeout=math.inf))
                a.online = online
            while a.events:
                qos1.append(client.publish(f"{a.topic}/events", a.events.popleft(), qos=1,
                                           timeout=math.inf))
            if samples or a.dropped:
                msg = a.sub.telemetry_message(samples, a.dropped).encode()
                a.dropped = 0
                info = paho.publish(f"{a.topic}/telemetry", msg, 0, False)
                _check(info, client)
                sent.append((a, len(samples)))
                count += 1
            if a.latest is not None and (samples or not a.state_sent):
                info = paho.publish(f"{a.topic}/state", a.latest.encode(), 0, True)
                _check(info, client)
                a.state_sent = True
                count += 1
        if info is not None:
            self._pending, self._pending_since, self._in_flight = info, time.monotonic(), sent
            # write now what the socket takes (the rest when it is writable, as aiomqtt does):
            # the samples leave in this tick, not a loop iteration later; corked, so that the
            # tick's packets (paho sends each on its own: two thirds of the bridge's CPU went
            # into loopback transmits, one a message) leave in as few segments as fit
            sock = paho.socket()
            with _corked(sock):
                rc = paho.loop_write()
            if rc != mqtt.MQTT_ERR_SUCCESS:
                raise aiomqtt.MqttCodeError(rc, "Could not publish message")
            if sock is not None:
                aiomqtt_door.drop_late_writer_soon(paho, sock.fileno())
        if not qos1:
            self.published += count
            return
        # The tick as a whole has a deadline (_session): a per-publish timeout would cost a task
        # per message inside aiomqtt (asyncio.wait_for). Every publish ends before the tick
        # does (no orphan fails later, unretrieved).
        results = await asyncio.gather(*qos1, return_exceptions=True)
        failed = next((r for r in results if isinstance(r, BaseException)), None)
        if failed is not None:
            raise failed
        self.published += count + len(qos1)

    def _lost_in_flight(self, lost: list[tuple[_ArmOut, int]]) -> None:
        """What a failed tick carried may not have reached the broker: the next message says
        so in `dropped`."""
        for a, n in lost:
            a.dropped += n
            self.dropped_samples += n


@contextlib.contextmanager
def _corked(sock: Any) -> Iterator[None]:
    """TCP_CORK on `sock` (Linux) for the block: what is written goes out when it ends."""
    cork = getattr(socket, "TCP_CORK", None)
    if cork is None or sock is None:
        yield
        return
    try:
        sock.setsockopt(socket.IPPROTO_TCP, cork, 1)
    except OSError:
        yield
        return
    try:
        yield
    finally:
        with contextlib.suppress(OSError):
            sock.setsockopt(socket.IPPROTO_TCP, cork, 0)


def _check(info: mqtt.MQTTMessageInfo, client: aiomqtt.Client) -> None:
    """A publish paho could not queue (no connection): end the session, as aiomqtt would."""
    if info.rc != mqtt.MQTT_ERR_SUCCESS:
        raise aiomqtt.MqttCodeError(info.rc, "Could not publish message")


def _is_refusal(exc: aiomqtt.MqttCodeError) -> bool:
    """The broker answered CONNACK with a refusal (bad credentials, not authorised, client id
    rejected), not "server unavailable" (a broker starting or overloaded: just down). A failed
    publish is an MqttCodeError too, with paho's own codes (4 is "no connection"): not ours."""
    if not isinstance(exc, MqttConnectError):
        return False
    value = getattr(exc.rc, "value", exc.rc)
    return value not in (3, 136)  # MQTT 3.1.1 / 5 "server unavailable"


def start_mqtt_bridge(settings: Settings, services: Mapping[str, ArmService]) -> MqttBridge | None:
    """The bridge for these arms if `settings.mqtt_url` is set (started), else None."""
    if not settings.mqtt_url:
        return None
    bridge = MqttBridge(services, settings.mqtt_url, settings.mqtt_prefix, settings.mqtt_rate)
    bridge.start()
    return bridge
