"""Lab-wide telemetry benchmark: one Mosquitto, one arm server with many simulated arms.

Starts a real mosquitto on a free loopback port and `armserver serve` in a subprocess (its CPU
is its own) on a config of ARMS simulated rbe3001 arms polled at HZ (`count = ARMS` in one
`[[arms]]` entry), publishing with ARMSERVER_MQTT_URL at the bridge's rate. Then, for SECONDS:

- PER_ARM subscribers on each arm's telemetry topic (240 by default), one subscriber on every
  arm's telemetry (`{prefix}/+/telemetry`), and one subscriber that subscribes to everything
  and then stops reading its socket for the whole window (a stalled screen);
- one WebSocket client on the first arm, in both runs, for the sample timestamps (jitter).

Prints, per healthy subscriber, delivery % (distinct samples received over the samples the
server published in the window, from `seq`) and the latency of the newest sample of each
message (device timestamp to receipt: at most one poll period plus the broker hop), and the
server's CPU (share of one core) and sample jitter with the bridge on, then the same server
config with the bridge off (no ARMSERVER_MQTT_URL).

    python bench/mqtt.py                      # 24 arms at 50 Hz, 10 subscribers per arm, 10 s
    python bench/mqtt.py --arms 4 --seconds 3 --per-arm 2
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import os
import socket
import statistics
import sys
import tempfile
import time
import urllib.request
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import websockets
from _server import ROOT, ServerProcess, pct  # bench/_server.py

sys.path.insert(0, str(ROOT / "tests"))
from _mosquitto import Broker  # noqa: E402  (tests/_mosquitto.py: the suite's broker)

# ---------------------------------------------------------------- a minimal MQTT subscriber


def _string(s: str) -> bytes:
    b = s.encode()
    return len(b).to_bytes(2, "big") + b


def _packet(first: int, body: bytes) -> bytes:
    n, out = len(body), bytearray([first])
    while True:
        byte, n = n % 128, n // 128
        out.append(byte | (0x80 if n else 0))
        if not n:
            return bytes(out) + body


@dataclass(eq=False)
class Sub(asyncio.Protocol):
    """One subscriber: MQTT 3.1.1 over an asyncio protocol, QoS 0, counting what each message
    carries. A stalled one pauses reading (with a small receive buffer) until released."""

    name: str
    topic: str
    seqs: dict[str, set[int]] = field(default_factory=dict)
    newest: dict[str, int] = field(default_factory=dict)  # each arm's highest seq seen
    latency_s: list[float] = field(default_factory=list)
    messages: int = 0
    recording: bool = False
    #: Messages received after this time (time.time()) count for delivery, not latency: after
    #: the window this process parses what it read, which holds its loop up for about half a
    #: second, and what arrives meanwhile is stamped that much late (that was the whole of the
    #: p99: the messages of the last 0.5 s, received at one instant, 150-550 ms "late")
    latency_until: float = float("inf")
    #: (receipt time, PUBLISH body) as read: parsed after the window, so that the latency of a
    #: message is not the time this process took to parse the ones before it
    raw: list[tuple[float, bytes]] = field(default_factory=list)
    buf: bytearray = field(default_factory=bytearray)
    transport: asyncio.Transport | None = None

    async def run(self, port: int, stall: asyncio.Event | None = None) -> None:
        loop = asyncio.get_running_loop()
        sock = socket.create_connection(("127.0.0.1", port))
        if stall is not None:  # a small receive buffer, so the stall backs up into the broker
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        sock.setblocking(False)
        transport, _ = await loop.create_connection(lambda: self, sock=sock)
        transport.write(_packet(0x10, _string("MQTT") + bytes([4, 2, 0, 60])
                                + _string(f"bench-{self.name}-{os.getpid()}")))
        transport.write(_packet(0x82, b"\x00\x01" + _string(self.topic) + b"\x00"))
        if stall is not None:
            await asyncio.sleep(0.5)  # CONNACK and SUBACK in, then read nothing
            transport.pause_reading()
            await stall.wait()
            transport.resume_reading()
        await asyncio.Future()  # until cancelled

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = transport  # type: ignore[assignment]

    def data_received(self, data: bytes) -> None:
        now = time.time()
        buf = self.buf
        buf += data
        pos = 0
        while len(buf) - pos >= 2:
            n, mult, i = 0, 1, pos + 1
            while True:
                if i >= len(buf):
                    del buf[:pos]
                    return
                b = buf[i]
                i += 1
                n += (b & 0x7F) * mult
                mult *= 128
                if not b & 0x80:
                    break
            if len(buf) - i < n:
                break
            if buf[pos] >> 4 == 3 and self.recording:
                self.raw.append((now, bytes(buf[i:i + n])))
            pos = i + n
        del buf[:pos]

    def parse(self) -> None:
        for now, body in self.raw:
            self._publish(now, body)
        self.raw.clear()

    def _publish(self, now: float, body: bytes) -> None:
        tlen = int.from_bytes(body[:2], "big")
        if not body[2:2 + tlen].endswith(b"/telemetry"):
            return
        msg = json.loads(body[2 + tlen:])
        self.messages += 1
        samples = msg["samples"]
        if samples:
            self.seqs.setdefault(msg["arm"], set()).update(s["seq"] for s in samples)
            self.newest[msg["arm"]] = max(self.newest.get(msg["arm"], 0), samples[-1]["seq"])
            if now <= self.latency_until:
                self.latency_s.append(now - samples[-1]["time"])

    def close(self) -> None:
        if self.transport is not None:
            self.transport.close()


# ---------------------------------------------------------------- the server under test


class Server(ServerProcess):
    """`armserver serve` over `config`'s arms, bridged to the broker at `broker_url` (None: no
    bridge) at `rate`; with `pin`, the server on one core and the bench and broker on the rest
    (on a shared machine the others' load then lands on the server's core while the
    subscribers keep theirs busy: --no-pin)."""

    def __init__(self, config: Path, broker_url: str | None, rate: float, pin: bool) -> None:
        env = ({"ARMSERVER_MQTT_URL": broker_url, "ARMSERVER_MQTT_RATE": str(rate)}
               if broker_url else {})
        super().__init__(pin, config, env, timeout=60,
                         ready=lambda h: not broker_url or h["mqtt"]["state"] == "up")

    async def published(self, arms: list[str]) -> dict[str, tuple[int, float]]:
        """Each arm's latest `seq` (the samples published so far) and its device time: one
        request at a time, each
        on its own connection (24 at once timed out on a loaded host, and a kept-alive one
        can be closed under the next request)."""
        def seq(arm: str) -> tuple[int, float]:
            url = f"{self.url}/api/v1/arms/{arm}/state"
            for attempt in range(3):
                try:
                    with urllib.request.urlopen(url, timeout=60) as r:
                        state = json.loads(r.read())
                        return int(state["seq"]), float(state["time"])
                except OSError:
                    if attempt == 2:
                        raise
            raise AssertionError("unreachable")

        return {a: await asyncio.to_thread(seq, a) for a in arms}


@contextlib.contextmanager
def serving(config: Path, broker_url: str | None, rate: float, pin: bool) -> Iterator[Server]:
    srv = Server(config, broker_url, rate, pin)
    try:
        yield srv
    finally:
        srv.close()


async def sample_times(ws_url: str, seconds: float) -> list[float]:
    """The device timestamps of every sample of one arm, over the WebSocket, for `seconds`."""
    out: list[float] = []
    async with websockets.connect(ws_url, max_size=None) as ws:
        await ws.recv()  # the latest sample, sent at connect: older than the stream
        end = time.monotonic() + seconds
        while (left := end - time.monotonic()) > 0:
            with contextlib.suppress(TimeoutError):
                msg = json.loads(await asyncio.wait_for(ws.recv(), left))
                if msg["type"] == "telemetry":
                    out += [s["time"] for s in msg["samples"]]
    return out


def jitter_ms(times: list[float], hz: float) -> tuple[float, float]:
    """Std dev of the sample interval, and p99 of |interval - 1/hz|, ms."""
    d = [b - a for a, b in zip(times, times[1:], strict=False)]
    if len(d) < 2:
        return float("nan"), float("nan")
    return statistics.pstdev(d) * 1e3, pct([abs(x - 1 / hz) for x in d], 0.99) * 1e3


async def run_on(srv: Server, args: argparse.Namespace, broker: Broker | None,
                 arms: list[str]) -> dict[str, object]:
    tasks: list[asyncio.Task[None]] = []
    subs: list[Sub] = []
    stalled: Sub | None = None
    stall_release = asyncio.Event()
    if broker is not None:
        for arm in arms:
            subs += [Sub(f"{arm}-{k}", f"armserver/{arm}/telemetry") for k in range(args.per_arm)]
        subs.append(Sub("all", "armserver/+/telemetry"))
        stalled = Sub("stalled", "armserver/#")
        tasks = [asyncio.create_task(s.run(broker.port)) for s in subs]
        tasks.append(asyncio.create_task(stalled.run(broker.port, stall_release)))
    await asyncio.sleep(2.0)  # connected and subscribed; the stalled one is stalled
    # before `first`: what arrives while we ask is counted (only the window is)
    for s in [*subs, *([stalled] if stalled else [])]:
        s.recording = True
    first_st = await srv.published(arms)
    first = {a: v[0] for a, v in first_st.items()}
    h0 = (await asyncio.to_thread(srv.health)).get("mqtt") or {}
    cpu0, t0 = srv.cpu_seconds(), time.monotonic()
    times = await sample_times(f"ws://127.0.0.1:{srv.port}/api/v1/arms/{arms[0]}/telemetry"
                               "?rate=10", args.seconds)
    cpu_s, wall = srv.cpu_seconds() - cpu0, time.monotonic() - t0
    for s in subs:
        s.latency_until = time.time()  # the end of the window: the parsing below holds us up
    last_st = await srv.published(arms)
    last = {a: v[0] for a, v in last_st.items()}
    samples = sum(last[a] - first[a] for a in arms)
    # each arm's poll rate from its own samples (seq over device time): the requests for the
    # states take a while on a loaded host, so the window's wall time would not do
    poll_hz = statistics.fmean((last_st[a][0] - first_st[a][0])
                               / max(1e-9, last_st[a][1] - first_st[a][1]) for a in arms)
    # what was published in the window reaches the subscribers (or 10 s pass)
    def caught_up() -> bool:
        for s in subs:
            s.parse()
        return all(s.newest.get(a, 0) >= last[a] for s in subs
                   for a in (arms if s.name == "all" else [s.topic.split("/")[1]]))

    for _ in range(100):
        if caught_up():
            break
        await asyncio.sleep(0.1)
    for s in subs:
        s.recording = False
        s.parse()
    stall_release.set()
    await asyncio.sleep(1.0)  # the stalled one reads what the broker kept for it
    if stalled is not None:
        stalled.parse()
    health = await asyncio.to_thread(srv.health)
    for t in tasks:
        t.cancel()
    await asyncio.gather(*tasks, return_exceptions=True)
    for s in [*subs, *([stalled] if stalled else [])]:
        s.close()
    mq = health.get("mqtt") or {}
    out: dict[str, object] = {"cpu": cpu_s / wall, "cpu_s": cpu_s, "wall": wall,
                              "cpu_per_sample_us": 1e6 * cpu_s / (poll_hz * len(arms) * wall),
                              "poll_hz": poll_hz,
                              "jitter": jitter_ms(times, args.hz), "mqtt": mq}
    if mq:  # what the bridge itself spent, CPU time measured in its ticks (health `tick_cpu_s`)
        n = mq["published"] - h0.get("published", 0)
        out["bridge_msgs"] = n
        out["bridge_us_per_msg"] = 1e6 * (mq["tick_cpu_s"] - h0.get("tick_cpu_s", 0.0)) / max(1, n)
    if subs:
        deliveries: list[float] = []
        for s in subs:
            for arm, seqs in (s.seqs.items() if s.name == "all" else
                              [(s.topic.split("/")[1], s.seqs.get(s.topic.split("/")[1], set()))]):
                window = set(range(first[arm] + 1, last[arm] + 1))
                deliveries.append(100.0 * len(seqs & window) / max(1, len(window)))
        lat = [x for s in subs for x in s.latency_s]
        all_sub = subs[-1]
        per_arm = deliveries[:len(subs) - 1]
        all_arms = [100.0 * len(all_sub.seqs.get(a, set()) & set(range(first[a] + 1, last[a] + 1)))
                    / max(1, last[a] - first[a]) for a in arms]
        if stalled is not None:
            got = sum(len(v & set(range(first[a] + 1, last[a] + 1)))
                      for a, v in stalled.seqs.items())
            out["stalled_pct"] = 100.0 * got / max(1, samples)
        out.update(per_arm_min=min(per_arm), all_arms_min=min(all_arms) if all_arms else 0.0)
        out.update(delivery_min=min(deliveries), delivery_mean=statistics.fmean(deliveries),
                   lat_p50=pct(lat, 0.5) * 1e3, lat_p90=pct(lat, 0.9) * 1e3,
                   lat_p99=pct(lat, 0.99) * 1e3,
                   all_arms=len(all_sub.seqs), messages=sum(s.messages for s in subs))
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--arms", type=int, default=24)
    p.add_argument("--hz", type=float, default=50.0, help="each arm's poll rate")
    p.add_argument("--rate", type=float, default=10.0, help="the bridge's ARMSERVER_MQTT_RATE")
    p.add_argument("--per-arm", type=int, default=10, help="subscribers per arm")
    p.add_argument("--seconds", type=float, default=10.0)
    p.add_argument("--no-pin", dest="pin", action="store_false",
                   help="leave the server, broker and bench on every core")
    args = p.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        cfg = Path(tmp) / "lab.toml"
        cfg.write_text(f'[[arms]]\nprofile = "rbe3001"\nname = "lab"\ncount = {args.arms}\n'
                       f'[arms.link]\npoll_hz = {args.hz}\n')
        arms = [f"lab-{k}" for k in range(1, args.arms + 1)]
        bdir = Path(tmp) / "broker"
        bdir.mkdir()
        broker = Broker(bdir, extra="max_queued_messages 1000\n").start()
        assert broker.proc is not None
        cpus = sorted(os.sched_getaffinity(0))
        if len(cpus) > 1 and args.pin:
            os.sched_setaffinity(broker.proc.pid, set(cpus[1:]))
        try:
            with serving(cfg, broker.url, args.rate, args.pin) as srv:
                on = asyncio.run(run_on(srv, args, broker, arms))
            with serving(cfg, None, args.rate, args.pin) as srv:
                off = asyncio.run(run_on(srv, args, None, arms))
        finally:
            broker.stop()
    n = args.arms * args.per_arm
    print(f"{args.arms} simulated arms at {args.hz:g} Hz, bridge at {args.rate:g} Hz, "
          f"{n} subscribers ({args.per_arm} per arm) + 1 all-arms + 1 stalled, "
          f"{args.seconds:g} s, {os.cpu_count()} cores, load average {os.getloadavg()[0]:.1f}")
    print(f"delivery per healthy subscriber: per-arm min {on['per_arm_min']:.3f} %, all-arms "
          f"min {on['all_arms_min']:.3f} % (over {on['all_arms']} arms), mean "
          f"{on['delivery_mean']:.3f} %  (target >= 99.9 %); stalled subscriber after release: "
          f"{on.get('stalled_pct', float('nan')):.1f} % (informative: the broker queues 1000)")
    print(f"latency of each message's newest sample (device time to receipt, stamped as read, "
          f"parsed later): p50 {on['lat_p50']:.1f} ms, p90 {on['lat_p90']:.1f} ms, "
          f"p99 {on['lat_p99']:.1f} ms  (target p99 < 50 ms; includes up to 1/poll rate of "
          f"sample age)")
    print(f"messages received by the subscribers: {on['messages']}")
    mq = on["mqtt"] or {}
    print(f"bridge: published {mq.get('published')}, dropped samples "
          f"{mq.get('dropped_samples')}, connects {mq.get('connects')}")
    print(f"bridge CPU time per message (its ticks, in the server, thread CPU time): "
          f"{on['bridge_us_per_msg']:.1f} us x {on['bridge_msgs'] / on['wall']:.0f} messages/s "
          f"= {on['bridge_us_per_msg'] * on['bridge_msgs'] / on['wall'] / 1e4:.2f} % of a core")
    for label, r in (("bridge on ", on), ("bridge off", off)):
        sd, p99 = r["jitter"]  # type: ignore[misc]
        print(f"{label}: server CPU {100 * r['cpu']:.1f} % of a core, "
              f"{r['cpu_per_sample_us']:.0f} us of CPU per sample, polled at "
              f"{r['poll_hz']:.1f} Hz per arm, sample interval jitter sd {sd:.2f} ms, "
              f"p99 |dt - 1/hz| {p99:.2f} ms")
    print(f"ratios on/off (one run): server CPU {on['cpu'] / off['cpu']:.3f}, CPU per sample "
          f"{on['cpu_per_sample_us'] / off['cpu_per_sample_us']:.3f}, poll rate "
          f"{on['poll_hz'] / off['poll_hz']:.3f}")


if __name__ == "__main__":
    main()
