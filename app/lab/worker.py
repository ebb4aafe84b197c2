"""One worker process of a lab (`python -m app.lab.worker`, started by app/lab/supervisor.py):
today's whole server (app/web/factory.py's app, its control thread, its links) over the arms
the plan gives worker `--index`, served on a Unix socket that only the front talks to.

The worker reads its settings from the JSON file the front wrote (`--settings`, in the lab's
0700 folder: it holds the tokens), so the front and every worker check the same tokens, hosts
and limits. It runs in its own session (a Ctrl-C at the terminal reaches the front only, which
passes each signal on once: the first stops the arms as `POST /stop` does, a second holds) and
stops itself if the front goes away without telling it (`watch_parent`).
"""

from __future__ import annotations

import argparse
import functools
import json
import logging
import os
import signal
import threading
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import uvicorn

from app.config import Settings
from app.lab.headers import CLIENT_HEADER
from app.lab.placement import plan_lab, worker_socket
from app.links.serial import on_terminal
from app.runtime.control_thread import TerminalHold
from app.teleop.config import load_teleop
from app.teleop.remote import Peer
from app.web.factory import create_app
from app.web.serving import ArmHttpToolsProtocol, ArmServer

log = logging.getLogger("armserver.lab")

#: How often a worker looks whether its front still runs, s.
PARENT_CHECK_S = 0.5


class FrontClient:
    """The client's address as the front saw it, for the audit log and the gates' messages:
    over the Unix socket uvicorn has none (`scope["client"]` is None)."""

    def __init__(self, app: Any) -> None:
        self.app = app

    async def __call__(self, scope: Any, receive: Any, send: Any) -> None:
        if scope["type"] in ("http", "websocket") and scope.get("client") is None:
            for key, value in scope["headers"]:
                if key == CLIENT_HEADER:
                    host, _, port = value.decode("latin-1").rpartition(":")
                    if host and port.isdigit():
                        scope = {**scope, "client": (host, int(port))}
                    break
        await self.app(scope, receive, send)


def watch_parent(parent: int) -> threading.Thread:
    """A daemon thread that signals this process (SIGTERM: stop the arms, then exit) once its
    parent is no longer `parent` (the front died, even by SIGKILL)."""
    def run() -> None:
        while os.getppid() == parent:
            time.sleep(PARENT_CHECK_S)
        log.warning("the lab's front (pid %d) is gone: stopping", parent)
        os.kill(os.getpid(), signal.SIGTERM)

    thread = threading.Thread(target=run, name="armserver-parent", daemon=True)
    thread.start()
    return thread


def uvicorn_config(app: Any, settings: Settings, access_log: bool = False,
                   **where: Any) -> uvicorn.Config:
    """The uvicorn options of `armserver serve` (app/cli.py: the same limits), bound to
    `where` (host and port, or uds)."""
    options: dict[str, Any] = {
        "log_level": settings.log_level, "proxy_headers": False,
        "ws_max_size": settings.max_ws_message_bytes,
        "ws_per_message_deflate": settings.ws_compression,
        "timeout_graceful_shutdown": settings.shutdown_timeout_s, "access_log": access_log,
        "http": functools.partial(ArmHttpToolsProtocol, max_head=settings.max_header_bytes),
        "limit_concurrency": settings.max_connections, **where}
    return uvicorn.Config(app, **options)


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m app.lab.worker")
    p.add_argument("--settings", required=True, help="the front's settings, JSON")
    p.add_argument("--index", type=int, required=True)
    p.add_argument("--workers", type=int, required=True)
    p.add_argument("--uds", required=True, help="the Unix socket to serve on")
    p.add_argument("--parent", type=int, required=True, help="the front's pid")
    args = p.parse_args(argv)
    settings = Settings(**json.loads(Path(args.settings).read_text(encoding="utf-8")))
    logging.basicConfig(level=settings.log_level.upper(),
                        format=f"%(asctime)s %(levelname)s worker {args.index} %(name)s: "
                               "%(message)s")
    plan = plan_lab(settings, args.workers)
    profiles = list(plan.workers[args.index])
    # An arm on a terminal anywhere in the lab: this worker's raised threads run at the
    # default too, for the life of the process (app/runtime/control_thread.py: the bytes of
    # a terminal in another worker come from a kernel worker these would keep from a CPU).
    terminals = any(on_terminal(p.link.kind, p.link.address) for arms in plan.workers
                    for p in arms)
    hold = TerminalHold() if terminals else None
    watch_parent(args.parent)
    app = create_app(settings, profiles, plan.cameras_of(args.index))
    # the other workers' arms: a teleoperation leader may be one (app/teleop/remote.py), and
    # the config's [[teleop]] defaults name them (checked against every arm of the lab)
    folder = Path(args.uds).parent
    app.state.lab_peers = {p.name: Peer(p, worker_socket(folder, k))
                           for k, arms in enumerate(plan.workers) if k != args.index
                           for p in arms}
    app.state.teleop_pairs = load_teleop(settings.config, [p for arms in plan.workers
                                                           for p in arms])
    Path(args.uds).unlink(missing_ok=True)
    ArmServer(uvicorn_config(FrontClient(app), settings, uds=args.uds), app).run()
    if hold is not None:
        hold.release()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
