"""A lab behind one address (issue 27): `armserver serve --workers 2` as a real process, its
workers real processes on their own Unix sockets, the simulated arms behind their links.

The front routes each arm's HTTP and WebSocket to the worker that owns it, merges `/arms` and
`/health`, passes tokens and leases through unchanged; a worker killed with SIGKILL is
restarted and its arm comes back while the other worker's samples go on without a gap.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import json
import os
import signal
import sqlite3
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
import pytest
from _serve import clean_env, start
from _wait import wait_for, wait_until
from conftest import OPERATOR, VIEWER, may_raise_priority, threads_niceness
from websockets.asyncio.client import connect
from websockets.exceptions import ConnectionClosed

from app.store import DB_NAME

CONFIG = """
[[arms]]
profile = "rbe3001"
name = "left"
worker = 0

[[arms]]
profile = "rbe3001"
name = "right"
worker = 1

[[arms]]
profile = "angler"
name = "rails"

[[cameras]]
name = "table-left"
arm = "left"
source = "sim:left"

[[cameras]]
name = "table-right"
arm = "right"
source = "sim:right"

[[teleop]]
leader = "left"
follower = "right"
deadman_s = 0.5
"""
ARMS = ["left", "right", "rails"]
AUTH = {"Authorization": f"Bearer {VIEWER}"}
OP = {"Authorization": f"Bearer {OPERATOR}"}
INSTRUCTOR = "instructor-token-lab"
#: A worker's arms are back within this, s (issue 27 asks 5 s; a loaded two-core machine
#: gets slack, a restarting worker's imports alone took 7 s at load average 7: the bound of a
#: wait, not a timing assert; the tests print the time taken).
BACK_WITHIN_S = 30.0
#: The lab is up within this, s (a bound, not a timing assert).
START_WITHIN_S = 120.0


@dataclass
class Lab:
    proc: subprocess.Popen[bytes]
    url: str
    ws: str
    #: The lab's data folder (its store, shared by the workers), and its log.
    data: Path | None = None
    log: Path | None = None

    def workers(self) -> dict[int, int]:
        """The worker processes' pids by worker index."""
        pid = self.proc.pid
        children = Path(f"/proc/{pid}/task/{pid}/children").read_text().split()
        out = {}
        for child in children:
            try:
                argv = argv_of(int(child))
            except FileNotFoundError:
                continue
            if b"app.lab.worker" in argv:
                out[int(arg_after(argv, b"--index"))] = int(child)
        return out


def argv_of(pid: int) -> list[bytes]:
    """A process's command line, as its arguments."""
    return Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")


def arg_after(argv: list[bytes], flag: bytes) -> str:
    """The value that follows `flag` in `argv`."""
    return argv[argv.index(flag) + 1].decode()


@pytest.fixture(scope="module")
def lab(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Lab]:
    folder = tmp_path_factory.mktemp("lab")
    (folder / "lab.toml").write_text(CONFIG)
    env = clean_env(ARMSERVER_DATA_DIR=str(folder / "data"), ARMSERVER_VIEWER_TOKENS=VIEWER,
                    ARMSERVER_OPERATOR_TOKENS=OPERATOR,
                    ARMSERVER_INSTRUCTOR_TOKENS=INSTRUCTOR, ARMSERVER_LEASE_TTL_S="5")
    # the front's imports, then worker 0, then worker 1 (after worker 0 made the store):
    # about 14 s at load average 7 on two cores; a generous bound for a loaded machine
    srv = start(folder / "lab.log", "--workers", "2", "--config", str(folder / "lab.toml"),
                "--log-level", "warning", env=env, start_s=START_WITHIN_S, headers=AUTH)
    proc = srv.proc
    lab = Lab(proc, srv.url, srv.url.replace("http://", "ws://"), folder / "data",
              folder / "lab.log")
    try:
        yield lab
    finally:
        workers = list(lab.workers().values()) if proc.poll() is None else []
        folders = {Path(arg_after(argv_of(pid), b"--uds")).parent for pid in workers}
        srv.stop()
        for pid in workers:  # they stop with the front; a stuck one is this test's failure
            wait_until(lambda pid=pid: not Path(f"/proc/{pid}").exists()  # type: ignore[misc]
                       or b"zombie" in Path(f"/proc/{pid}/status").read_bytes().lower(),
                       what=f"worker {pid} stopped with the front")
        for folder in folders:  # its sockets and the settings file (tokens) with it
            assert not folder.exists(), sorted(folder.iterdir())


def test_each_arm_answers_from_its_own_worker(lab: Lab) -> None:
    with httpx.Client(base_url=lab.url, headers=AUTH) as c:
        arms = c.get("/api/v1/arms")
        assert arms.status_code == 200
        assert [a["name"] for a in arms.json()] == ARMS
        assert [a["model"] for a in arms.json()] == ["rbe3001", "rbe3001", "angler"]
        health = c.get("/api/v1/health").json()
        assert health["status"] == "ok" and health["auth"] is True
        assert list(health["arms"]) == ARMS
        assert all(link["connected"] for link in health["arms"].values())
        for arm in ARMS:
            state = c.get(f"/api/v1/arms/{arm}/state")
            assert state.status_code == 200, state.text
            assert len(state.json()["positions"]) in (3, 4)
            assert c.get(f"/api/v1/arms/{arm}").json()["name"] == arm
        missing = c.get("/api/v1/arms/nobody/state")
        assert missing.status_code == 404
        assert missing.json() == {"detail": "no arm 'nobody'; this server hosts left, right, "
                                  "rails", "code": "unknown_arm"}
        assert c.get("/api/v1/me").json()["role"] == "viewer"
        # each camera from the worker of its arm, the list merged
        cameras = c.get("/api/v1/cameras")
        assert cameras.status_code == 200, cameras.text
        assert [(cam["name"], cam["arm"]) for cam in cameras.json()] == [
            ("table-left", "left"), ("table-right", "right")]
        for name in ("table-left", "table-right"):
            one = c.get(f"/api/v1/cameras/{name}")
            assert one.status_code == 200 and one.json()["name"] == name, one.text
        # an answer that never ends (MJPEG) is relayed as it comes, until the client goes
        with c.stream("GET", "/api/v1/cameras/table-right/stream") as stream:
            assert stream.status_code == 200
            assert stream.headers["content-type"].startswith("multipart/x-mixed-replace")
            seen = b""
            for chunk in stream.iter_raw():
                seen += chunk
                if b"\xff\xd8" in seen:  # a JPEG's start: a frame came through
                    break
        assert b"\xff\xd8" in seen
        assert c.get("/").status_code == 200  # the dashboard
        # the workers are separate processes: one arm's latch is not another's
        # the front names the client's address to the worker (a client's own claim dropped)
        latched = c.post("/api/v1/arms/right/estop",
                         headers={"X-Armserver-Lab-Client": "203.0.113.9:1"})
        assert latched.status_code == 200 and latched.json() == {"estop": True}
        assert c.get("/api/v1/arms/right/state").json()["estop"] is True
        assert c.get("/api/v1/arms/left/state").json()["estop"] is False
        released = c.delete("/api/v1/arms/right/estop", headers=OP)
        assert released.status_code == 200, released.text
        assert c.get("/api/v1/arms/right/state").json()["estop"] is False
        # the audit log, from the one store every worker writes (within its flush, 0.1 s),
        # shows the right arm's requests wherever it is read
        instructor = {"Authorization": f"Bearer {INSTRUCTOR}"}

        def routes() -> dict[tuple[str, str], Any]:
            audit = c.get("/api/v1/audit", headers=instructor)
            assert audit.status_code == 200, audit.text
            return {(a["method"], a["route"]): a for a in audit.json()}

        wait_until(lambda: ("DELETE", "/api/v1/arms/right/estop") in routes(),
                   what="the right arm's worker's records in the audit log")
        press = routes()[("POST", "/api/v1/arms/right/estop")]
        assert press["address"] == "127.0.0.1" and press["status"] == 200


def test_with_no_arm_on_a_terminal_each_worker_raises_its_control_threads(lab: Lab) -> None:
    """Where the system allows it (root, CAP_SYS_NICE), each worker's control thread and poll
    thread run at CONTROL_NICE; a lab with an arm on a terminal runs them at the default
    (tests/test_terminal_priority.py)."""
    from app.runtime.control_thread import CONTROL_NICE

    allowed = may_raise_priority(CONTROL_NICE)
    for k, pid in lab.workers().items():
        nice = threads_niceness(pid)
        assert min(nice) == (CONTROL_NICE if allowed else os.getpriority(os.PRIO_PROCESS, 0)), \
            (k, nice)


def test_tokens_and_leases_as_today(lab: Lab) -> None:
    with httpx.Client(base_url=lab.url) as c:
        for path in ("/api/v1/arms", "/api/v1/arms/left/state", "/api/v1/me"):
            r = c.get(path)
            assert r.status_code == 401 and r.json()["code"] == "unauthorized", path
        assert c.get("/api/v1/health").status_code == 200  # open to everyone, as today
        move = {"positions": [0.0, 0.0, 0.0]}
        viewer_move = c.post("/api/v1/arms/left/move/joints", json=move, headers=AUTH)
        assert viewer_move.status_code == 403 and viewer_move.json()["code"] == "forbidden"
        lease = c.post("/api/v1/arms/left/lease", headers=OP)
        assert lease.status_code in (200, 201), lease.text
        lease_id = lease.json()["id"]
        try:
            other = c.post("/api/v1/arms/left/move/joints", json=move, headers=OP)
            assert other.status_code == 409 and other.json()["code"] == "leased"
            # the lease is the left arm's worker's: the right arm is free
            other_lease = c.post("/api/v1/arms/right/lease", headers=OP)
            assert other_lease.status_code in (200, 201), other_lease.text
            assert c.delete(f"/api/v1/arms/right/lease/{other_lease.json()['id']}",
                            headers=OP).status_code in (200, 204)
        finally:
            assert c.delete(f"/api/v1/arms/left/lease/{lease_id}",
                            headers=OP).status_code in (200, 204)
        big = c.post("/api/v1/arms/left/kinematics/forward", headers=OP,
                     content=b"x" * (64 * 1024 + 1))
        assert big.status_code == 413 and big.json()["code"] == "too_large"


def test_an_answer_through_the_front_has_one_date_and_one_server(lab: Lab) -> None:
    """uvicorn writes Date and Server on every answer of the front; a worker's answer has its
    own, which the front does not pass on beside them (Date is a singleton field, RFC 9110
    5.3 and 6.6.1: every answer a worker gave through the front had two of each). Each way an
    answer leaves the front: a JSON answer relayed whole, a worker's 404 renamed, a refusal,
    the answers merged from every worker, the front's own, and a stream relayed as it comes."""
    with httpx.Client(base_url=lab.url, headers=AUTH) as c:
        answers = {
            "relayed": c.get("/api/v1/arms/left/state"),
            "renamed 404": c.get("/api/v1/arms/nobody/state"),
            "refused": c.post("/api/v1/arms/left/move/joints", content=b"{", headers=OP),
            "merged": c.get("/api/v1/arms"),
            "health": c.get("/api/v1/health"),
            "me": c.get("/api/v1/me"),
        }
        with c.stream("GET", "/api/v1/cameras/table-right/stream") as stream:
            answers["stream"] = stream
        assert [r.status_code for r in answers.values()] == [200, 404, 422, 200, 200, 200, 200]
        for what, r in answers.items():
            for name in ("date", "server"):
                assert len(r.headers.get_list(name)) == 1, (what, r.headers.raw)


def test_head_through_the_front_is_get_without_the_body(lab: Lab) -> None:
    """HEAD as GET without the body (tests/test_http_head.py) through the front: the merged
    list's length is the merged GET's, an arm's answer comes from its worker, and a stream's
    HEAD ends at its head (the connection then answers the next request)."""
    with httpx.Client(base_url=lab.url, headers=AUTH) as c:
        for path in ("/api/v1/arms", "/api/v1/arms/nobody/state"):
            got, head = c.get(path), c.head(path)
            assert head.status_code == got.status_code and head.content == b"", path
            assert int(head.headers["content-length"]) == len(got.content), path
            assert len(head.headers.get_list("date")) == 1
        state = c.head("/api/v1/arms/rails/state")
        assert state.status_code == 200 and state.content == b""
        assert int(state.headers["content-length"]) > 0
        stream = c.head("/api/v1/cameras/table-right/stream")  # (it would never end as a GET)
        assert stream.status_code == 200 and stream.content == b""
        assert stream.headers["content-type"].startswith("multipart/x-mixed-replace")
        assert c.get("/api/v1/health").status_code == 200  # the same client, on it goes


async def test_telemetry_websocket_through_the_front(lab: Lab) -> None:
    async with connect(f"{lab.ws}/api/v1/arms/rails/telemetry?rate=50",
                       additional_headers=AUTH) as ws:
        samples: list[dict[str, Any]] = []
        while len(samples) < 20:
            message = json.loads(await asyncio.wait_for(ws.recv(), 10))
            if message["type"] == "telemetry":
                assert message["arm"] == "rails"
                samples += message["samples"]
        seqs = [s["seq"] for s in samples]
        assert seqs == list(range(seqs[0], seqs[0] + len(seqs)))
    for query, code in (("", 4401), ("?token=" + VIEWER, None)):
        async with connect(f"{lab.ws}/api/v1/arms/nobody/telemetry{query}") as ws:
            with pytest.raises(ConnectionClosed) as closed:
                await asyncio.wait_for(ws.recv(), 10)
            assert closed.value.rcvd is not None
            assert closed.value.rcvd.code == (code or 4404)


#: The longest a sample of the other worker's arm may come after the one before it, s, on its
#: own clock, while a worker dies or hangs. The simulated rbe3001 polls at 500 Hz (2 ms); the
#: bound catches the other worker stalled on the harmed one (a shared lock, a blocked loop:
#: seconds), with room for a loaded shared two-core machine, where the CPU a restarting
#: worker's start takes and other tests made gaps of up to 0.3 s (the rate check below is
#: the "no dip" figure).
MAX_SAMPLE_GAP_S = 1.0


async def _outage(lab: Lab, harm: Any) -> float:
    """Read the left arm (worker 0) throughout; `harm(pid)` worker 1; wait (bounded) until its
    right arm is down, then back on a new worker process. Checks that the left arm never
    noticed (no sample lost or dropped, no gap over MAX_SAMPLE_GAP_S on its own clock, its
    rate as before) and returns the seconds from the harm to the right arm's return."""
    before = lab.workers()
    assert set(before) == {0, 1}
    samples: list[dict[str, Any]] = []
    dropped = 0

    async def read_left() -> None:  # worker 0's arm, all along
        nonlocal dropped
        async with connect(f"{lab.ws}/api/v1/arms/left/telemetry?rate=50",
                           additional_headers=AUTH) as ws:
            async for raw in ws:
                message = json.loads(raw)
                if message["type"] == "telemetry":
                    samples.extend(message["samples"])
                    dropped += message["dropped"]

    reader = asyncio.create_task(read_left())
    try:
        await wait_for(lambda: len(samples) > 500, what="the left arm's samples (a baseline)")
        first = len(samples)
        harm(before[1])
        harmed, harmed_wall = time.monotonic(), time.time()
        async with httpx.AsyncClient(base_url=lab.url, headers=AUTH) as c:
            async def right_state() -> int:
                return (await c.get("/api/v1/arms/right/state", timeout=30)).status_code

            async def right_down() -> bool:
                r = await c.get("/api/v1/health", timeout=30)
                return r.json()["arms"]["right"]["connected"] is False

            assert await wait_for(right_down, timeout=BACK_WITHIN_S, what="the right arm down",
                                  every=0.005)
            await wait_for(lambda: lab.workers().get(1) not in (None, before[1]),
                           timeout=BACK_WITHIN_S, what="worker 1 on a new process")
            await wait_for(_is(right_state, 200), timeout=BACK_WITHIN_S,
                           what="the right arm back")
            back_after = time.monotonic() - harmed
            health = (await c.get("/api/v1/health")).json()
            assert health["status"] == "ok"
            assert lab.workers()[0] == before[0]
        await wait_for(lambda: len(samples) > first + 100, what="more left samples")
    finally:
        reader.cancel()
        await asyncio.gather(reader, return_exceptions=True)
        with contextlib.suppress(ProcessLookupError):  # a failed test leaves no stopped one
            os.kill(before[1], signal.SIGKILL)
    window = samples[first - 10:]
    seqs = [s["seq"] for s in window]
    assert seqs == list(range(seqs[0], seqs[0] + len(seqs))), "the left arm lost samples"
    assert dropped == 0
    assert all(s["link"] == "up" and not s.get("stale") for s in window)
    gaps = [b["time"] - a["time"] for a, b in itertools.pairwise(window)]
    assert max(gaps) < MAX_SAMPLE_GAP_S, max(gaps)
    # on its own clock, the rate over the harm and the restart against the rate before it in
    # the same run (the machine's load, shared with other tests, sets both alike)
    def rate(part: list[dict[str, Any]]) -> float:
        return (len(part) - 1) / (part[-1]["time"] - part[0]["time"])

    before_harm = rate(samples[:first])
    # (where the left arm's sampling paused, on the samples' wall clock from the harm: a dip's
    # cause is in when it came)
    paused = ", ".join(f"{(a['time'] - harmed_wall) * 1e3:+.0f} ms: {gap * 1e3:.0f}"
                       for gap, (a, _) in zip(gaps, itertools.pairwise(window), strict=True)
                       if gap > 0.02)
    print(f"the left arm: {before_harm:.1f} samples/s before the harm, {rate(window):.1f} "
          f"over it and the restart ({(window[-1]['time'] - window[0]['time']):.2f} s, the "
          f"right arm back at +{back_after * 1e3:.0f} ms); its pauses over "
          f"20 ms: {paused or 'none'}")
    assert rate(window) > 0.75 * before_harm, (rate(window), before_harm, paused)
    return back_after


# Reads a sample rate while a process dies: in the serial part's `browser` lane
# (tests/conftest.py), so never beside a browser test, whose Chromium, run as root, raises its
# own processes to niceness -8: beside two of them the left arm kept 240-385 samples/s over
# the restart (session 26), its control thread's -10 notwithstanding. Beside the timing lane's
# safety machine (its arms at -10 too) and `stress-ng --cpu 2` on a slow hour it kept 436-500
# in twelve runs, and once, in a whole suite, 375 (a pause of half a second): the pauses it
# prints say when.
@pytest.mark.serial
async def test_a_killed_worker_comes_back_and_the_other_never_notices(lab: Lab) -> None:
    """... and a telemetry socket on the killed worker's arm is closed 1012 (service restart:
    reconnect) by the front."""
    async with connect(f"{lab.ws}/api/v1/arms/right/telemetry?rate=50",
                       additional_headers=AUTH) as right:
        await asyncio.wait_for(right.recv(), 10)
        back_after = await _outage(lab, lambda pid: os.kill(pid, signal.SIGKILL))
        with pytest.raises(ConnectionClosed) as closed:
            while True:  # what came before the kill, then the close
                await asyncio.wait_for(right.recv(), 10)
    assert closed.value.rcvd is not None and closed.value.rcvd.code == 1012
    print(f"the right arm was back {back_after:.2f} s after its worker's SIGKILL")


@pytest.mark.serial  # as above
async def test_a_hung_worker_is_killed_and_restarted(lab: Lab) -> None:
    """SIGSTOP: the worker neither exits nor answers; the supervisor's prober finds it out
    (PROBE_MISSES health probes of PROBE_DEADLINE_S), kills it and starts it again."""
    back_after = await _outage(lab, lambda pid: os.kill(pid, signal.SIGSTOP))
    print(f"the right arm was back {back_after:.2f} s after its worker's SIGSTOP")
    async with httpx.AsyncClient(base_url=lab.url, headers=AUTH) as c:
        arms = (await c.get("/api/v1/arms")).json()
        assert [a["name"] for a in arms] == ARMS
        assert all(a["link"]["connected"] for a in arms)


async def _kill_the_right_arms_worker(lab: Lab, c: httpx.AsyncClient) -> None:
    """SIGKILL worker 1 (the right arm's) and wait, bounded, for the right arm on a new one."""
    before = lab.workers()[1]
    os.kill(before, signal.SIGKILL)

    async def right_state() -> int:
        return (await c.get("/api/v1/arms/right/state")).status_code

    await wait_for(lambda: lab.workers().get(1) not in (None, before),
                   timeout=BACK_WITHIN_S, what="worker 1 on a new process")
    await wait_for(_is(right_state, 200), timeout=BACK_WITHIN_S, what="the right arm back")


@pytest.mark.serial  # beside this module's other kills, on the serial part's lab
async def test_a_latched_estop_holds_across_its_workers_kill(lab: Lab) -> None:
    """The right arm latched, its worker killed with SIGKILL: the worker started in its place
    starts the arm latched (the latch is in the lab's store), and a move is refused 409
    `estop_latched` until someone releases it."""
    right = "/api/v1/arms/right"
    async with httpx.AsyncClient(base_url=lab.url, headers=OP, timeout=30) as c:
        assert (await c.post(f"{right}/estop")).json() == {"estop": True}
        try:
            assert _right_latched_on_disk(lab)  # at the answer
            await _kill_the_right_arms_worker(lab, c)
            assert (await c.get(f"{right}/state")).json()["estop"] is True
            r = await c.post(f"{right}/move/joints", json={"positions": [0.1, 0.1, 0.1]})
            assert r.status_code == 409 and r.json()["code"] == "estop_latched", r.text
        finally:
            released = await c.delete(f"{right}/estop")
        assert released.status_code == 200 and released.json() == {"estop": False}


@pytest.mark.serial  # as above
async def test_a_lease_holds_across_its_workers_kill(lab: Lab) -> None:
    """The right arm leased, its worker killed with SIGKILL: the worker started in its place
    has the lease (kept in the lab's store), so a move without it is 409 `leased`, a new lease
    is refused, and the holder's renewal and moves go on."""
    right = "/api/v1/arms/right"
    async with httpx.AsyncClient(base_url=lab.url, headers=OP, timeout=30) as c:
        r = await c.post(f"{right}/lease")
        assert r.status_code == 201, r.text
        lease = r.json()["id"]
        try:
            await _kill_the_right_arms_worker(lab, c)
            r = await c.post(f"{right}/move/joints", json={"positions": [0.1, 0.1, 0.1]})
            assert r.status_code == 409 and r.json()["code"] == "leased", r.text
            r = await c.post(f"{right}/lease")
            assert r.status_code == 409 and r.json()["code"] == "leased", r.text
            r = await c.put(f"{right}/lease/{lease}")
            assert r.status_code == 200 and r.json()["id"] == lease, r.text
            r = await c.post(f"{right}/stop", headers={"X-Arm-Lease": lease})
            assert r.status_code == 200, r.text
        finally:
            released = await c.delete(f"{right}/lease/{lease}")
        assert released.status_code == 204, released.text


@pytest.mark.serial  # as above
async def test_a_press_while_its_worker_restarts_latches_the_arm_as_it_comes_back(
        lab: Lab) -> None:
    """Worker 1 killed; while it restarts a press on its arm is answered 503 `link_down` and
    kept by the front, which sends it to the new worker before any other request: the arm's
    first answer from the new worker already says latched."""
    right = "/api/v1/arms/right"
    async with httpx.AsyncClient(base_url=lab.url, headers=OP, timeout=30) as c:
        async def right_down() -> bool:
            r = await c.get("/api/v1/health")
            return r.json()["arms"]["right"]["connected"] is False

        before = lab.workers()[1]
        os.kill(before, signal.SIGKILL)
        try:
            await wait_for(right_down, timeout=BACK_WITHIN_S, what="the right arm down",
                           every=0.005)
            pressed = [await c.post(f"{right}/estop") for _ in range(2)]  # (one is kept)
            for r in pressed:
                assert r.status_code == 503 and r.json()["code"] == "link_down", r.text
                assert "this estop press is kept" in r.json()["detail"], r.text
            # and latched in the lab's store by the front, at the answer: the worker reads it
            # as it starts, however long it takes
            assert _right_latched_on_disk(lab)
            # a token that grants nothing here: not kept (nor able to fill the kept presses)
            r = await c.post(f"{right}/estop", headers={"Authorization": "Bearer not-a-token"})
            assert r.status_code == 503 and "kept" not in r.json()["detail"], r.text

            async def right_state() -> int:
                return (await c.get(f"{right}/state")).status_code

            await wait_for(_is(right_state, 200), timeout=BACK_WITHIN_S,
                           what="the right arm back")
            assert (await c.get(f"{right}/state")).json()["estop"] is True
            assert lab.workers()[1] != before
        finally:
            released = await c.delete(f"{right}/estop")
        assert released.status_code == 200 and released.json() == {"estop": False}
    # one press sent, once: the worker's log (the lab's) says so once
    assert lab.log is not None
    assert lab.log.read_text().count("an estop press kept while it was down") == 1


def _right_latched_on_disk(lab: Lab) -> bool:
    """Whether the lab's store says the right arm is latched (read as another process)."""
    assert lab.data is not None
    with sqlite3.connect(f"file:{lab.data / DB_NAME}?mode=ro", uri=True) as c:
        row = c.execute("SELECT value FROM settings WHERE scope = 'arm:right' "
                        "AND key = 'estop'").fetchone()
    return row is not None and json.loads(row[0])["latched"] is True


def _is(fn: Any, value: Any) -> Any:
    async def check() -> bool:
        return bool(await fn() == value)
    return check



def test_placement_follows_the_config_and_refuses_what_cannot_be(tmp_path: Path) -> None:
    from conftest import make_settings

    from app.config import ConfigError
    from app.lab.placement import lab_workers, plan_lab

    config = tmp_path / "lab.toml"
    config.write_text(CONFIG + '\n[[arms]]\nprofile = "rbe3001"\nname = "spare"\ncount = 3\n')
    settings = make_settings(config=str(config))
    assert lab_workers(settings, None) == 2  # the config names workers 0 and 1
    assert lab_workers(settings, 1) == 1  # --workers 1: one process, as ever
    plan = plan_lab(settings, 3)
    # named ones where named, the others each to the emptiest worker, in config order
    assert [[p.name for p in arms] for arms in plan.workers] == [
        ["left", "spare-1"], ["right", "spare-2"], ["rails", "spare-3"]]
    assert plan.camera_worker == {"table-left": 0, "table-right": 1}
    with pytest.raises(ConfigError, match="names worker 1, but the server runs 1"):
        plan_lab(settings, 1)
    # a simulated camera renders its source arm's world, in that arm's process
    config.write_text(CONFIG.replace('source = "sim:right"', 'source = "sim:left"'))
    with pytest.raises(ConfigError, match="camera 'table-right' renders arm 'left'"):
        plan_lab(make_settings(config=str(config)), 2)
    for bad in ("-1", "true", '"0"', "64"):
        config.write_text(f'[[arms]]\nprofile = "rbe3001"\nworker = {bad}\n')
        with pytest.raises(ConfigError, match="worker must be an integer 0..63"):
            plan_lab(make_settings(config=str(config)), 2)


@pytest.mark.serial  # as above
async def test_a_worker_hung_in_its_start_is_restarted(lab: Lab) -> None:
    """Worker 1 killed, its new process stopped (SIGSTOP) before its first answer: the
    supervisor sees it use no CPU while starting (START_FROZEN_S), kills it and starts another,
    and the right arm comes back."""
    before = lab.workers()[1]
    os.kill(before, signal.SIGKILL)
    starting = await wait_for(lambda: lab.workers().get(1) not in (None, before)
                              and lab.workers()[1], timeout=BACK_WITHIN_S, every=0.002,
                              what="worker 1's new process")
    os.kill(starting, signal.SIGSTOP)
    try:
        async with httpx.AsyncClient(base_url=lab.url, headers=AUTH, timeout=30) as c:
            async def why() -> str:
                return str((await c.get("/api/v1/health")).json()["arms"]["right"]
                           ["last_error"])

            assert "hung in its start" in await wait_for(
                _contains(why, "hung in its start"), timeout=BACK_WITHIN_S,
                what="worker 1 killed for hanging in its start", every=0.05)
            await wait_for(lambda: lab.workers().get(1) not in (None, before, starting),
                           timeout=BACK_WITHIN_S, what="worker 1 on a third process")
            await wait_for(_is(lambda: _status(c, "/api/v1/arms/right/state"), 200),
                           timeout=BACK_WITHIN_S, what="the right arm back")
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.kill(starting, signal.SIGKILL)


async def _status(c: httpx.AsyncClient, path: str) -> int:
    return (await c.get(path)).status_code


def _contains(fn: Any, part: str) -> Any:
    async def check() -> str | None:
        text = str(await fn())
        return text if part in text else None
    return check


def test_a_slow_worker_is_not_a_hung_one() -> None:
    """The supervisor's rule: unanswered probes are a hang only with no activity (stopped,
    wholly deadlocked), or after SILENT_S of silence however busy it is; `activity` tells a
    running process and a starved one from a stopped one (real processes: this one, a
    stopped child, and two busy children on one CPU)."""
    from app.lab.supervisor import PROBE_MISSES, SILENT_S, activity, is_hung, is_stopped

    assert not is_hung(1, True, 1.5)  # one miss: asked again at once
    assert is_hung(1, True, 1.5, stopped=True)  # ... unless stopped by a signal
    assert not is_hung(0, True, 0.2, stopped=True)  # (answered since: continued)
    assert is_hung(PROBE_MISSES, True, 2.5)  # two, and frozen: SIGSTOP
    assert not is_hung(PROBE_MISSES, False, 2.5)  # two, but it runs: slow, not hung
    assert not is_hung(7, False, SILENT_S - 0.5)
    assert is_hung(8, False, SILENT_S)  # its HTTP side stuck while it runs
    mine = activity(os.getpid())
    assert mine is not None
    deadline = time.monotonic() + 10  # run until the scheduler's count of it is updated
    while activity(os.getpid()) == mine and time.monotonic() < deadline:
        sum(range(10_000))
    now = activity(os.getpid())
    assert now is not None and now[0] > mine[0]  # it ran
    busy = "while True: pass"
    child = subprocess.Popen([sys.executable, "-c", busy])
    rival = subprocess.Popen([sys.executable, "-c", busy])
    try:
        # two busy processes on one CPU: each waits on the run queue while the other runs
        # (what a live worker does on a machine busy beyond its cores): active, not frozen
        cpu = min(os.sched_getaffinity(0))
        for p in (child, rival):
            os.sched_setaffinity(p.pid, {cpu})
        before = activity(child.pid)
        assert before is not None
        wait_until(lambda: (a := activity(child.pid)) is not None and a[1] > before[1],
                   what="the child waited for its CPU")
        os.kill(child.pid, signal.SIGSTOP)
        wait_until(lambda: Path(f"/proc/{child.pid}/stat").read_text().rsplit(")", 1)[1]
                   .split()[0] == "T", what="the child stopped")
        assert is_stopped(child.pid) and not is_stopped(os.getpid())
        stopped = activity(child.pid)
        assert stopped is not None
        time.sleep(0.3)  # the window under test: a stopped process neither runs nor waits
        assert activity(child.pid) == stopped
        os.kill(child.pid, signal.SIGCONT)
        wait_until(lambda: not is_stopped(child.pid), what="the child continued")
    finally:
        for p in (child, rival):
            p.kill()
            p.wait()
    assert activity(child.pid) is None  # gone: unreadable
    assert not is_stopped(child.pid)
