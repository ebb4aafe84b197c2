"""The practice bus (app/arms/dynamixel/practice.py) in a process of its own (in the server's,
its thread shared the GIL with the server's threads and read a scan's PING late): its process
ends with the server's pipe, its port with it; a bus whose process died is told as stopped;
its servos as plugged in, eight at most. The scans of it: test_setup_servos_routes.py,
test_setup_servos_readme.py, test_setup_servos_e2e.py."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
from conftest import may_raise_priority, thread_niceness

from app.arms.dynamixel.practice import PracticeBus, PracticeServo


def test_its_process_ends_with_the_pipe_and_takes_its_port() -> None:
    bus = PracticeBus(2)
    assert bus.servos() == [PracticeServo(1, 57_600), PracticeServo(1, 57_600)]
    assert bus.plug()[-1] == PracticeServo(1, 57_600)
    port = Path(bus.port)
    assert port.is_symlink() and bus._proc.pid != os.getpid()
    bus.close()
    assert bus._proc.returncode == 0
    assert not port.exists() and not port.parent.exists()
    bus.close()  # again: nothing
    with pytest.raises(ValueError, match="stopped"):
        bus.servos()


def test_a_bus_whose_process_died_is_told_stopped_and_past_eight_servos_is_refused() -> None:
    bus = PracticeBus(7)
    try:
        assert len(bus.plug()) == 8
        with pytest.raises(ValueError, match="8 servos at most"):
            bus.plug()
        assert len(bus.servos()) == 8  # the refusal changed nothing
        bus._proc.kill()
        bus._proc.wait(10)
        with pytest.raises(ValueError, match="stopped"):
            bus.plug()
    finally:
        bus.close()
    assert not Path(bus.port).parent.exists()  # the killed child's folder, removed here


def test_its_servos_answer_before_the_rest_of_the_machine_where_the_system_allows() -> None:
    """Every thread of the bus's process (the bus's own among them) runs at NICENESS where
    the system lets a process raise its priority (root, as `make test` runs in CI), else at
    the server's niceness: beside a load on both cores its servos read as silent."""
    from app.arms.dynamixel import practice

    mine = os.getpriority(os.PRIO_PROCESS, 0)
    allowed = may_raise_priority(practice.NICENESS)
    bus = PracticeBus(1)
    try:
        pid = bus._proc.pid
        tids = [int(t) for t in os.listdir(f"/proc/{pid}/task")]
        assert len(tids) >= 2  # the main thread and the bus's
        want = practice.NICENESS if allowed else mine
        assert {thread_niceness(pid, t) for t in tids} == {want}
        assert bus.servos() == [PracticeServo(1, 57_600)]  # and it serves
    finally:
        bus.close()
