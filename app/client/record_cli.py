"""`armserver record ...`: recordings (LeRobot v3.0 datasets on the server) from a shell,
through the client (API.md "Recordings (v1.2)").

    armserver record create demo --arm openmanipulator_x --camera openmanipulator_x --fps 30 \\
        --task "pick the red cube"
    armserver record start demo          # an episode records ...
    armserver record stop demo           # ... and is written
    armserver record discard demo        # (or thrown away)
    armserver record list | show demo | archive demo -o demo.tar

Answers print as JSON, refusals as `{"code", "detail", "status"}` on stderr, like `call`.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from app.client.cli import RawText, _add_connection, run_call
from app.client.sync import ArmClient


def _archive(c: ArmClient, a: argparse.Namespace) -> Any:
    data = c.recording_archive(a.name)
    out = Path(a.output or f"{a.name}.tar")
    if str(out) == "-":
        sys.stdout.buffer.write(data)
        return RawText("")
    out.write_bytes(data)
    return {"archive": str(out), "bytes": len(data)}


def add_record(sub: Any) -> None:
    p = sub.add_parser("record", help="recordings: LeRobot datasets of episodes on the server",
                       description="Create datasets, record episodes into them, download them.")
    _add_connection(p)
    cmds = p.add_subparsers(dest="command", required=True, metavar="COMMAND")

    def cmd(name: str, action: Any, help: str) -> argparse.ArgumentParser:
        c: argparse.ArgumentParser = cmds.add_parser(name, help=help, description=help)
        c.set_defaults(action=action)
        _add_connection(c, suppress=True)
        return c

    cmd("list", lambda c, a: c.recordings(), "every dataset")
    sh = cmd("show", lambda c, a: c.recording(a.name), "one dataset, its current episode")
    cr = cmd("create", lambda c, a: c.create_recording(a.name, a.arm, a.camera or [], a.fps,
                                                       a.task),
             "a new dataset of ARMs (in the order given) and CAMERAs")
    cr.add_argument("--arm", action="append", required=True, help="an arm (repeat for more)")
    cr.add_argument("--camera", action="append", default=None, help="a camera (repeat)")
    cr.add_argument("--fps", type=int, default=30, help="frames per second (default 30)")
    cr.add_argument("--task", default="demonstration", help="what the episodes show")
    st = cmd("start", lambda c, a: c.start_episode(a.name, a.task), "start an episode")
    st.add_argument("--task", default=None, help="this episode's task (default: the dataset's)")
    sp = cmd("stop", lambda c, a: c.stop_episode(a.name), "end the episode and write it")
    di = cmd("discard", lambda c, a: c.discard_episode(a.name), "throw the episode away")
    ar = cmd("archive", _archive, "download the dataset as a tar file")
    ar.add_argument("-o", "--output", default=None, help="file (default NAME.tar; - stdout)")
    for c in (sh, cr, st, sp, di, ar):
        c.add_argument("name", help="the dataset's name")
    p.set_defaults(func=run_call)
