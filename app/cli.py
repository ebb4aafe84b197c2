"""`armserver` command line.

    armserver serve [--config FILE] [--host 127.0.0.1] [--port 8000] [--log-level info]
                    [--workers N]     N worker processes behind one address (app/lab)
    armserver devices                 list USB serial and HID devices that look like arms
    armserver sim ...                 run a simulated device on a pty or TCP port (app.sim.serve)
    armserver setup-servos --port URL --profile NAME [--joint JOINT]
                                      find Dynamixel servos; set one up as a joint's
    armserver call ... / watch ...    client commands (app.client.cli), where installed

Settings come from the environment (ARMSERVER_*); flags override them. The server binds to
127.0.0.1 unless told otherwise: reaching it from other hosts is a decision, best taken with
tokens configured.
"""

from __future__ import annotations

import argparse
import importlib.util
import logging
import sys
from collections.abc import Sequence
from typing import Any

log = logging.getLogger("armserver")

LOOPBACK = {"127.0.0.1", "::1", "localhost"}


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="armserver", description="Networked robot-arm server.")
    sub = p.add_subparsers(dest="command", required=True, metavar="command")

    serve = sub.add_parser("serve", help="run the REST and WebSocket server",
                           description="Run the server (settings from ARMSERVER_*; flags win).")
    serve.add_argument("--config", help="server config TOML ([[arms]] tables); default: the "
                       "simulated rbe3001 and angler")
    serve.add_argument("--host", help="address to bind (default 127.0.0.1: this machine only)")
    serve.add_argument("--port", type=int, help="TCP port (default 8000)")
    serve.add_argument("--log-level", choices=["critical", "error", "warning", "info", "debug"])
    serve.add_argument("--workers", type=_positive, metavar="N",
                       help="spread the arms over N worker processes behind this one address "
                       "(app/lab; default: 1, one process, unless the config names workers)")
    serve.add_argument("--access-log", action="store_true",
                       help="log every HTTP request (off by default: at thousands of requests "
                       "a second the log line costs more than the answer)")
    serve.set_defaults(func=_serve)

    devices = sub.add_parser("devices", help="list attached serial and HID devices",
                             description="List USB serial and HID devices that look like arms.")
    devices.set_defaults(func=_devices)

    setup = sub.add_parser(
        "setup-servos", help="find Dynamixel servos (any standard baud rate); with --joint, "
        "give the one servo on the bus that joint's ID, baud rate and settings",
        description="Scan a Dynamixel bus at the standard baud rates and print what answers; "
        "with --joint, set up the one servo that is not another joint's (EEPROM, torque off) "
        "and verify it. Exit 0 when done; 3 no servo, 4 several at once or a collision, "
        "5 refused (ID in use, torque on), 6 not verified.")
    setup.add_argument("--port", required=True, help="serial device or pyserial URL "
                       "(/dev/ttyUSB0, a simulator's pty, socket://127.0.0.1:7000)")
    setup.add_argument("--profile", required=True, help="built-in profile name or TOML path")
    setup.add_argument("--joint", help="the joint whose servo is the one on the bus")
    setup.add_argument("--timeout", type=float, default=0.1,
                       help="how long a broadcast PING waits for answers, s (a servo heard "
                            "has at least 1 s to answer a READ or a WRITE)")
    setup.add_argument("--baudrates", help="rates to scan, comma separated (default: every "
                       "standard rate, 57600 first)")
    setup.set_defaults(func=_setup_servos)

    # Parsed by app.sim.serve itself (see main); listed here for --help.
    sub.add_parser("sim", help="run a simulated arm device on a pty or TCP port "
                   "(armserver sim --help)", add_help=False)

    register_client_commands(sub)
    return p


def register_client_commands(subparsers: Any) -> None:
    """Hook for the client commands (`call`, `watch`, `estop`, `record`, `teleop`): added from
    app.client if present."""
    if importlib.util.find_spec("app.client.cli") is None:
        return
    from app.client.cli import register_client_commands as register
    from app.client.estop_cli import add_estop
    from app.client.record_cli import add_record
    from app.client.teleop_cli import add_teleop

    register(subparsers)
    add_estop(subparsers)
    add_record(subparsers)
    add_teleop(subparsers)


def _settings(args: argparse.Namespace) -> Any:
    from app.config import Settings

    over = {k: v for k, v in (("config", args.config), ("host", args.host), ("port", args.port),
                              ("log_level", args.log_level)) if v is not None}
    return Settings(**over)  # validated, flags included (model_copy would skip validation)


def _serve(args: argparse.Namespace) -> int:
    import uvicorn

    from app.web.factory import create_app

    settings = _settings(args)
    logging.basicConfig(level=settings.log_level.upper(),
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    from app.lab.placement import lab_workers

    workers = lab_workers(settings, getattr(args, "workers", None))
    if workers > 1:  # a lab over worker processes (app/lab)
        from app.lab.serve import serve_lab

        return serve_lab(settings, workers, access_log=bool(getattr(args, "access_log", False)))
    app = create_app(settings)
    if settings.host not in LOOPBACK and not settings.auth_enabled:
        log.warning("binding %s with no tokens: anyone who can reach this port may move the "
                    "arms (set ARMSERVER_OPERATOR_TOKENS)", settings.host)
    from app.web.serving import ArmServer

    config = uvicorn.Config(app, host=settings.host, port=settings.port,
                            log_level=settings.log_level, ws_max_size=settings.max_ws_message_bytes,
                            proxy_headers=False, ws_per_message_deflate=settings.ws_compression,
                            timeout_graceful_shutdown=settings.shutdown_timeout_s,
                            access_log=bool(getattr(args, "access_log", False)),
                            **http_limits(settings))
    ArmServer(config, app).run()
    return 0


def http_limits(settings: Any) -> dict[str, Any]:
    """uvicorn options that bound what one client can make the server do before any route
    runs: httptools' C parser with a bound on the request head (`max_header_bytes`: httptools
    has none of its own, a 64 MiB header took 3.8 s to parse) and `max_connections` open at
    once (503 `busy`, JSON). See app/web/serving.py."""
    import functools

    from app.web.serving import ArmHttpToolsProtocol

    http = functools.partial(ArmHttpToolsProtocol, max_head=settings.max_header_bytes)
    return {"http": http, "limit_concurrency": settings.max_connections}


def _positive(text: str) -> int:
    n = int(text)
    if n < 1:
        raise argparse.ArgumentTypeError(f"must be 1 or more, got {n}")
    return n


def _setup_servos(args: argparse.Namespace) -> int:
    """`armserver setup-servos`: app/arms/dynamixel/setup.py; the reason on stderr and a
    non-zero exit when it finds nothing, several servos, or is refused."""
    from app.arms.dynamixel.setup import (
        EXIT_NONE,
        SCAN_ORDER,
        SetupError,
        report,
        set_up_joint,
    )
    from app.arms.loading import load_profile

    profile = load_profile(args.profile)
    rates = (SCAN_ORDER if not args.baudrates else
             tuple(int(r) for r in args.baudrates.split(",") if r.strip()))
    try:
        if args.joint is None:
            found = report(args.port, profile, timeout=args.timeout, rates=rates)
            if found.collisions:
                return 4
            if not found.found:
                print("armserver setup-servos: no servo answered at any standard baud rate "
                      "(check power, the cable and the adapter)", file=sys.stderr)
                return EXIT_NONE
            return 0
        set_up_joint(args.port, profile, args.joint, timeout=args.timeout, rates=rates)
    except SetupError as exc:
        print(f"armserver setup-servos: {exc.reason}", file=sys.stderr)
        return exc.exit_code
    except OSError as exc:
        print(f"armserver setup-servos: cannot open {args.port}: {exc}", file=sys.stderr)
        return 2
    return 0


def _devices(args: argparse.Namespace) -> int:
    from app.links.discovery import format_devices, list_devices

    print(format_devices(list_devices()))
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv and argv[0] == "sim":  # app.sim.serve owns its own flags
        from app.sim.serve import main as sim_main

        return int(sim_main(argv[1:]) or 0)
    args = _parser().parse_args(argv)
    from pydantic import ValidationError

    from app.config import ConfigError, settings_error

    try:
        return int(args.func(args) or 0)
    except ValidationError as exc:  # settings: say which variable and why, no traceback
        if exc.title != "Settings":
            raise
        print(f"armserver: {settings_error(exc)}", file=sys.stderr)
    except ConfigError as exc:
        print(f"armserver: {exc}", file=sys.stderr)
    return 2


def run() -> None:
    """The console entry point `armserver` (pyproject [project.scripts])."""
    raise SystemExit(main())


if __name__ == "__main__":
    run()
