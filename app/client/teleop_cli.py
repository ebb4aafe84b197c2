"""`armserver teleop ...`: a teleoperation session from a shell, through the client (API.md
"Teleoperation (v1.2)").

    armserver teleop --leader leader --follower follower --rate 50
    armserver teleop --leader leader --follower follower --free-leader --load-supported

It takes the follower's lease (renewed while it runs; `--lease ID` uses one already held),
starts the session, prints its figures every second (achieved rate, latency p50/p99 from a
leader sample to the follower's command, commands, holds and why it holds) and stops it on
Ctrl-C (SIGINT) or SIGTERM: the follower holds where it is. Exit 0 when stopped so, 1 when
the session ended on its own (an estop, another client's lease: the reason on stderr) or was
refused (`{"code", "detail", "status"}` on stderr, like `call`).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import signal
import sys
import threading
from collections.abc import Iterator
from typing import Any

from app import schemas as s
from app.client.cli import _add_connection, _client, _fail
from app.client.errors import ArmServerError
from app.client.sync import ArmClient


def line(t: s.TeleopSession) -> str:
    """One line of a session's figures."""
    lat = t.latency_ms
    state = t.status if t.status != "running" or t.held is None else f"held ({t.held})"
    return (f"{state:<10} {t.achieved_hz:6.1f} Hz  latency p50 "
            + ("   -   " if lat is None else f"{lat.p50:6.2f}") + " ms  p99 "
            + ("   -   " if lat is None else f"{lat.p99:6.2f}")
            + f" ms  commands {t.commands}  holds {t.holds}")


@contextlib.contextmanager
def _follower_lease(c: ArmClient, a: argparse.Namespace) -> Iterator[None]:
    """The follower's lease for the session: `--lease` as given, else taken and renewed."""
    if a.lease:
        yield
        return
    with c.hold_lease(a.follower):
        yield


@contextlib.contextmanager
def _stop_signals() -> Iterator[threading.Event]:
    """An event set by SIGINT (Ctrl-C) or SIGTERM while the session runs; the handlers as
    they were afterwards."""
    stop = threading.Event()
    old = {sig: signal.signal(sig, lambda *_: stop.set())
           for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield stop
    finally:
        for sig, handler in old.items():
            signal.signal(sig, handler)


def run_teleop(a: argparse.Namespace) -> int:
    try:
        with _client(a) as c, _follower_lease(c, a):
            t = c.start_teleop(a.leader, a.follower, rate_hz=a.rate, mapping=a.mapping,
                               deadman_s=a.deadman, free_leader=a.free_leader,
                               load_supported=a.load_supported)
            print(f"teleop {t.id}: {t.leader} -> {t.follower} at {t.rate_hz:g} Hz "
                  f"({t.mapping}{', leader by hand' if t.free_leader else ''}); "
                  "Ctrl-C stops", flush=True)
            with _stop_signals() as stop:
                while not stop.wait(a.every):
                    now = _find(c.teleop_sessions(), t.id)
                    print(line(now), flush=True)
                    if now.status != "running":
                        print(json.dumps({"ended": now.reason}), file=sys.stderr)
                        return 1
            end = c.stop_teleop(t.id)
            print(line(end), flush=True)
            print(f"stopped: {end.reason}", flush=True)
            return 0
    except ArmServerError as exc:
        return _fail(exc)
    except ValueError as exc:  # a request the schemas refuse before it is sent
        print(json.dumps({"code": "invalid_request", "detail": str(exc), "status": 0}),
              file=sys.stderr)
        return 1


def _find(sessions: list[s.TeleopSession], sid: str) -> s.TeleopSession:
    for t in sessions:
        if t.id == sid:
            return t
    raise ArmServerError("not_found", f"teleoperation session {sid} is gone", 404)


def add_teleop(sub: Any) -> None:
    p = sub.add_parser("teleop", help="teleoperation: a leader arm drives a follower until "
                       "Ctrl-C", description="Start a teleoperation session (the follower's "
                       "lease taken unless --lease), print its figures every second, stop it "
                       "on Ctrl-C: the follower holds where it is.")
    _add_connection(p)
    p.add_argument("--leader", required=True, help="the arm that leads")
    p.add_argument("--follower", required=True, help="the arm that follows")
    p.add_argument("--rate", type=float, default=50.0, help="commands a second, 30..100 "
                   "(default 50)")
    p.add_argument("--mapping", choices=["joints", "tip"], default="joints",
                   help="joints one to one (like arms) or through the tip (default joints)")
    p.add_argument("--deadman", type=float, default=0.2, help="a leader sample older than "
                   "this (s) holds the follower (default 0.2)")
    p.add_argument("--free-leader", action=argparse.BooleanOptionalAction, default=None,
                   help="the leader's torque off for the session, to be moved by hand "
                   "(default: a real leader's; a simulated one is then moved by PUT "
                   "/arms/{leader}/world/hand)")
    p.add_argument("--load-supported", action="store_true",
                   help="the freed leader's joints that fall without torque (an "
                   "OpenManipulator-X's shoulder, elbow and wrist; the angler's z winch) are "
                   "held by hand or rest: without it such a leader is refused (409 in_use)")
    p.add_argument("--every", type=float, default=1.0, help="print the figures every this "
                   "many seconds (default 1)")
    p.set_defaults(func=run_teleop)
