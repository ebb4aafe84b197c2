"""`armserver call ARM ...` and `armserver watch ARM`: the client from a shell.

`app.cli` adds these to `armserver` through `register_client_commands(subparsers)`; each
subcommand sets `func(args) -> int` (the exit status). Standalone: `python -m app.client.cli`.

`call` prints the answer as pretty JSON on stdout; a refused request prints
`{"code", "detail", "status"}` on stderr and exits 1 (2 if the server cannot be reached).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from collections.abc import Callable, Sequence
from typing import Any

from pydantic import BaseModel

from app import schemas as s
from app.client.errors import ArmServerError, ConnectionFailed
from app.client.sync import ArmClient

DEFAULT_URL = "http://127.0.0.1:8000"

Action = Callable[[ArmClient, argparse.Namespace], Any]


def _add_connection(p: argparse.ArgumentParser, suppress: bool = False) -> None:
    """The connection options; `suppress` on a sub-command's parser so they may be given after
    the command too (`call rbe3001 state --url ...`) without overriding those given before."""
    def d(value: Any) -> Any:
        return argparse.SUPPRESS if suppress else value

    p.add_argument("--url", default=d(os.environ.get("ARMSERVER_URL", DEFAULT_URL)),
                   help="server base URL (env ARMSERVER_URL; default http://127.0.0.1:8000)")
    p.add_argument("--token", default=d(os.environ.get("ARMSERVER_TOKEN")),
                   help="bearer token (env ARMSERVER_TOKEN)")
    p.add_argument("--lease", default=d(None), help="lease id to send as X-Arm-Lease")
    p.add_argument("--timeout", type=float, default=d(10.0), help="request timeout, s")


def _move_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--duration", type=float, default=None, help="move duration, s")
    p.add_argument("--speed", type=float, default=1.0, help="speed fraction 0..1")
    p.add_argument("--mode", choices=["queue", "replace"], default="queue")
    p.add_argument("--wait", action="store_true", help="answer when the motion ends")


def _move_pose(c: ArmClient, a: argparse.Namespace) -> Any:
    return c.move_pose(a.arm, a.x, a.y, a.z, path=a.path, branch=a.branch, ik_case=a.ik_case,
                       duration=a.duration, speed=a.speed, mode=a.mode, wait=a.wait)


def _move_joints(c: ArmClient, a: argparse.Namespace) -> Any:
    return c.move_joints(a.arm, a.q, duration=a.duration, speed=a.speed, mode=a.mode,
                         wait=a.wait)


def _add_call(sub: Any) -> None:
    p = sub.add_parser("call", help="send one request to an arm and print the answer as JSON",
                       description="Send one request to an arm; print the answer as JSON.")
    _add_connection(p)
    p.add_argument("arm", help="arm name, e.g. rbe3001 or angler")
    cmds = p.add_subparsers(dest="command", required=True, metavar="COMMAND")

    def cmd(name: str, action: Action, help: str) -> argparse.ArgumentParser:
        c: argparse.ArgumentParser = cmds.add_parser(name, help=help, description=help)
        c.set_defaults(action=action)
        _add_connection(c, suppress=True)
        return c

    cmd("info", lambda c, a: c.arm(a.arm), "describe the arm (joints, link, capabilities)")
    cmd("state", lambda c, a: c.state(a.arm), "latest telemetry sample")
    mp = cmd("move-pose", _move_pose, "move the tip to X Y Z (m)")
    for axis in ("x", "y", "z"):
        mp.add_argument(axis, type=float)
    mp.add_argument("--path", choices=["joint", "line"], default="joint")
    mp.add_argument("--branch", type=int, default=None, help="IK solution index")
    mp.add_argument("--ik-case", choices=["dx_zero", "dx_used"], default=None, help="angler")
    _move_options(mp)
    mj = cmd("move-joints", _move_joints, "joint-space move to Q... (rad / m)")
    mj.add_argument("q", type=float, nargs="+", metavar="Q")
    _move_options(mj)
    mo = cmd("motion", lambda c, a: c.motion(a.arm, a.id), "status of motion ID")
    mo.add_argument("id")
    ca = cmd("cancel", lambda c, a: c.cancel_motion(a.arm, a.id), "cancel motion ID")
    ca.add_argument("id")
    cmd("stop", lambda c, a: c.stop(a.arm), "stop all motion; the arm holds")
    cmd("estop", lambda c, a: c.estop(a.arm), "latch the emergency stop")
    cmd("release", lambda c, a: c.release_estop(a.arm), "release the emergency stop")
    tq = cmd("torque", lambda c, a: c.set_torque(a.arm, a.on == "on", a.load_supported),
             "the joints' torque off (moved by hand) or on again (holding)")
    tq.add_argument("on", choices=["on", "off"])
    tq.add_argument("--load-supported", action="store_true",
                    help="the joints that fall without torque are held or rest")
    gr = cmd("gripper", lambda c, a: c.gripper(a.arm, a.value), "gripper 0 open .. 1 closed")
    gr.add_argument("value", type=float)
    fk = cmd("forward", lambda c, a: c.forward(a.arm, a.q), "forward kinematics of Q...")
    fk.add_argument("q", type=float, nargs="+", metavar="Q")
    ik = cmd("inverse", lambda c, a: c.inverse(a.arm, a.x, a.y, a.z, ik_case=a.ik_case),
             "every IK solution of X Y Z (m)")
    for axis in ("x", "y", "z"):
        ik.add_argument(axis, type=float)
    ik.add_argument("--ik-case", choices=["dx_zero", "dx_used"], default=None)
    cmd("status", lambda c, a: c.rbe3001_status(a.arm), "rbe3001: raw STATUS (ticks, ADC)")
    pg = cmd("ping", lambda c, a: c.dxl_ping(a.arm, a.id), "dynamixel: ping one id or all")
    pg.add_argument("id", type=int, nargs="?", default=None)
    qu = cmd("queue", _queue, "the arm's classroom queue: join, leave ID, status")
    qu.add_argument("what", choices=["join", "leave", "status"])
    qu.add_argument("id", nargs="?", default=None, help="the entry id (leave)")
    cmd("revoke", lambda c, a: c.revoke_lease(a.arm), "instructor: end the arm's lease")
    au = cmd("audit", _audit, "instructor: the arm's audit log, newest first")
    au.add_argument("--who", default=None, help="only this person's records")
    au.add_argument("--limit", type=int, default=50)
    au.add_argument("--csv", action="store_true", help="print CSV")
    p.set_defaults(func=run_call)


def _queue(c: ArmClient, a: argparse.Namespace) -> Any:
    if a.what == "join":
        return c.join_queue(a.arm)
    if a.what == "leave":
        if not a.id:
            raise ValueError("queue leave needs the entry id (from queue join or status)")
        return c.leave_queue(a.arm, a.id)
    return c.queue(a.arm)


def _audit(c: ArmClient, a: argparse.Namespace) -> Any:
    if a.csv:
        return RawText(c.audit_csv(arm=a.arm, who=a.who, limit=a.limit))
    return c.audit(arm=a.arm, who=a.who, limit=a.limit)


class RawText(str):
    """An answer printed as it is, not as JSON."""


def _add_watch(sub: Any) -> None:
    p = sub.add_parser("watch", help="print an arm's telemetry live, one line per message",
                       description="Print an arm's telemetry live: one line per message.")
    _add_connection(p)
    p.add_argument("arm")
    p.add_argument("--rate", type=float, default=10.0, help="messages per second (default 10)")
    p.add_argument("--events", action="store_true", help="print events as well")
    p.add_argument("--count", type=int, default=0, help="stop after N messages (0: never)")
    p.set_defaults(func=run_watch)


def register_client_commands(subparsers: Any) -> None:
    """Add `call` and `watch` to an argparse subparsers object (from `add_subparsers()`)."""
    _add_call(subparsers)
    _add_watch(subparsers)


def _json(obj: Any) -> str:
    if isinstance(obj, BaseModel):
        return obj.model_dump_json(indent=2)
    if isinstance(obj, list):
        return json.dumps([o.model_dump(mode="json") if isinstance(o, BaseModel) else o
                           for o in obj], indent=2)
    return json.dumps(obj, indent=2)


def _fail(exc: ArmServerError) -> int:
    print(json.dumps({"code": exc.code, "detail": exc.detail, "status": exc.status}, indent=2),
          file=sys.stderr)
    return 2 if isinstance(exc, ConnectionFailed) else 1


def _client(a: argparse.Namespace) -> ArmClient:
    return ArmClient(a.url, token=a.token, lease=a.lease, timeout=a.timeout)


def run_call(a: argparse.Namespace) -> int:
    try:
        with _client(a) as c:
            result = a.action(c, a)
    except ArmServerError as exc:
        return _fail(exc)
    except ValueError as exc:  # a request the schemas refuse before it is sent
        print(json.dumps({"code": "invalid_request", "detail": str(exc), "status": 0}, indent=2),
              file=sys.stderr)
        return 1
    if isinstance(result, RawText):
        print(result, end="")
        return 0
    print(_json(result) if result is not None else "null")
    return 0


def _fmt(v: Sequence[float]) -> str:
    return "[" + ", ".join(f"{x:+.4f}" for x in v) + "]"


def format_message(msg: s.TelemetryMessage | s.EventMessage) -> str:
    """One line: the last sample of a batch (seq, joints, tip) with batch size and drops."""
    if isinstance(msg, s.EventMessage):
        return f"event {msg.event} {json.dumps(msg.data, default=str)}"
    if not msg.samples:
        return f"seq - n=0 dropped={msg.dropped}"
    last = msg.samples[-1]
    tip = last.tip
    motion = f" motion={last.motion.id}:{last.motion.status}" if last.motion else ""
    return (f"seq {last.seq} n={len(msg.samples)} dropped={msg.dropped} "
            f"joints={_fmt(last.positions)} tip={_fmt((tip.x, tip.y, tip.z))}"
            f"{' ESTOP' if last.estop else ''}{motion}")


def run_watch(a: argparse.Namespace) -> int:
    n = 0
    try:
        with _client(a) as c:
            for msg in c.telemetry_messages(a.arm, rate=a.rate):
                if isinstance(msg, s.EventMessage) and not a.events:
                    continue
                print(format_message(msg), flush=True)
                n += 1
                if a.count and n >= a.count:
                    break
    except ArmServerError as exc:
        return _fail(exc)
    except KeyboardInterrupt:
        pass
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m app.client.cli",
                                     description="armserver client commands")
    sub = parser.add_subparsers(dest="cmd", required=True)
    register_client_commands(sub)
    args = parser.parse_args(argv)
    return int(args.func(args))


if __name__ == "__main__":
    sys.exit(main())
