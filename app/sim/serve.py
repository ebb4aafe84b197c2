"""Serve any SimDevice over a real byte stream: a pseudo-terminal or a TCP socket.

This lets unmodified host software (DynamixelSDK, pyserial, our serial link) talk to a
simulator exactly as to hardware: `serve_pty` makes a path that opens like /dev/ttyUSB0,
`serve_tcp` a `socket://host:port` endpoint. Host bytes go to `device.receive(data, now)`;
each reply is written `delay` seconds after `now`, strictly in order (a FIFO with one
writer, so a later reply never overtakes an earlier one). Packetized devices (HID-style,
64-byte packets) get the host's stream cut into 64-byte packets. A physics tick task calls
`device.advance(now)` every `tick_s` so state evolves between requests. `now` is
`time.monotonic()` in seconds.

Command: `armserver sim dynamixel (--pty PATH | --listen tcp://127.0.0.1:PORT)
[--ids 1,2,3,4] [--baudrate 1000000] [--mode ID:MODE ...] [--drop F] [--corrupt F]
[--latency S] [--supply V] [--fault ID:FAULT@T ...]` (see `main`). A fault is a hardware
error name of protocol.mx28.HARDWARE_ERRORS (overload, overheating, electrical_shock,
motor_encoder, input_voltage), `power_cycle` or `brown_out`, raised on servo ID (or `all`)
T seconds after the start: `--fault 1:overload@2.0`.

`armserver sim PROFILE (--pty PATH | --listen URL) [--drop F] [--corrupt F] [--latency S]`
serves the simulated hardware of any arm type instead (PROFILE: a built-in profile name
such as `rbe3001`, or a profile TOML path; the device is its arm type's `simulator`).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import logging
import os
import signal
import time
import tty
from collections.abc import Callable, Sequence
from pathlib import Path
from urllib.parse import urlsplit

from app.config import FaultConfig
from app.sim.base import SimDevice
from app.sim.dynamixel_bus import DynamixelBus
from app.sim.faults import ReplyFaults
from app.sim.xm430_servo import Xm430Servo
from protocol.mx28 import HARDWARE_ERRORS, hardware_error_bits

log = logging.getLogger(__name__)

PACKET_SIZE = 64  # host packet size of packetized devices (rbe3001 HID reports), bytes
TICK_S = 0.01  # physics tick, s: 100 Hz keeps Present* fresh between requests
REPLY_BACKLOG = 1024  # replies waiting to be written; beyond this they are dropped (logged)
READ_CHUNK = 4096  # bytes per read from the pty or socket


class _Pump:
    """Host bytes -> device -> timed, ordered replies through `write`."""

    def __init__(self, device: SimDevice, write: Callable[[bytes], None],
                 faults: ReplyFaults | None = None) -> None:
        self.device = device
        self._write = write
        self.faults = faults or ReplyFaults()
        self._last_due = 0.0
        self._pending = bytearray()
        self._queue: asyncio.Queue[tuple[float, bytes]] = asyncio.Queue(REPLY_BACKLOG)
        self._task = asyncio.get_running_loop().create_task(self._writer())

    def on_data(self, data: bytes) -> None:
        now = time.monotonic()
        chunks = [data]
        if self.device.packetized:
            self._pending += data
            n = len(self._pending) // PACKET_SIZE * PACKET_SIZE
            chunks = [bytes(self._pending[k:k + PACKET_SIZE]) for k in range(0, n, PACKET_SIZE)]
            del self._pending[:n]
        for chunk in chunks:
            for delay, reply in self.device.receive(chunk, now):
                out = self.faults.apply(reply)
                if out is None:
                    continue
                # latency delays every reply alike: never reordered
                self._last_due = max(self._last_due, now + delay + self.faults.latency_s)
                try:
                    self._queue.put_nowait((self._last_due, out))
                except asyncio.QueueFull:
                    log.warning("reply backlog full (%d); reply dropped", REPLY_BACKLOG)

    async def _writer(self) -> None:
        while True:
            due, reply = await self._queue.get()
            wait = due - time.monotonic()
            if wait > 0:
                await asyncio.sleep(wait)
            try:
                self._write(reply)
            except OSError as exc:
                log.warning("reply not written: %s", exc)

    async def close(self) -> None:
        self._task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await self._task


async def _ticker(device: SimDevice, period: float) -> None:
    while True:
        device.advance(time.monotonic())
        await asyncio.sleep(period)


class PtyServer:
    """A device behind a pseudo-terminal; `link_path` is a symlink to the slave tty."""

    def __init__(self, device: SimDevice, link_path: str | os.PathLike[str],
                 tick_s: float | None = TICK_S, faults: FaultConfig | None = None,
                 seed: int | None = 0) -> None:
        self.device = device
        self.faults = ReplyFaults(faults, seed)
        self.link_path = Path(link_path)
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)  # at once: a cooked pty echoes and turns LF into CRLF
        os.set_blocking(self.master, False)
        self.tty_name = os.ttyname(self.slave)
        if self.link_path.is_symlink():
            self.link_path.unlink()
        self.link_path.symlink_to(self.tty_name)
        self._loop = asyncio.get_running_loop()
        self._pump = _Pump(device, self._write, self.faults)
        self._loop.add_reader(self.master, self._on_readable)
        self._tick = self._loop.create_task(_ticker(device, tick_s)) if tick_s else None
        self._closed = False

    def set_faults(self, faults: FaultConfig) -> None:
        self.faults.faults = faults

    def _on_readable(self) -> None:
        try:
            data = os.read(self.master, READ_CHUNK)
        except (BlockingIOError, InterruptedError):
            return
        except OSError as exc:  # EIO cannot happen while we hold the slave, but be safe
            log.warning("pty read failed: %s", exc)
            return
        if data:
            self._pump.on_data(data)

    def _write(self, data: bytes) -> None:
        view = memoryview(data)
        while view:
            try:
                view = view[os.write(self.master, view):]
            except BlockingIOError:
                log.warning("pty full (host not reading); %d reply bytes dropped", len(view))
                return

    async def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        self._loop.remove_reader(self.master)
        if self._tick is not None:
            self._tick.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._tick
        await self._pump.close()
        for fd in (self.master, self.slave):
            with contextlib.suppress(OSError):
                os.close(fd)
        if self.link_path.is_symlink():
            self.link_path.unlink()


class TcpServer:
    """A device behind a TCP listener; every connection feeds the same device."""

    def __init__(self, device: SimDevice, tick_s: float | None = TICK_S,
                 faults: FaultConfig | None = None, seed: int | None = 0) -> None:
        self.device = device
        self.faults = ReplyFaults(faults, seed)
        self.server: asyncio.Server | None = None
        self._conns: set[asyncio.Task[None]] = set()
        self._refuse_until = 0.0
        loop = asyncio.get_running_loop()
        self._tick = loop.create_task(_ticker(device, tick_s)) if tick_s else None

    @property
    def port(self) -> int:
        assert self.server is not None
        return int(self.server.sockets[0].getsockname()[1])

    def set_faults(self, faults: FaultConfig) -> None:
        self.faults.faults = faults

    def disconnect(self) -> None:
        """Drop every connection now and refuse new ones for `faults.reconnect_after_s`: the
        host sees the cable pulled (end of file), then the device back."""
        self._refuse_until = time.monotonic() + self.faults.faults.reconnect_after_s
        for t in list(self._conns):
            t.cancel()

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        if time.monotonic() < self._refuse_until:
            writer.close()
            return
        task = asyncio.current_task()
        assert task is not None
        self._conns.add(task)
        after = self.faults.faults.disconnect_after_s
        timer = (asyncio.get_running_loop().call_later(after, self.disconnect)
                 if after is not None else None)
        pump = _Pump(self.device, writer.write, self.faults)
        try:
            while data := await reader.read(READ_CHUNK):
                pump.on_data(data)
        except ConnectionError as exc:
            log.info("connection lost: %s", exc)
        except asyncio.CancelledError:
            log.info("connection dropped (simulated disconnect or shutdown)")
        finally:
            if timer is not None:
                timer.cancel()
            self._conns.discard(task)
            await pump.close()
            writer.close()
            with contextlib.suppress(ConnectionError):
                await writer.wait_closed()

    async def close(self) -> None:
        if self.server is not None:
            self.server.close()
        for t in [*self._conns, *([self._tick] if self._tick else [])]:
            t.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await t
        self._tick = None
        if self.server is not None:
            await self.server.wait_closed()
            self.server = None


async def serve_pty(device: SimDevice, link_path: str | os.PathLike[str],
                    tick_s: float | None = TICK_S, faults: FaultConfig | None = None,
                    seed: int | None = 0) -> PtyServer:
    """Serve `device` on a new pseudo-terminal reachable at the symlink `link_path`, with
    per-reply `faults` (drop, corrupt, latency; settable later with `set_faults`)."""
    return PtyServer(device, link_path, tick_s, faults, seed)


async def serve_tcp(device: SimDevice, host: str = "127.0.0.1", port: int = 0,
                    tick_s: float | None = TICK_S, faults: FaultConfig | None = None,
                    seed: int | None = 0) -> TcpServer:
    """Serve `device` on a TCP listener (port 0: any free port; see `.port`), with per-reply
    `faults` and, for TCP, disconnects (`disconnect()`, or `faults.disconnect_after_s`)."""
    srv = TcpServer(device, tick_s, faults, seed)
    srv.server = await asyncio.start_server(srv._serve, host, port)
    return srv


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="armserver sim", description="Serve a simulated device.")
    p.add_argument("device", help="`dynamixel` (a bus of --ids), or a profile (built-in name "
                   "or TOML path) whose arm type's simulator to serve")
    where = p.add_mutually_exclusive_group(required=True)
    where.add_argument("--pty", metavar="PATH", help="symlink to create for the pseudo-terminal")
    where.add_argument("--listen", metavar="URL", help="tcp://HOST:PORT to listen on")
    p.add_argument("--ids", default="1,2,3,4", help="servo ids, comma separated")
    p.add_argument("--baudrate", type=int, default=1_000_000, help="bus baud rate, bit/s")
    p.add_argument("--xm430", default="", metavar="IDS",
                   help="ids (among --ids) that are XM430-W350 servos, model 1020, e.g. an "
                        "OpenManipulator-X: --ids 11,12,13,14,15 --xm430 11,12,13,14,15")
    p.add_argument("--mode", action="append", default=[], metavar="ID:MODE",
                   help="operating mode of a servo (1 velocity, 3 position, 4 extended, 16 PWM)")
    p.add_argument("--drop", type=float, default=0.0, help="fraction of replies lost")
    p.add_argument("--corrupt", type=float, default=0.0,
                   help="fraction of replies with one byte changed")
    p.add_argument("--latency", type=float, default=0.0, help="extra delay of every reply, s")
    p.add_argument("--supply", type=float, default=None, metavar="V",
                   help="supply voltage the servos see (default 12 V): speed scales with it")
    p.add_argument("--fault", action="append", default=[], metavar="ID:FAULT@T",
                   help="at T s raise FAULT on servo ID (or all): a hardware error name "
                        f"({', '.join(HARDWARE_ERRORS)}), power_cycle or brown_out")
    return p


_BUS_EVENTS = ("power_cycle", "brown_out")


def parse_fault(spec: str) -> tuple[int | None, str, float]:
    """`ID:FAULT@T` -> (id or None for `all`, fault, t seconds); ValueError if malformed."""
    head, at, when = spec.partition("@")
    sid, colon, name = head.partition(":")
    if not (at and colon and sid and name):
        raise ValueError(f"--fault wants ID:FAULT@SECONDS, got {spec!r}")
    name = name.strip().lower().replace("-", "_")
    if name not in _BUS_EVENTS:
        hardware_error_bits(name)  # ValueError naming the valid ones
    t = float(when)
    if not t >= 0.0 or t == float("inf"):
        raise ValueError(f"--fault time must be a finite number of seconds >= 0, got {when!r}")
    return (None if sid.strip().lower() == "all" else int(sid)), name, t


def schedule_faults(bus: DynamixelBus, faults: Sequence[tuple[int | None, str, float]],
                    loop: asyncio.AbstractEventLoop) -> list[asyncio.TimerHandle]:
    """Raise each (id, fault, t) on `bus` t seconds from now."""

    def fire(sid: int | None, name: str) -> None:
        ids = None if sid is None else [sid]
        try:
            if name == "power_cycle":
                bus.power_cycle(ids)
            elif name == "brown_out":
                bus.brown_out(ids)
            else:
                for i in [s.id for s in bus.servos] if sid is None else [sid]:
                    bus.inject_hardware_error(i, name)
        except KeyError as exc:
            log.warning("fault %s not raised: %s", name, exc)
            return
        log.info("fault %s raised on %s", name, "all servos" if sid is None else f"id {sid}")

    return [loop.call_later(t, fire, sid, name) for sid, name, t in faults]


def _pairs(items: Sequence[str]) -> dict[int, int]:
    out: dict[int, int] = {}
    for item in items:
        a, _, b = item.partition(":")
        out[int(a)] = int(b)
    return out


def _profile_device(source: str) -> tuple[SimDevice, str]:
    """The simulator of a profile's arm type, and a line saying what it is."""
    from app.arms import arm_type
    from app.config import ConfigError, load_profile

    try:
        profile = load_profile(source)
    except ConfigError as exc:
        raise ValueError(f"{source!r} is neither `dynamixel` nor a usable profile: {exc}") from None
    return arm_type(profile.model).simulator(profile), f"{profile.model} ({profile.name})"


async def _run(args: argparse.Namespace) -> None:
    timers: list[asyncio.TimerHandle] = []
    device: SimDevice
    if args.device == "dynamixel":
        ids = [int(i) for i in args.ids.split(",") if i.strip()]
        bus = DynamixelBus(ids, args.baudrate, _pairs(args.mode),
                           {i: Xm430Servo for i in _xm430_ids(args)})
        if args.supply is not None:
            bus.set_supply_voltage(args.supply)
        timers = schedule_faults(bus, [parse_fault(f) for f in args.fault],
                                 asyncio.get_running_loop())
        device, what = bus, f"dynamixel bus ids {ids} at {args.baudrate} bit/s"
    else:
        if args.fault or args.supply is not None or args.mode or args.xm430:
            raise ValueError("--fault, --supply, --mode and --xm430 are for `dynamixel` only")
        device, what = _profile_device(args.device)
    faults = FaultConfig(drop=args.drop, corrupt=args.corrupt, latency_s=args.latency)
    server: PtyServer | TcpServer
    if args.pty:
        server = await serve_pty(device, args.pty, faults=faults, seed=None)
        where = f"{args.pty} -> {server.tty_name}"
    else:
        url = urlsplit(args.listen)
        if url.scheme != "tcp" or not url.hostname or url.port is None:
            raise ValueError(f"--listen wants tcp://HOST:PORT, got {args.listen!r}")
        server = await serve_tcp(device, url.hostname, url.port, faults=faults, seed=None)
        where = f"tcp://{url.hostname}:{server.port} (socket://{url.hostname}:{server.port})"
    print(f"{what} on {where}", flush=True)
    stop = asyncio.Event()
    with contextlib.suppress(NotImplementedError):  # SIGTERM: close cleanly (remove the link)
        asyncio.get_running_loop().add_signal_handler(signal.SIGTERM, stop.set)
    try:
        await stop.wait()
    finally:
        for timer in timers:
            timer.cancel()
        await server.close()


def _check_faults_and_supply(args: argparse.Namespace) -> None:
    """ValueError, before anything starts, for a fault on an absent id or a bad supply."""
    ids = {int(i) for i in args.ids.split(",") if i.strip()}
    for spec in args.fault:
        sid = parse_fault(spec)[0]
        if sid is not None and sid not in ids:
            raise ValueError(f"--fault {spec!r}: no servo {sid} in --ids {args.ids}")
    if args.supply is not None and not 0.0 <= args.supply <= 30.0:
        raise ValueError(f"--supply wants volts in 0..30, got {args.supply}")


def _xm430_ids(args: argparse.Namespace) -> set[int]:
    """The ids of --xm430; ValueError for one not in --ids."""
    ids = {int(i) for i in args.ids.split(",") if i.strip()}
    xm = {int(i) for i in args.xm430.split(",") if i.strip()}
    if xm - ids:
        raise ValueError(f"--xm430 {args.xm430}: no servo {min(xm - ids)} in --ids {args.ids}")
    return xm


def main(argv: list[str] | None = None) -> int:
    """`armserver sim ...`: run a simulated device until interrupted; 0 on a clean stop,
    2 on bad arguments."""
    args = _parser().parse_args(argv)
    try:
        _pairs(args.mode)
        _check_faults_and_supply(args)
        _xm430_ids(args)
        asyncio.run(_run(args))
    except KeyboardInterrupt:
        return 0
    except (ValueError, OSError) as exc:
        print(f"armserver sim: {exc}", flush=True)
        return 2
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
