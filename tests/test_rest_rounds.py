"""The poll thread's rounds of arms at rest in C (issue 27: app/links/_restpoll.c, driven by
app/links/poller.py `PollThread._rest`).

`_restpoll.run` is tested on its own against a responder on the other end of a real socket
pair (each request read, counted and answered as the test scripts it): what it counts as a
repeat, when it returns, what it hands back; then the thread links over the arm types'
simulators on loopback sockets: the rounds in C are the ones used, and a pause, a new batch
time or closing reach a link whose batch would otherwise run for 30 s."""

from __future__ import annotations

import contextlib
import os
import resource
import socket
import threading
import time
from collections.abc import Callable, Iterator

import pytest
from _wait import TIMEOUT_S, wait_for
from test_link_thread import arm

from app.links import poller

REQ = bytes(range(64))
REPLY = bytes(range(100, 164))
OTHER = bytes(range(1, 65))
PERIOD = 0.002


def test_the_rounds_in_c_are_built_and_used():
    """`make test` installs a C compiler and Python's headers first (tests/_deps.py): the
    module is built, and the poll thread uses it (ARMSERVER_POLL_REST unset)."""
    assert poller._restpoll is not None, "app/links/_restpoll.c was not built"
    assert poller.REST_IN_C


#: The kind of socket pair the rounds are tested over (each test of `run` with both: the
#: `wake_pipe` fixture's parameter): "tcp", a loopback TCP connection as pyserial's
#: `socket://` makes (its replies carry the kernel's time: each is read at the link's next
#: slot), or "unix", a Unix socket pair (no time: each reply is waited for, as on a tty).
PAIR = "tcp"


def socket_pair() -> tuple[socket.socket, socket.socket]:
    """The link's end (non-blocking, as pyserial's `socket://` is) and the device's, of the
    kind `PAIR` says."""
    if PAIR == "unix":
        ours, theirs = socket.socketpair()
    else:
        with socket.create_server(("127.0.0.1", 0)) as server:
            ours = socket.create_connection(server.getsockname())
            theirs, _ = server.accept()
        for s in (ours, theirs):
            s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        timestamps_on(ours, theirs)
    ours.setblocking(False)
    return ours, theirs


#: Linux's SO_TIMESTAMPNS (`socket` has no name for it), as app/links/_restpoll.c sets it.
SO_TIMESTAMPNS = 35


def timestamps_on(ours: socket.socket, theirs: socket.socket) -> None:
    """Receive timestamps on `ours`, and delivered already: the kernel switches them on for
    the whole system only once a worker thread of its own has run after the first socket asks
    (`net_enable_timestamp`), and until then a segment comes without one (the rounds then wait
    for its reply, as on a tty). In a loaded `make test` the first replies of a test came so,
    and were stamped when read. Probes from `theirs` until one comes with its time."""
    ours.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
    ours.settimeout(TIMEOUT_S)
    try:
        deadline = time.monotonic() + TIMEOUT_S
        while True:
            theirs.sendall(b"?")
            data, ancillary, _, _ = ours.recvmsg(1, 1024)
            assert data == b"?"
            if any(t == SO_TIMESTAMPNS for _, t, _ in ancillary):
                return
            assert time.monotonic() < deadline, "no receive timestamps on a TCP socket"
            time.sleep(0.01)  # (a poll: the kernel's worker switches them on)
    finally:
        ours.settimeout(None)


@contextlib.contextmanager
def responder(answer: Callable[[int, bytes], bytes | None],
              sent: list[float] | None = None) -> Iterator[tuple[int, list[bytes]]]:
    """A socket pair (`socket_pair`) with on the device's end a thread that reads each 64-byte
    request and writes `answer(n, request)` (None: closes its end), and appends to `sent` the
    time (`time.time()`) each answer's write returned. Yields the link's descriptor and the
    requests read."""
    ours, theirs = socket_pair()
    got: list[bytes] = []

    def serve() -> None:
        buf = b""
        try:
            while True:
                data = theirs.recv(4096)
                if not data:
                    return
                buf += data
                while len(buf) >= len(REQ):
                    req, buf = buf[:len(REQ)], buf[len(REQ):]
                    got.append(req)
                    out = answer(len(got), req)
                    if out is None:
                        theirs.shutdown(socket.SHUT_RDWR)
                        return
                    if out:
                        theirs.sendall(out)
                        if sent is not None:
                            sent.append(time.time())
        except OSError:
            return

    t = threading.Thread(target=serve, daemon=True)
    t.start()
    try:
        yield ours.fileno(), got
    finally:
        ours.close()
        theirs.close()
        t.join(2.0)


@pytest.fixture(params=["tcp", "unix"])
def wake_pipe(request: pytest.FixtureRequest) -> Iterator[tuple[int, int]]:
    """The thread's wake-up pipe, for a test of `run` over the kind of pair its parameter
    names (`PAIR`)."""
    global PAIR
    PAIR = request.param
    r, w = os.pipe()
    os.set_blocking(r, False)
    try:
        yield r, w
    finally:
        os.close(r)
        os.close(w)
        PAIR = "tcp"


def run(links: list[tuple], wake_fd: int) -> list[tuple]:
    assert poller._restpoll is not None
    return poller._restpoll.run(links, wake_fd, poller.EARLY_S, float(poller.CATCH_UP), 1.0,
                                4096)


def clocks() -> tuple[float, float]:
    """time.monotonic() (the rounds' slots) and time.time() (their `ats`) at one moment."""
    return time.monotonic(), time.time()


def assert_next_slot(next_slot: float, start: tuple[float, float], period: float,
                     ats: list[float]) -> None:
    """The slot after the rounds that began at `start` (`clocks()`) and read at `ats`: one
    period a read after the first, or, where the rounds fell more than CATCH_UP periods
    behind their slots (a stalled host: a clean clone's run once lost 55 ms here), on the
    period's grid, ahead (`_restpoll.c` `done`)."""
    slot, wall = start
    # (within 0.1 us: the rounds add a period a read, and at a monotonic clock of 69,000 s the
    # sums drift from the product by some 2 ns in a few hundred reads)
    if next_slot == pytest.approx(slot + len(ats) * period, abs=1e-7):
        return
    assert next_slot > slot + len(ats) * period, (next_slot, slot, len(ats))
    assert next_slot / period == pytest.approx(round(next_slot / period), abs=1e-6)
    behind = max(at - wall - k * period for k, at in enumerate(ats))  # read k's slot: k periods on
    assert behind > poller.CATCH_UP * period, (behind, ats)


def test_repeats_are_read_until_the_batch_is_due(wake_pipe):
    with responder(lambda n, req: REPLY) as (fd, got):
        start = clocks()
        slot = start[0]
        until = slot + 0.1
        [(next_slot, ats, end)] = run([(fd, REQ, REPLY, 0.05, slot, PERIOD, until, 1000)],
                                      wake_pipe[0])
        assert time.monotonic() >= until
        assert end is None
        assert 1 <= len(ats) <= 51  # (a slot every 2 ms from `slot`, up to `until`)
        assert len(got) == len(ats) and all(r == REQ for r in got)
        assert ats == sorted(ats) and abs(ats[-1] - time.time()) < 5.0
        assert_next_slot(next_slot, start, PERIOD, ats)


def test_a_timed_reply_is_read_at_the_next_slot_with_its_arrival_time(wake_pipe):
    """Over TCP each reply carries the kernel's time (SO_TIMESTAMPNS): the thread sleeps from
    one slot to the next, once a poll, and reads the reply before the next slot's request,
    the reply stamped with when it came (not when it was read). Over a Unix pair (as a tty)
    it waits for each reply: twice a poll."""
    period = 0.02
    sent: list[float] = []
    with responder(lambda n, req: REPLY, sent) as (fd, got):
        now = time.monotonic()
        before = resource.getrusage(resource.RUSAGE_THREAD).ru_nvcsw
        [(_slot, ats, end)] = run([(fd, REQ, REPLY, 0.5, now, period, now + 30, 10)],
                                  wake_pipe[0])
        sleeps = resource.getrusage(resource.RUSAGE_THREAD).ru_nvcsw - before
    assert end is None and len(ats) == 10 and len(got) == 10
    if PAIR == "unix":
        return  # (a reply already there when the thread looks needs no sleep: no bound)
    # each time is the reply's arrival: before its write returned on the other end (the
    # kernel stamps a loopback segment as the sender hands it over), and it is read a period
    # after (`sent`: the device's thread, which wants the GIL, may note its time late)
    assert all(at <= s for at, s in zip(ats, sent, strict=False)), (ats, sent)
    # one sleep a poll, to its slot; a reply not there by the next slot (a loaded machine)
    # adds one: waiting for each reply would be two a poll
    assert sleeps <= 1.5 * len(ats) + 2, (sleeps, len(ats))


def test_a_slot_on_its_grid_stays_on_it_read_after_read(wake_pipe):
    """Each read moves the slot one period on to the grid point itself (`following`), not to
    a sum of periods: at a monotonic clock many hours up the sum drifts about one ulp a read
    (2 ns in a few hundred at 69,000 s, 0.6 ms a day), off the grid links share slots on."""
    with responder(lambda n, req: REPLY) as (fd, got):
        slot = poller.aligned(time.monotonic(), PERIOD)
        [(next_slot, ats, end)] = run([(fd, REQ, REPLY, 0.05, slot, PERIOD, slot + 0.4, 1000)],
                                      wake_pipe[0])
    assert end is None and len(ats) >= 20, (end, len(ats))
    k = round(next_slot / PERIOD)
    assert next_slot == k * PERIOD  # exactly the grid point: one rounding, no sum
    # and in Python, as the link's own schedule moves: 200,000 polls (400 s at 500 Hz) on
    for start in (slot, 69288.49):
        s = poller.aligned(start, PERIOD)
        for _ in range(200_000):
            s = poller.following(s, PERIOD)
        assert s == round(s / PERIOD) * PERIOD, s
    # a slot off the grid (a caller's own) moves by plain periods
    assert poller.following(1000.0005, PERIOD) == 1000.0005 + PERIOD


def test_rounds_far_behind_skip_ahead_onto_the_grid(wake_pipe):
    """A device that stalls 60 ms (30 periods) on the third request: the rounds do not read
    the slots they missed one after another; the next slot is on the period's grid, ahead."""
    def answer(n: int, req: bytes) -> bytes:
        if n == 3:
            time.sleep(0.06)  # the scenario: the device stalls
        return REPLY

    with responder(answer) as (fd, got):
        start = clocks()
        slot = start[0]
        [(next_slot, ats, end)] = run([(fd, REQ, REPLY, 0.2, slot, PERIOD, slot + 0.1, 1000)],
                                      wake_pipe[0])
        assert end is None and len(ats) == len(got) >= 3
        assert next_slot != pytest.approx(slot + len(ats) * PERIOD, abs=1e-9)
        assert_next_slot(next_slot, start, PERIOD, ats)


def test_at_most_cap_repeats_are_read(wake_pipe):
    with responder(lambda n, req: REPLY) as (fd, got):
        now = time.monotonic()
        [(_slot, ats, end)] = run([(fd, REQ, REPLY, 0.05, now, PERIOD, now + 30, 5)],
                                  wake_pipe[0])
        assert end is None and len(ats) == 5 and len(got) == 5


def test_a_reply_that_differs_ends_the_rounds_and_is_handed_back_whole(wake_pipe):
    with responder(lambda n, req: OTHER if n == 4 else REPLY) as (fd, got):
        now = time.monotonic()
        [(slot, ats, end)] = run([(fd, REQ, REPLY, 0.05, now, PERIOD, now + 30, 64)],
                                 wake_pipe[0])
        assert len(ats) == 3 and len(got) == 4
        kind, data, deadline, at = end
        assert (kind, data) == ("reply", OTHER)
        assert at >= ats[-1] and deadline <= time.monotonic() + 0.05
        # the slot moved on for the three repeats only: the reply's own poll is Python's
        assert slot == pytest.approx(now + 3 * PERIOD, abs=1e-9)


def test_a_longer_reply_is_no_repeat(wake_pipe):
    with responder(lambda n, req: REPLY + b"!" if n == 2 else REPLY) as (fd, _got):
        now = time.monotonic()
        [(_slot, ats, end)] = run([(fd, REQ, REPLY, 0.05, now, PERIOD, now + 30, 64)],
                                  wake_pipe[0])
        assert len(ats) == 1 and end[:2] == ("reply", REPLY + b"!")


def test_a_short_reply_is_handed_back_at_its_timeout(wake_pipe):
    with responder(lambda n, req: REPLY[:20] if n == 3 else REPLY) as (fd, _got):
        now = time.monotonic()
        [(_slot, ats, end)] = run([(fd, REQ, REPLY, 0.05, now, PERIOD, now + 30, 64)],
                                  wake_pipe[0])
        assert len(ats) == 2
        kind, data, deadline, _at = end
        assert (kind, data) == ("reply", REPLY[:20])
        assert time.monotonic() >= deadline


def test_a_reply_in_parts_is_a_repeat(wake_pipe):
    ours, theirs = socket_pair()

    def serve() -> None:
        for _ in range(3):
            theirs.recv(64)
            theirs.sendall(REPLY[:10])
            time.sleep(0.005)
            theirs.sendall(REPLY[10:])

    t = threading.Thread(target=serve, daemon=True)
    t.start()
    try:
        now = time.monotonic()
        [(_slot, ats, end)] = run([(ours.fileno(), REQ, REPLY, 0.05, now, PERIOD, now + 30, 3)],
                                  wake_pipe[0])
        assert end is None and len(ats) == 3
    finally:
        t.join(2.0)
        ours.close()
        theirs.close()


def test_the_peer_closing_is_a_lost_link(wake_pipe):
    with responder(lambda n, req: None if n == 3 else REPLY) as (fd, _got):
        now = time.monotonic()
        [(_slot, ats, end)] = run([(fd, REQ, REPLY, 0.05, now, PERIOD, now + 30, 64)],
                                  wake_pipe[0])
        assert len(ats) == 2 and end == ("lost", "closed by the peer (end of file)")


def test_the_wake_pipe_ends_the_rounds_and_is_drained(wake_pipe):
    r, w = wake_pipe
    with responder(lambda n, req: REPLY) as (fd, got):
        now = time.monotonic()
        until = now + 30
        threading.Timer(0.05, os.write, (w, b"xx")).start()
        [(_slot, ats, end)] = run([(fd, REQ, REPLY, 0.05, now, PERIOD, until, 1000)], r)
        assert time.monotonic() < until  # (without the pipe: 30 s)
        assert end is None and len(ats) >= 1 and len(got) == len(ats)
        with pytest.raises(BlockingIOError):
            os.read(r, 16)


def test_links_of_two_periods_each_keep_their_own_slots(wake_pipe):
    with responder(lambda n, req: REPLY) as (fd1, got1), \
            responder(lambda n, req: OTHER) as (fd2, got2):
        start = clocks()
        now = start[0]
        (s1, ats1, e1), (s2, ats2, e2) = run(
            [(fd1, REQ, REPLY, 0.05, now, 0.002, now + 0.1, 1000),
             (fd2, REQ, OTHER, 0.05, now, 0.005, now + 0.1, 1000)], wake_pipe[0])
        assert e1 is None and e2 is None
        assert len(ats1) == len(got1) and len(ats2) == len(got2)
        assert len(ats1) > len(ats2) >= 1
        assert_next_slot(s1, start, 0.002, ats1)
        assert_next_slot(s2, start, 0.005, ats2)


def test_no_links_returns_at_once(wake_pipe):
    assert run([], wake_pipe[0]) == []


def test_a_bad_link_is_a_type_error_not_a_crash(wake_pipe):
    with pytest.raises(TypeError):
        run([("x",)], wake_pipe[0])
    with pytest.raises(ValueError):
        run([(0, b"", REPLY, 0.05, 0.0, PERIOD, 0.0, 1)], wake_pipe[0])


# ---------------------------------------------------------------- on the poll thread


async def test_an_arm_at_rest_is_polled_in_c_and_every_sample_published():
    async with arm("rbe3001") as (driver, link, _server):
        sub = driver.hub.subscribe()
        try:
            thread = poller.shared()
            runs0, repeats0 = thread.stats["rest_runs"], driver.stats["repeats"]
            await wait_for(lambda: driver.stats["repeats"] > repeats0 + 200, what="repeats")
            assert thread.stats["rest_runs"] > runs0
            samples, _events, dropped = sub.take()
        finally:
            sub.close()
        assert dropped == 0
        import json

        seqs = [json.loads(s)["seq"] for s in samples]
        assert seqs == list(range(seqs[0], seqs[0] + len(seqs)))
        assert driver.stats["corrupt"] == 0


async def test_a_request_reaches_an_arm_whose_batch_in_c_runs_for_30_s(monkeypatch):
    """A pause (the owner task's request) and a new batch time wake the rounds in C: without
    the thread's nudge the request would wait for the 30 s batch (the link may hold all its
    replies meanwhile here, not MAX_PREFETCHED)."""
    from app.links import threaded

    monkeypatch.setattr(threaded, "MAX_PREFETCHED", 1_000_000)
    async with arm("rbe3001") as (driver, link, _server):
        thread = poller.shared()
        repeats = driver.stats["repeats"]  # (settled: the simulator's arm is at rest)
        await wait_for(lambda: driver.stats["repeats"] > repeats + 150, what="the arm at rest")
        link.batch_repeats(30.0)
        runs = thread.stats["rest_runs"]
        await wait_for(lambda: thread.stats["rest_runs"] > runs and link._resting,
                       what="rounds in C with the 30 s batch")
        t0 = time.monotonic()
        await driver.set_claw(0.5)
        assert time.monotonic() - t0 < 10.0  # (a bound, not a speed: 30 s without the nudge)
        repeats = driver.stats["repeats"]
        link.batch_repeats(0.02)  # a reader came: its batch within 20 ms, not 30 s
        await wait_for(lambda: driver.stats["repeats"] > repeats, timeout=10.0,
                       what="the repeats of the new batch time")


async def test_a_held_up_control_loop_gets_a_bounded_backlog_and_the_polls_stop():
    """The rounds in C read up to MAX_PREFETCHED replies beyond those the owner task was woken
    for (`rest_begin`): while its control loop is held up (a second here: 500 polls' time),
    the link's backlog stays within twice that, the thread stops polling on its own, and the
    owner task takes the backlog and polls again once its loop runs. The board answers from a
    loop of its own, as a real one does."""
    from _tcp import LoopThread

    from app.arms.loading import load_profile
    from app.arms.rbe3001.driver import Rbe3001Driver
    from app.arms.rbe3001.sim import Rbe3001Firmware
    from app.links import threaded
    from app.links.threaded import ThreadLink
    from app.sim.serve import serve_tcp
    from app.telemetry.hub import TelemetryHub

    profile = load_profile("rbe3001")
    board = LoopThread()
    server = board.run(serve_tcp(Rbe3001Firmware(profile)))
    link = ThreadLink(f"socket://127.0.0.1:{server.port}")
    driver = Rbe3001Driver(profile, link, TelemetryHub("rbe3001"))
    await driver.start()
    try:
        assert await driver.wait_connected(10.0), f"never connected: {link.last_error}"
        thread = poller.shared()
        runs = thread.stats["rest_runs"]
        await wait_for(lambda: thread.stats["rest_runs"] > runs + 3 and link._resting,
                       what="the arm at rest, polled in C")
        most = 0
        scheduled = link.stats["scheduled"]
        stop = time.monotonic() + 1.0
        while time.monotonic() < stop:  # the control loop held up: no step of its runs
            most = max(most, link.prefetched)
            time.sleep(0.005)  # noqa: ASYNC251 - the loop held up on purpose
        read = link.stats["scheduled"] - scheduled
        assert not link.armed, "the thread went on polling for a held-up loop"
        assert most <= 2 * threaded.MAX_PREFETCHED, most
        assert read <= 2 * threaded.MAX_PREFETCHED, read  # (500 had it not stopped)
        repeats = driver.stats["repeats"]
        await wait_for(lambda: driver.stats["repeats"] > repeats + read + 50,
                       what="the backlog taken and the polls again")
    finally:
        await driver.close()
        board.run(server.close())
        board.stop()
