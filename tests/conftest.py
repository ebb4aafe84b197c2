"""Fixtures for the API tests: the real app over the simulated arms, in process (httpx over
ASGI, lifespan running) and over a real uvicorn server on a loopback port (for WebSockets).

No part of our code is mocked: the simulators sit behind the links and answer the bytes the
hardware would. Every app fixture asserts at teardown that the last-resort error handler was
never hit (a request that reaches it is a bug, whatever status it got).
"""

from __future__ import annotations

import asyncio
import atexit
import contextlib
import logging
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import threading
import time
import traceback
from collections.abc import AsyncIterator, Awaitable, Callable, Iterator
from dataclasses import dataclass
from typing import Any

import httpx
import pytest
import uvicorn
from fastapi import FastAPI

from app.cli import http_limits
from app.config import ArmProfile, Settings
from app.web.factory import create_app
from tests._scheduling import HeaviestFileFirst, Lanes, order_heaviest_first

#: How long the simulated arms may take to answer their first poll, s.
READY_TIMEOUT_S = 10.0
OPERATOR = "op-token-1"
VIEWER = "viewer-token-1"


#: The stores of make_settings' servers, a folder each under one folder per test process,
#: removed when that process exits (a store outlives its test: module-scoped servers, and a
#: restart test opens it again); before, each was a folder of its own in /tmp, left behind.
_DATA_ROOT = tempfile.mkdtemp(prefix="armserver-tests-")
_ROOT_PID = os.getpid()


@atexit.register
def _remove_data_root() -> None:
    if os.getpid() == _ROOT_PID:  # not a forked child's exit
        shutil.rmtree(_DATA_ROOT, ignore_errors=True)


def make_settings(**over: Any) -> Settings:
    """Settings independent of the environment the tests run in. `warm_start` off: the suite
    starts a server per test, and building every route and a full collection at each start
    were some 0.25 s of CPU a test (tests/test_warm_routes.py starts its servers warm)."""
    base: dict[str, Any] = {"config": None, "operator_tokens": "", "viewer_tokens": "",
                            "instructor_tokens": "", "cors_origins": "", "lease_ttl_s": 5.0,
                            "warm_start": False,
                            # a fresh store for each server (module-scoped servers start before
                            # the per-test ARMSERVER_DATA_DIR below is set)
                            "data_dir": tempfile.mkdtemp(prefix="data-", dir=_DATA_ROOT),
                            # the Host names of the in-process clients (httpx below, and
                            # schemathesis's ASGI client): an open server answers only its own
                            "allowed_hosts": "armserver.test,testserver"}
    base.update(over)
    return Settings(**base)


#: A reply timeout for a simulator that answers from the test's own process over a real
#: transport (a pty, `socket://`): beside busy workers its reply came after the profiles' 50 ms
#: and read as silence, where a real device's bytes wait in the UART for a late reader. Tests
#: that judge timeouts themselves keep the profile's own.
IN_PROCESS_REPLY_S = 0.3
#: The same over a pty, where a kernel worker at niceness 0 hands the bytes over, which other
#: processes' raised threads can hold off (session 24): 0.3 s ran out in a clean clone's run
#: (session 34: the angler's READ over a pty, its worker's first test, four workers starting),
#: and a late rbe3001 reply, cut by the timeout, was read as a corrupt one under load (session
#: 33). For tests over a pty that judge no time.
PTY_REPLY_S = 1.5


def with_reply_timeout(profile: ArmProfile, seconds: float | None = None) -> ArmProfile:
    """`profile` with its link's per-request reply timeout set to `seconds` (None:
    IN_PROCESS_REPLY_S)."""
    return profile.model_copy(update={"link": profile.link.model_copy(
        update={"timeout_s": IN_PROCESS_REPLY_S if seconds is None else seconds})})


def thread_niceness(pid: int, tid: int) -> int:
    """A thread's niceness, from /proc (field 19 of its stat, after the command's parentheses)."""
    with open(f"/proc/{pid}/task/{tid}/stat") as f:
        stat = f.read()
    return int(stat[stat.rindex(")") + 2:].split()[16])


def threads_niceness(pid: int) -> list[int]:
    """The niceness of every thread of process `pid`."""
    return [thread_niceness(pid, int(tid)) for tid in os.listdir(f"/proc/{pid}/task")]


def may_raise_priority(niceness: int) -> bool:
    """Whether a process here may set itself to `niceness` (root, CAP_SYS_NICE), asked of a
    child so that this one keeps its own."""
    probe = f"import os; os.setpriority(os.PRIO_PROCESS, 0, {niceness})"
    return subprocess.run([sys.executable, "-c", probe], capture_output=True).returncode == 0


async def wait_ready(app: FastAPI, timeout: float = READY_TIMEOUT_S) -> None:
    """Until every arm has published a fresh sample."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        services = getattr(app.state, "services", {})
        if services and all(s.hub.latest is not None and not s.driver.stale
                            for s in services.values()):
            return
        await asyncio.sleep(0.02)
    raise TimeoutError("the simulated arms did not answer in time")


@contextlib.asynccontextmanager
async def running_client(settings: Settings | None = None,
                         headers: dict[str, str] | None = None,
                         profiles: list[ArmProfile] | None = None
                         ) -> AsyncIterator[tuple[FastAPI, httpx.AsyncClient]]:
    """The app in process (lifespan running) over `profiles` (default: the default simulated
    arms), an httpx client over ASGI."""
    app = create_app(settings or make_settings(), profiles=profiles)
    async with app.router.lifespan_context(app):
        await wait_ready(app)
        transport = httpx.ASGITransport(app=app)
        async with httpx.AsyncClient(transport=transport, base_url="http://armserver.test",
                                     headers=headers, timeout=30.0) as client:
            yield app, client
    assert app.state.internal_errors == 0, "the last-resort error handler was hit"


@pytest.fixture(params=["c", "python"])
def poll_rest(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> str:
    """The test runs twice: the poll thread's rounds of arms at rest in C (the default where
    app/links/_restpoll.c was built) and in Python (ARMSERVER_POLL_REST=python's)."""
    from app.links import poller

    if request.param == "python":
        monkeypatch.setattr(poller, "REST_IN_C", False)
    return str(request.param)


@pytest.fixture(autouse=True)
def _data_dir(tmp_path_factory: pytest.TempPathFactory, monkeypatch: pytest.MonkeyPatch) -> None:
    """Each test's server keeps its store (safety settings) in a fresh directory, so that no
    test sees another's settings and none writes ./data."""
    monkeypatch.setenv("ARMSERVER_DATA_DIR", str(tmp_path_factory.mktemp("data")))


@pytest.fixture
async def app_and_client() -> AsyncIterator[tuple[FastAPI, httpx.AsyncClient]]:
    async with running_client() as pair:
        yield pair


@pytest.fixture
async def app_client(app_and_client: tuple[FastAPI, httpx.AsyncClient]) -> httpx.AsyncClient:
    """httpx client over the default app (simulated rbe3001 and angler, no tokens)."""
    return app_and_client[1]


@pytest.fixture
def client_factory() -> Callable[..., Any]:
    """`async with client_factory(settings, headers) as (app, client)`."""
    return running_client


# ---------------------------------------------------------------- live server


@dataclass
class LiveServer:
    url: str
    ws_url: str
    app: FastAPI
    server: uvicorn.Server
    loop: asyncio.AbstractEventLoop

    def call(self, fn: Callable[[], Awaitable[Any]], timeout: float = 10.0) -> Any:
        """Run a coroutine in the server's own loop (services belong to it)."""
        return asyncio.run_coroutine_threadsafe(fn(), self.loop).result(timeout)


def _free_socket(sndbuf: int | None) -> socket.socket:
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    if sndbuf is not None:  # inherited by accepted sockets: a small pipe to each client
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, sndbuf)
    sock.bind(("127.0.0.1", 0))
    return sock


@contextlib.contextmanager
def uvicorn_thread(server: uvicorn.Server, name: str, **serve: Any) -> Iterator[None]:
    """`server.serve(**serve)` on a thread of its own for the block: started (bounded wait),
    then stopped, and the thread must have ended (a thread that outlives its test spins
    beside every later one: session 31's flood)."""
    thread = threading.Thread(target=lambda: asyncio.run(server.serve(**serve)), name=name,
                              daemon=True)
    thread.start()
    deadline = time.monotonic() + 30.0  # (a bound for a loaded machine, not a timing)
    while not server.started:
        assert thread.is_alive() and time.monotonic() < deadline, f"{name} did not start"
        time.sleep(0.01)
    try:
        yield
    finally:
        server.should_exit = True
        thread.join(30)
        assert not thread.is_alive(), f"{name}'s thread outlived the test"


@contextlib.contextmanager
def serve_live(settings: Settings | None = None, sndbuf: int | None = None,
               profiles: list[ArmProfile] | None = None) -> Iterator[LiveServer]:
    """A real uvicorn server on a free loopback port, in a thread, over `profiles` (default:
    the default simulated arms)."""
    settings = settings or make_settings()
    app = create_app(settings, profiles=profiles)
    sock = _free_socket(sndbuf)
    port = sock.getsockname()[1]
    config = uvicorn.Config(app, log_level="warning", lifespan="on",
                            ws_max_size=settings.max_ws_message_bytes, **http_limits(settings))
    server = uvicorn.Server(config)
    loop_box: dict[str, asyncio.AbstractEventLoop] = {}

    def run() -> None:
        async def main() -> None:
            loop_box["loop"] = asyncio.get_running_loop()
            await server.serve(sockets=[sock])
        asyncio.run(main())

    thread = threading.Thread(target=run, name="live-uvicorn", daemon=True)
    thread.start()
    deadline = time.monotonic() + READY_TIMEOUT_S
    while not server.started:
        if not thread.is_alive() or time.monotonic() > deadline:
            raise RuntimeError("uvicorn did not start")
        time.sleep(0.01)
    live = LiveServer(f"http://127.0.0.1:{port}", f"ws://127.0.0.1:{port}", app, server,
                      loop_box["loop"])
    live.call(lambda: wait_ready(app))
    try:
        yield live
    finally:
        server.should_exit = True
        thread.join(10)
        sock.close()
    # a server thread that outlives its test runs on beside the next ones (session 31: a
    # spinning one logged into every later test of its process)
    assert not thread.is_alive(), "the live server's thread outlived the test"
    assert app.state.internal_errors == 0, "the last-resort error handler was hit"


@pytest.fixture
def live_server() -> Iterator[LiveServer]:
    """A real uvicorn server on 127.0.0.1 (a free port) over the default simulated arms."""
    with serve_live() as live:
        yield live


#: Files whose tests run after the parallel part of `make test` (pytest-xdist), besides every
#: browser test (`pytest.mark.browser`: beside four workers a page took four times as long as
#: alone, the camera panel's 52 s against 13 s, and on CI's slower host over 10 s to draw an arm
#: at rest, stop 35): the tests that time the server itself (a bounded shutdown, a held-up
#: executor (test_control.py, test_replan.py: the hold-up is the scenario and its setpoints'
#: speed is measured), the measured peak speed of a device tracking a plan: a PID catching up
#: after a tick that two busy workers held up overshoots; the faults soak, whose moves must
#: finish between link cuts). A single test of another file is marked `@pytest.mark.serial`
#: where it is (the measured speed of test_envelope_props.py, the measured line deviation of
#: test_motion.py).
SERIAL_FILES = frozenset({
    "test_shutdown.py", "test_control.py", "test_tracking.py", "test_soak.py", "test_replan.py",
    # the practice bus: beside six busy workers a scan's PING was answered after the scan's
    # window (the README block's test twice in five runs, session 14, when the bus answered
    # from the server's own process); kept here until runs beside busy workers show the bus
    # in its own process holds
    "test_setup_servos_e2e.py", "test_setup_servos_readme.py", "test_setup_servos_routes.py",
})


#: `make test` runs the serial part in two lanes side by side (SERIAL_LANES=2, the default:
#: `-n 2 --dist loadgroup`; SERIAL_LANES=1, one test at a time): each lane keeps the machine
#: about 40 % of one core busy, waiting on arms moving in real time. One test of each lane at a
#: time, never two timing tests or two browser tests together: tests/_scheduling.py (`lane_of`,
#: and why xdist's own `xdist_group` marks no longer do it).
@pytest.hookimpl(tryfirst=True)
def pytest_collection_modifyitems(config: Any, items: list[Any]) -> None:
    if hasattr(config, "workerinput"):  # an xdist worker: its collection is the order handed out
        order_heaviest_first(items)
    for item in items:
        if item.path.name in SERIAL_FILES or item.get_closest_marker("browser") is not None:
            item.add_marker(pytest.mark.serial)


@pytest.hookimpl(tryfirst=True)  # before xdist's own (DSession), which would make its own
def pytest_xdist_make_scheduler(config: Any, log: Any) -> Any:
    dist = config.getvalue("dist")
    if dist == "loadfile":
        return HeaviestFileFirst(config, log)
    if dist == "loadgroup":
        return Lanes(config, log)
    return None


# ---------------------------------------------------------------- strict skips


def strict_skips() -> bool:
    """ARMSERVER_STRICT_SKIPS=1 (`.ci/run` sets it; CI=true implies it unless it is set to 0):
    a skip is a failure. A test skips when what it needs is missing (chromium, mosquitto, node:
    tests/_deps.py), and a skipped test proves nothing; `make test` installs them or fails, so in
    CI a skip can only mean a broken set-up, which must not pass as green."""
    flag = os.environ.get("ARMSERVER_STRICT_SKIPS", "").strip().lower()
    if flag:
        return flag not in ("0", "false", "no", "off")
    return os.environ.get("CI", "").strip().lower() in ("1", "true", "yes")


def _reason(longrepr: Any) -> str:
    if isinstance(longrepr, tuple) and len(longrepr) == 3:  # (file, line, "Skipped: why")
        return f"{longrepr[2]} ({longrepr[0]}:{longrepr[1]})"
    return str(longrepr)


def _fail_skip(report: Any) -> None:
    report.outcome = "failed"
    report.longrepr = ("skipped under ARMSERVER_STRICT_SKIPS (CI), which makes a skip a "
                       f"failure: {_reason(report.longrepr)}")


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item: Any, call: Any) -> Iterator[None]:
    outcome = yield
    report = outcome.get_result()  # type: ignore[attr-defined]
    # an xfail is reported as a skip with `wasxfail`: that one is expected, not a skip
    if report.skipped and not hasattr(report, "wasxfail") and strict_skips():
        _fail_skip(report)


@pytest.hookimpl(hookwrapper=True)
def pytest_make_collect_report(collector: Any) -> Iterator[None]:
    outcome = yield
    report = outcome.get_result()  # type: ignore[attr-defined]
    if report.skipped and strict_skips():  # a module-level pytest.skip / importorskip
        _fail_skip(report)


class _NameTheWriter(logging.Filter):
    """asyncio's "socket.send() raised exception." (a write on a transport whose connection
    is gone) with the thread and the code that wrote: the warning alone names neither, and a
    writer that spins logs it into every later test of its process (session 31: a test
    server's loop of sends, found only with this)."""

    def filter(self, record: logging.LogRecord) -> bool:
        if record.msg == "socket.send() raised exception.":
            frames = [f for f in traceback.extract_stack()
                      if "/asyncio/" not in f.filename and "/logging/" not in f.filename]
            where = "; ".join(f"{f.filename.rsplit('/', 2)[-1]}:{f.lineno} {f.name}"
                              for f in frames[-7:-1])
            record.msg = (f"{record.msg} (thread {threading.current_thread().name}, "
                          f"written by {where})")
        return True


logging.getLogger("asyncio").addFilter(_NameTheWriter())
