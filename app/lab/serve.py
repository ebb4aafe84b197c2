"""`armserver serve --workers N`: the lab's front on the public address, its workers behind it.

The front process writes its settings (tokens included) to a 0700 folder of its own for the
workers to read, starts them (app/lab/supervisor.py) and serves app/lab/front.py with uvicorn
on `host:port`, with the same limits as a single server (header bytes, connections, body, the
WebSocket message size). A SIGINT/SIGTERM goes on to every worker at once (`LabServer`: the
first stops their arms as `POST /stop` does, a second holds them), then the front shuts down.
"""

from __future__ import annotations

import logging
import os
import shutil
import tempfile
from pathlib import Path

import uvicorn

from app.config import Settings
from app.doors.uvicorn import SignalServer
from app.lab.front import LabFront
from app.lab.placement import plan_lab, worker_socket
from app.lab.supervisor import Supervisor, Worker
from app.lab.upstream import Upstream
from app.lab.worker import uvicorn_config
from app.web.middleware import HeadAsGet

log = logging.getLogger("armserver.lab")

#: Kept-alive connections from the front to each worker.
KEEPALIVE = 64


class LabServer(SignalServer):
    """The front's uvicorn server: each signal it takes goes to the workers at once (the
    first: every arm stops as `POST /stop` does; a second: they hold), then uvicorn's own
    shutdown, whose lifespan end waits for the workers."""

    def __init__(self, config: uvicorn.Config, supervisor: Supervisor) -> None:
        super().__init__(config)
        self.supervisor = supervisor

    def first_signal(self, sig: int) -> None:
        log.warning("signal %d: stopping every worker's arms, then shutting down", sig)
        self.supervisor.signal_all(sig)

    def again(self, sig: int) -> None:
        log.warning("signal %d again: every worker holds its arms and exits now", sig)
        self.supervisor.signal_all(sig)


def worker_client(uds: Path) -> Upstream:
    """The front's connection pool to one worker, over its Unix socket."""
    return Upstream(uds, KEEPALIVE)


def build_front(settings: Settings, count: int, folder: Path) -> LabFront:
    """The front over `count` workers (those the plan leaves without arms are not started)."""
    plan = plan_lab(settings, count)
    settings_file = folder / "settings.json"
    fd = os.open(settings_file, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w", encoding="utf-8") as f:
        f.write(settings.model_dump_json())
    workers = [Worker(k, tuple(p.name for p in arms), worker_socket(folder, k),
                      worker_client(worker_socket(folder, k)))
               for k, arms in enumerate(plan.workers) if arms]
    return LabFront(plan, Supervisor(workers, settings_file, count), settings)


def serve_lab(settings: Settings, count: int, access_log: bool = False) -> int:
    """Run the lab until a signal: the front on settings.host:port, `count` workers."""
    folder = Path(tempfile.mkdtemp(prefix="armserver-lab-"))  # 0700
    try:
        front = build_front(settings, count, folder)
        if settings.host not in ("127.0.0.1", "::1", "localhost") and not settings.auth_enabled:
            log.warning("binding %s with no tokens: anyone who can reach this port may move "
                        "the arms (set ARMSERVER_OPERATOR_TOKENS)", settings.host)
        for w in front.workers:
            log.info("worker %d will host %s", w.index, ", ".join(w.arms))
        # (HEAD as GET without the body, as each worker's app: app/web/middleware.py)
        config = uvicorn_config(HeadAsGet(front), settings, access_log, host=settings.host,
                                port=settings.port, lifespan="on")
        LabServer(config, front.supervisor).run()
    finally:
        shutil.rmtree(folder, ignore_errors=True)
    return 0
