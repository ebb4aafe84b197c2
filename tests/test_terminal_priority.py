"""A raised thread runs at the default niceness while the process has a terminal in use.

Linux delivers a terminal's received bytes (a USB serial adapter's, a pty's) in a work item of
an unbound kworker at niceness 0; beside a CPU load, the control thread at -10 kept that
worker from a CPU for seconds (traced: docs/performance.md, "Session 24"), and the servo
set-up read its servos as silent. So while a serial link or a set-up bus has a terminal open,
every thread that raised its priority (`raise_priority`: the control thread, the link poll
thread, a serial link's own thread) runs at 0, and the process's main thread (the HTTP side)
at HOLD_MAIN_NICE below them; all get their niceness back when the last terminal is closed.
Links over a socket keep the raise. These read each thread's niceness from /proc; they need
the right to raise it (root or CAP_SYS_NICE), as the raise itself does.
"""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import threading
import tty
from collections.abc import Iterator
from pathlib import Path

import pytest
from _serve import Served, clean_env, start
from _wait import wait_until
from conftest import may_raise_priority, thread_niceness, threads_niceness
from test_lab_workers import Lab

from app.arms.dynamixel.setup import Bus
from app.links.serial import SerialLink
from app.links.threaded import ThreadLink
from app.runtime import control_thread
from app.runtime.control_thread import CONTROL_NICE, HOLD_MAIN_NICE, ControlThread, TerminalHold

pytestmark = pytest.mark.skipif(not may_raise_priority(CONTROL_NICE),
                                reason="raising a thread's priority is not allowed here")


@pytest.fixture
def control() -> Iterator[int]:
    """A running control thread (raised to CONTROL_NICE): its native id."""
    assert control_thread._terminals == 0  # (no terminal left open by another test)
    thread = ControlThread("test-control")
    thread.start()
    try:
        assert thread._thread is not None and thread._thread.native_id is not None
        tid = thread._thread.native_id
        assert thread_niceness(os.getpid(), tid) == CONTROL_NICE
        yield tid
    finally:
        thread.stop()


@pytest.fixture
def pty_path() -> Iterator[str]:
    """A raw pseudo-terminal's slave path (its master held open, nothing answering)."""
    master, slave = os.openpty()
    tty.setraw(slave)
    try:
        yield os.ttyname(slave)
    finally:
        os.close(slave)
        os.close(master)


def niceness(tid: int) -> int:
    return thread_niceness(os.getpid(), tid)


def main_tid() -> int:
    tid = threading.main_thread().native_id
    assert tid is not None
    return tid


def test_a_set_up_bus_on_a_terminal_holds_the_raised_threads_at_the_default(
        control: int, pty_path: str) -> None:
    bus = Bus(pty_path)
    try:
        assert niceness(control) == 0
    finally:
        bus.close()
    assert niceness(control) == CONTROL_NICE
    bus.close()  # a second close releases nothing twice
    assert control_thread._terminals == 0


async def test_serial_links_on_terminals_hold_until_the_last_is_closed(
        control: int, pty_path: str) -> None:
    """An asyncio serial link and a threaded one, each on a terminal: the raise comes back
    when both are closed, not at the first close."""
    master2, slave2 = os.openpty()
    tty.setraw(slave2)
    first, second = SerialLink(pty_path), ThreadLink(os.ttyname(slave2))
    main, before = main_tid(), niceness(main_tid())
    try:
        await first.open()
        assert niceness(control) == 0
        assert niceness(main) == max(before, HOLD_MAIN_NICE)
        await second.open()
        assert second._thread is not None and second._thread.native_id is not None
        assert niceness(second._thread.native_id) == 0  # (it raised itself: held with the rest)
        await first.close()
        assert niceness(control) == 0
        await second.close()
        assert niceness(control) == CONTROL_NICE
        assert niceness(main) == before
    finally:
        await first.close()
        await second.close()
        os.close(slave2)
        os.close(master2)
    assert control_thread._terminals == 0


async def test_a_link_over_a_socket_keeps_the_raise(control: int) -> None:
    listener = socket.create_server(("127.0.0.1", 0))
    link = ThreadLink(f"socket://127.0.0.1:{listener.getsockname()[1]}")
    before = niceness(main_tid())
    try:
        await link.open()
        assert niceness(control) == CONTROL_NICE
        assert link._thread is not None and link._thread.native_id is not None
        assert niceness(link._thread.native_id) == CONTROL_NICE  # (the owner's requests)
        assert niceness(main_tid()) == before
        assert control_thread._terminals == 0
    finally:
        await link.close()
        listener.close()


def test_a_link_opened_by_the_control_thread_on_a_terminal_does_not_keep_its_raise(
        pty_path: str) -> None:
    """A thread inherits its creator's niceness: the link's thread, started from the control
    thread at -10, was left at -10 by the hold (it had not raised itself, so the hold did not
    know it), the one thread above the kworker that delivers its own port's bytes."""
    assert control_thread._terminals == 0
    thread = ControlThread("test-control-opens")
    thread.start()
    link = ThreadLink(pty_path)
    try:
        thread.submit(link.open()).result(30)
        assert link._thread is not None and link._thread.native_id is not None
        assert thread._thread is not None and thread._thread.native_id is not None
        assert niceness(link._thread.native_id) == 0
        assert niceness(thread._thread.native_id) == 0
    finally:
        thread.submit(link.close()).result(30)
        thread.stop()
    assert control_thread._terminals == 0


def test_a_hold_puts_the_main_thread_below_the_raised_ones(control: int) -> None:
    """... and gives it back its niceness at the last release."""
    main, before = main_tid(), niceness(main_tid())
    first, second = TerminalHold(), TerminalHold()
    try:
        assert niceness(control) == 0
        assert niceness(main) == max(before, HOLD_MAIN_NICE)
        first.release()
        assert niceness(main) == max(before, HOLD_MAIN_NICE)
    finally:
        first.release()
        second.release()
    assert niceness(main) == before
    assert niceness(control) == CONTROL_NICE


def test_a_thread_the_main_thread_starts_during_a_hold_gets_its_niceness_back(
        control: int) -> None:
    """A thread inherits its creator's niceness: one the main thread starts while it is at
    HOLD_MAIN_NICE (an executor's, a camera's) runs there with it, and comes back with it at
    the last release; one started before the hold is left where it was."""
    main, before = main_tid(), niceness(main_tid())
    stop = threading.Event()
    tids: list[int] = []

    def start_one() -> None:
        started = threading.Event()

        def run() -> None:
            tids.append(threading.get_native_id())
            started.set()
            stop.wait(30)

        threading.Thread(target=run, daemon=True).start()
        assert started.wait(10)

    try:
        start_one()  # before the hold
        hold = TerminalHold()
        try:
            start_one()
            assert niceness(main) == max(before, HOLD_MAIN_NICE)
            assert [niceness(t) for t in tids] == [before, max(before, HOLD_MAIN_NICE)]
        finally:
            hold.release()
        assert [niceness(t) for t in (main, *tids)] == [before, before, before]
        assert niceness(control) == CONTROL_NICE
    finally:
        stop.set()


def test_a_hold_with_no_raised_thread_leaves_the_main_thread() -> None:
    """A process with nothing raised (a lab's front, a client tool with a set-up bus) keeps its
    main thread where it is: a fresh interpreter, so that no thread of this one is raised."""
    probe = ("import os\n"
             "from app.runtime.control_thread import TerminalHold\n"
             "hold = TerminalHold()\n"
             "print(os.getpriority(os.PRIO_PROCESS, 0))\n"
             "hold.release()\n")
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True,
                         timeout=60, env=clean_env())
    assert out.returncode == 0, out.stderr
    assert int(out.stdout) == os.getpriority(os.PRIO_PROCESS, 0)  # (inherited from this one)


def test_a_thread_raised_while_a_terminal_is_in_use_starts_at_the_default() -> None:
    """... and gets its niceness when the terminal is closed; a thread that ended is
    forgotten (its id may be another thread's later)."""
    hold = TerminalHold()
    got: dict[str, int | None] = {}
    raised, go_on, ended = threading.Event(), threading.Event(), threading.Event()

    def run() -> None:
        got["asked"] = control_thread.raise_priority()
        got["tid"] = threading.get_native_id()
        got["now"] = os.getpriority(os.PRIO_PROCESS, 0)
        raised.set()
        go_on.wait(10)
        got["after"] = os.getpriority(os.PRIO_PROCESS, 0)
        control_thread.lower_priority()
        ended.set()

    thread = threading.Thread(target=run)
    try:
        thread.start()
        assert raised.wait(10), "the thread did not raise itself"
        assert got["asked"] == CONTROL_NICE and got["now"] == 0
    finally:
        hold.release()
        go_on.set()
        thread.join(10)
    assert ended.is_set() and got["after"] == CONTROL_NICE
    assert got["tid"] not in control_thread._raised


def test_an_arm_on_a_terminal_lowers_every_workers_raised_threads(tmp_path: Path) -> None:
    """`armserver serve --workers 2`, the angler on a pty (the simulated servos behind it, a
    process of their own) on worker 0 and a simulated rbe3001 on worker 1: worker 1 has no
    terminal itself, but the kernel worker that delivers worker 0's bytes would wait for its
    raised threads, so no thread of either runs above the default. (Without a terminal in the
    lab each worker has its threads at CONTROL_NICE: tests/test_lab_workers.py.)"""
    tty_path = tmp_path / "ttyANGLER"
    env = clean_env(ARMSERVER_DATA_DIR=str(tmp_path / "data"))
    sim = subprocess.Popen([sys.executable, "-m", "app.cli", "sim", "angler", "--pty",
                            str(tty_path)], env=env, stdout=subprocess.DEVNULL)
    front: Served | None = None
    try:
        wait_until(tty_path.exists, timeout=60, what="the simulated angler's pty")
        (tmp_path / "lab.toml").write_text(
            f'[[arms]]\nprofile = "angler"\nname = "rails"\nworker = 0\n[arms.link]\n'
            f'kind = "serial"\naddress = "{tty_path}"\n\n'
            '[[arms]]\nprofile = "rbe3001"\nname = "left"\nworker = 1\n')
        front = start(tmp_path / "lab.log", "--workers", "2", "--config",
                      str(tmp_path / "lab.toml"), "--log-level", "warning", env=env,
                      start_s=120)
        workers = Lab(front.proc, "", "").workers()
        assert sorted(workers) == [0, 1]
        for k, pid in workers.items():
            nice = threads_niceness(pid)
            assert 0 in nice and CONTROL_NICE not in nice, (k, nice)
            assert thread_niceness(pid, pid) == HOLD_MAIN_NICE, (k, nice)  # (the main thread)
    finally:
        if front is not None:  # (SIGTERM: the front stops its workers' arms, then them)
            front.stop()
        sim.terminate()
        sim.wait(10)
