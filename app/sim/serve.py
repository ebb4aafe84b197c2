"""The `armserver sim` command: serve a simulated device (a Dynamixel bus, or any arm
type's simulated hardware) over a pseudo-terminal or a TCP socket, with faults.

The servers themselves (`serve_pty`, `serve_tcp`, `PtyServer`, `TcpServer`: how a SimDevice
meets a real byte stream) are app/sim/servers.py, re-exported here.

Command: `armserver sim dynamixel (--pty PATH | --listen tcp://127.0.0.1:PORT)
[--ids 1,2,3,4 | --factory N] [--baudrate 1000000] [--mode ID:MODE ...] [--drop F] [--corrupt F]
[--latency S] [--supply V] [--fault ID:FAULT@T ...]` (see `main`). A fault is a hardware
error name of protocol.mx28.HARDWARE_ERRORS (overload, overheating, electrical_shock,
motor_encoder, input_voltage), `power_cycle` or `brown_out`, raised on servo ID (or `all`)
T seconds after the start: `--fault 1:overload@2.0`.

`armserver sim PROFILE (--pty PATH | --listen URL [--listen URL ...]) [--drop F]
[--corrupt F] [--latency S]` serves the simulated hardware of any arm type instead (PROFILE:
a built-in profile name such as `rbe3001`, or a profile TOML path; the device is its arm
type's `simulator`). `--listen` given N times serves N devices alike from this one process, one
on each address, with one physics tick for all (a lab's arms: bench/lab.py).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import logging
import signal
from collections.abc import Sequence
from urllib.parse import urlsplit

from app.arms.dynamixel.sim_bus import FACTORY_BAUDRATE, DynamixelBus
from app.arms.dynamixel.sim_xm430 import Xm430Servo
from app.config import FaultConfig
from app.sim.base import SimDevice
from app.sim.servers import PACKET_SIZE as PACKET_SIZE  # the servers, re-exported
from app.sim.servers import READ_CHUNK as READ_CHUNK
from app.sim.servers import REPLY_BACKLOG as REPLY_BACKLOG
from app.sim.servers import TICK_S as TICK_S
from app.sim.servers import PtyServer as PtyServer
from app.sim.servers import TcpServer as TcpServer
from app.sim.servers import serve_pty as serve_pty
from app.sim.servers import serve_tcp as serve_tcp
from app.sim.servers import tick_all
from protocol.mx28 import HARDWARE_ERRORS, hardware_error_bits

log = logging.getLogger(__name__)


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="armserver sim", description="Serve a simulated device.")
    p.add_argument("device", help="`dynamixel` (a bus of --ids), or a profile (built-in name "
                   "or TOML path) whose arm type's simulator to serve")
    where = p.add_mutually_exclusive_group(required=True)
    where.add_argument("--pty", metavar="PATH", help="symlink to create for the pseudo-terminal")
    where.add_argument("--listen", metavar="URL", action="append",
                       help="tcp://HOST:PORT to listen on; given N times, N devices alike, "
                            "one on each address, served by this one process (a lab's arms: "
                            "bench/lab.py)")
    p.add_argument("--ids", default="1,2,3,4", help="servo ids, comma separated")
    p.add_argument("--baudrate", type=int, default=1_000_000, help="bus baud rate, bit/s")
    p.add_argument("--factory", type=int, default=0, metavar="N",
                   help="N servos in the factory state instead of --ids: every one ID 1 at "
                   "57,600 bps (two or more on one ID collide); on a pty they hear only a host "
                   "at their rate, on a socket (no baud rate) every host")
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
    from app.arms.loading import load_profile
    from app.config import ConfigError

    try:
        profile = load_profile(source)
    except ConfigError as exc:
        raise ValueError(f"{source!r} is neither `dynamixel` nor a usable profile: {exc}") from None
    return arm_type(profile.model).simulator(profile), f"{profile.model} ({profile.name})"


def _device(args: argparse.Namespace) -> tuple[SimDevice, str, list[asyncio.TimerHandle]]:
    """A new device as the arguments describe it, a line saying what it is, its fault timers."""
    timers: list[asyncio.TimerHandle] = []
    device: SimDevice
    if args.device == "dynamixel" and args.factory > 0:
        bus = DynamixelBus.factory(args.factory, None if args.listen else FACTORY_BAUDRATE)
        device, what = bus, f"dynamixel bus of {args.factory} factory servo(s) (ID 1, 57,600 bps)"
    elif args.device == "dynamixel":
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
    return device, what, timers


async def _run(args: argparse.Namespace) -> None:
    faults = FaultConfig(drop=args.drop, corrupt=args.corrupt, latency_s=args.latency)
    servers: list[PtyServer | TcpServer] = []
    timers: list[asyncio.TimerHandle] = []
    ticks: asyncio.Task[None] | None = None
    try:
        if args.pty:
            device, what, timers = _device(args)
            pty = await serve_pty(device, args.pty, faults=faults, seed=None)
            servers.append(pty)
            print(f"{what} on {args.pty} -> {pty.tty_name}", flush=True)
        else:
            devices = []
            for listen in args.listen:
                url = urlsplit(listen)
                if url.scheme != "tcp" or not url.hostname or url.port is None:
                    raise ValueError(f"--listen wants tcp://HOST:PORT, got {listen!r}")
                device, what, more = _device(args)
                timers += more
                devices.append(device)
                # one physics tick for all the process's devices (below), not a task each
                tcp = await serve_tcp(device, url.hostname, url.port, tick_s=None,
                                      faults=faults, seed=None)
                servers.append(tcp)
                print(f"{what} on tcp://{url.hostname}:{tcp.port} "
                      f"(socket://{url.hostname}:{tcp.port})", flush=True)
            ticks = asyncio.get_running_loop().create_task(tick_all(devices, TICK_S))
        stop = asyncio.Event()
        with contextlib.suppress(NotImplementedError):  # SIGTERM: close cleanly
            asyncio.get_running_loop().add_signal_handler(signal.SIGTERM, stop.set)
        await stop.wait()
    finally:
        for timer in timers:
            timer.cancel()
        if ticks is not None:
            ticks.cancel()
        for server in servers:
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
