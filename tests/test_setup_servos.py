"""`armserver setup-servos` (issue 24, item 3) against the simulated bus in the factory state
(every servo ID 1 at 57,600 bps), served on a real pseudo-terminal whose termios baud rate the
bus honours: factory servos found, set up one at a time as the angler's joints, collisions and
refusals reported with a non-zero exit and nothing written."""

from __future__ import annotations

import asyncio
import math
import os
import threading
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, TypeVar

import pytest
from _tcp import LoopThread

from app.arms.dynamixel.practice import NICENESS
from app.arms.dynamixel.setup import EXIT_NONE, EXIT_SEVERAL
from app.arms.dynamixel.sim_bus import DynamixelBus
from app.arms.dynamixel.sim_mx28 import BAUD_CODES
from app.cli import main
from app.sim.servers import serve_pty, serve_tcp
from protocol import dynamixel as dxl
from tests.conftest import IN_PROCESS_REPLY_S, may_raise_priority, thread_niceness

T = TypeVar("T")

ANGLER = {"x": 2, "y": 1, "theta3": 3, "z": 4}  # the profile's motor ids


class Served(LoopThread):
    """A bus served on a pty (or TCP) from a loop in its own thread, for a blocking client
    (tests/test_setup_servos_baud.py's too)."""

    def __init__(self, bus: DynamixelBus, path: Path | None) -> None:
        super().__init__()
        self.bus = bus
        if path is not None:
            self.server: Any = self.run(serve_pty(bus, path))
            self.url = str(path)
        else:
            srv = self.run(serve_tcp(bus))
            self.server, self.url = srv, f"socket://127.0.0.1:{srv.port}"

    def call(self, fn: Callable[[], T]) -> T:
        async def go() -> T:
            return fn()
        return self.run(go())

    def close(self) -> None:
        self.run(self.server.close())
        self.stop()


@pytest.fixture
def factory_bus(tmp_path: Path) -> Iterator[Served]:
    served = Served(DynamixelBus.factory(1), tmp_path / "ttyDXL")
    try:
        yield served
    finally:
        served.close()


def test_the_bus_answers_from_a_thread_above_the_rest_of_the_machine_where_allowed(
        factory_bus: Served) -> None:
    """The bus's loop thread runs at the practice bus's NICENESS where the system lets a
    process raise its priority (root, as `make test` runs in CI), else at this thread's
    (tests/_tcp.py LoopThread): it stands for a board with a processor of its own."""
    mine = os.getpriority(os.PRIO_PROCESS, 0)
    allowed = may_raise_priority(NICENESS)
    tid = factory_bus.thread.native_id
    assert tid is not None and tid != threading.get_native_id()
    assert thread_niceness(os.getpid(), tid) == (NICENESS if allowed else mine)
    assert os.getpriority(os.PRIO_PROCESS, 0) == mine  # this thread's own is as it was
    assert setup(factory_bus.url) == 0  # and it serves (a scan: the factory servo found)


def setup(url: str, joint: str | None = None, rates: str | None = "57600,1000000") -> int:
    """`armserver setup-servos` on `url` for the angler; at the two rates the servos here run
    at (the full scan of every standard rate is `test_factory_servo_found_at_57600`'s). The
    scan's window is IN_PROCESS_REPLY_S (the bus answers from a thread of this process): at
    0.15 s, beside stress-ng, a scan once heard none of four servos."""
    argv = ["setup-servos", "--port", url, "--profile", "angler", "--timeout",
            str(IN_PROCESS_REPLY_S)]
    if rates:
        argv += ["--baudrates", rates]
    return main([*argv, "--joint", joint] if joint else argv)


def state(bus: DynamixelBus) -> list[tuple[int, int, int]]:
    """(ID, baud rate, operating mode) of every servo on the bus, by ID."""
    return sorted((s.id, BAUD_CODES[s.get("baud_rate")], s.get("operating_mode"))
                  for s in bus.servos)


def test_factory_servo_found_at_57600(factory_bus: Served,
                                      capsys: pytest.CaptureFixture[str]) -> None:
    assert setup(factory_bus.url, rates=None) == 0  # every standard rate
    out = capsys.readouterr().out
    assert "found ID 1 at 57,600 bps: MX-28(2.0), firmware 45, operating mode 3" in out
    assert "[factory state]" in out
    assert "joint y's ID, but not the profile's 1,000,000 bps" in out


def test_four_factory_servos_set_up_one_at_a_time(factory_bus: Served,
                                                  capsys: pytest.CaptureFixture[str]) -> None:
    bus = factory_bus.bus
    assert setup(factory_bus.url, "x") == 0
    assert state(bus) == [(2, 1_000_000, 4)]
    x = next(s for s in bus.servos)
    assert x.get("return_delay_time") == 0  # the profile's link.return_delay_us
    # the next servo joins the bus beside the one set up: y keeps ID 1, moves to 1 Mbps
    factory_bus.call(bus.add_servo)
    assert setup(factory_bus.url, "y") == 0
    assert state(bus) == [(1, 1_000_000, 4), (2, 1_000_000, 4)]
    # two new servos at once: both ID 1 at 57,600, their replies collide
    factory_bus.call(bus.add_servo)
    extra = factory_bus.call(bus.add_servo)
    capsys.readouterr()
    assert setup(factory_bus.url, "theta3") == EXIT_SEVERAL
    err = capsys.readouterr().err
    assert "garbled replies at 57,600 bps" in err and "connect one servo at a time" in err
    assert state(bus).count((1, 57_600, 3)) == 2  # nothing written
    factory_bus.call(lambda: bus.remove_servo(extra))  # type: ignore[arg-type]
    assert setup(factory_bus.url, "theta3") == 0
    factory_bus.call(bus.add_servo)
    assert setup(factory_bus.url, "z") == 0
    want = sorted((ANGLER[j], 1_000_000, 4) for j in ANGLER)
    assert state(bus) == want
    # every servo as the profile wants it: nothing left to set up for a joint already placed
    capsys.readouterr()
    assert setup(factory_bus.url) == 0
    out = capsys.readouterr().out
    for joint, i in ANGLER.items():
        assert f"found ID {i} at 1,000,000 bps" in out and f"= joint {joint}" in out


class LateAt57600(DynamixelBus):
    """A bus behind a port that hands the replies to the first broadcast PING at 57,600 bps
    over after the scan's window (a busy PC's starved kernel worker): dropped here."""

    late = True

    def receive(self, data: bytes, now: float) -> list[tuple[float, bytes]]:
        out = super().receive(data, now)
        if self.late and self.baudrate == 57_600 and dxl.ping(dxl.BROADCAST_ID) in data:
            self.late = False
            return []
        return out


def test_a_new_servo_late_at_its_rate_is_scanned_again_before_there_is_none(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """y's servo answers at 1 Mbps; the new one's replies at 57,600 come after the first
    pass's window. The first pass heard only a servo already set up: the rates are scanned
    again before "no servo to set up", and the new servo becomes x."""
    bus = LateAt57600.factory(1)
    served = Served(bus, tmp_path / "ttyLate")
    try:
        served.call(lambda: bus.add_servo(id=1, baudrate=1_000_000))
        assert setup(served.url, "x") == 0, capsys.readouterr().err
        assert not bus.late  # (the first PING at 57,600 went unanswered)
        assert state(bus) == [(1, 1_000_000, 3), (2, 1_000_000, 4)]
    finally:
        served.close()


def test_a_listing_scans_twice_for_a_servo_late_beside_one_that_answered(
        tmp_path: Path) -> None:
    """The listing (`setup-servos` without `--joint`, the scan route): y's servo answers at
    1 Mbps, a factory servo's replies at 57,600 come after the first pass's window. Both
    are listed, each once (session 39 listed only y)."""
    from app.arms.dynamixel.setup import scan_port

    bus = LateAt57600.factory(1)
    served = Served(bus, tmp_path / "ttyLateList")
    try:
        served.call(lambda: bus.add_servo(id=1, baudrate=1_000_000))
        got = scan_port(served.url, rates=(57_600, 1_000_000))
        assert not bus.late  # (the first PING at 57,600 went unanswered)
        assert got.passes == 2 and not got.collisions
        assert sorted((f.id, f.baudrate) for f in got.found) == [(1, 57_600), (1, 1_000_000)]
    finally:
        served.close()


def test_refusals_exit_non_zero_with_a_reason(tmp_path: Path,
                                              capsys: pytest.CaptureFixture[str]) -> None:
    served = Served(DynamixelBus.factory(0), tmp_path / "ttyEmpty")
    try:
        assert setup(served.url, "x") == EXIT_NONE
        assert "nothing answered at any standard rate" in capsys.readouterr().err
        assert setup(served.url) == EXIT_NONE
        # y's servo in place: x's set-up does not take another joint's servo
        bus = served.bus
        served.call(lambda: bus.add_servo(id=1, baudrate=1_000_000))
        assert setup(served.url, "x") == EXIT_NONE
        assert "only ID 1 (y), already set up" in capsys.readouterr().err
        assert state(bus) == [(1, 1_000_000, 3)]
        # two factory servos on one ID: refused, nothing written (beside stress-ng the pty
        # once handed their garbled replies over after the 57,600 window while y answered
        # at 1 Mbps: "only ID 1 (y), already set up", until the set-up scanned again before
        # saying so; session 39's `make test-loaded`)
        served.call(bus.add_servo)
        served.call(bus.add_servo)
        assert setup(served.url, "x") == EXIT_SEVERAL
        assert state(bus) == [(1, 57_600, 3), (1, 57_600, 3), (1, 1_000_000, 3)]
        # a profile that gives joint x the ID of joint y: refused before anything is written
        twin = tmp_path / "twin.toml"
        text = (Path(__file__).parent.parent / "app/arms/angler/angler.toml").read_text()
        twin.write_text(text.replace("motor_id = 2 ", "motor_id = 1 ", 1))
        capsys.readouterr()
        assert main(["setup-servos", "--port", served.url, "--profile", str(twin),
                     "--joint", "x", "--baudrates", "57600,1000000"]) == 5
        assert "ID 1 is in use by joint y" in capsys.readouterr().err
        # torque on (a servo holding a load): EEPROM untouched
        served.call(lambda: bus.remove_servo(bus.servos[-1]))
        served.call(lambda: bus.servos[-1].set("torque_enable", 1))
        assert setup(served.url, "x") == 5
        assert "torque on" in capsys.readouterr().err
    finally:
        served.close()


def test_over_a_socket_the_rate_is_read_from_the_servo(capsys: pytest.CaptureFixture[str]
                                                       ) -> None:
    """A socket carries no baud rate: one broadcast PING, each servo's rate from its item."""
    served = Served(DynamixelBus.factory(1, baudrate=None), None)
    try:
        assert setup(served.url, "theta3") == 0
        assert state(served.bus) == [(3, 1_000_000, 4)]
        assert "joint theta3: set up and verified: ID 3 at 1,000,000 bps" in \
            capsys.readouterr().out
    finally:
        served.close()


def test_a_scan_that_heard_nothing_tries_once_more() -> None:
    """A servo whose first PING went unanswered (as a reply the machine delivered after the
    window reads) is found by the second pass; an empty bus is tried twice, and so is a bus
    that answered (a listing; the set-up's own scan passes once where it heard a servo)."""
    from app.arms.dynamixel.setup import Bus, scan, scan_port

    served = Served(DynamixelBus.factory(1, baudrate=None), None)
    try:
        got = scan_port(served.url, timeout=IN_PROCESS_REPLY_S)
        assert got.passes == 2 and [(f.id, f.baudrate) for f in got.found] == [(1, 57_600)]
        bus = Bus(served.url, timeout=IN_PROCESS_REPLY_S)
        try:
            assert scan(bus).passes == 1
        finally:
            bus.close()
        answer = served.bus.receive
        heard: list[bytes] = []

        def deaf_to_the_first(data: bytes, now: float) -> list[tuple[float, bytes]]:
            heard.append(data)
            return [] if len(heard) == 1 else answer(data, now)

        served.call(lambda: setattr(served.bus, "receive", deaf_to_the_first))
        got = scan_port(served.url, timeout=IN_PROCESS_REPLY_S)
        assert got.passes == 2 and [(f.id, f.baudrate) for f in got.found] == [(1, 57_600)]
        assert heard[0] == heard[1]  # the same broadcast PING, again
    finally:
        served.close()
    empty = Served(DynamixelBus.factory(0, baudrate=None), None)
    try:
        got = scan_port(empty.url, timeout=IN_PROCESS_REPLY_S)
        assert got.passes == 2 and not got.found
    finally:
        empty.close()


def test_pty_baud_mismatch_is_silence(tmp_path: Path) -> None:
    """A servo at 1 Mbps does not answer a host at 57,600 on the pty (and does at 1 Mbps)."""
    import serial
    from _wait import TIMEOUT_S

    from protocol import dynamixel as dxl

    served = Served(DynamixelBus(ids=(1,), baudrate=1_000_000), tmp_path / "ttyMis")
    try:
        # silence is "nothing within 0.2 s" (a time under test); the answer is waited for, up
        # to the tests' bound (the read returns with its 14 bytes): beside stress-ng the bus's
        # thread once took longer than 0.2 s to answer
        for rate, answers, wait in ((57_600, False, 0.2), (1_000_000, True, TIMEOUT_S)):
            port = serial.serial_for_url(served.url, baudrate=rate, timeout=wait)
            try:
                port.write(dxl.ping(1))
                assert bool(port.read(14)) is answers, rate
            finally:
                port.close()
    finally:
        served.close()


async def test_factory_servos_to_a_first_move(tmp_path: Path) -> None:
    """The day-one path: four factory servos set up one at a time by setup-servos, then the
    angler served on that bus (a serial link, as hardware): not homed, theta3 not calibrated,
    a move refused; homed and calibrated by declaring the pose; then it moves."""
    import httpx
    from _wait import wait_for

    from app.arms.loading import load_profile
    from app.web.factory import create_app
    from tests.conftest import make_settings, wait_ready, with_reply_timeout

    served = Served(DynamixelBus.factory(1), tmp_path / "ttyDXL")
    try:
        bus = served.bus
        for k, joint in enumerate(ANGLER):
            if k:
                served.call(bus.add_servo)  # the next servo, alone with the ones set up
            assert await asyncio.to_thread(setup, served.url, joint) == 0
        assert state(bus) == sorted((i, 1_000_000, 4) for i in ANGLER.values())
        # the arm as assembled to the design's MATLAB, theta3 at -30 deg: its servo reads
        # 4096 - 341 ticks at power-up (extended position mode restarts within one turn)
        served.call(lambda: setattr(bus.servo(3), "pos", 4096.0 - 341.0))
        p = load_profile("angler")
        # the bus answers from a thread of this process: IN_PROCESS_REPLY_S, not the profile's
        # 50 ms (beside stress-ng a SYNC_READ's status came later, and the move failed)
        profile = with_reply_timeout(p.model_copy(update={"link": p.link.model_copy(
            update={"kind": "serial", "address": served.url})}))
        app = create_app(make_settings(), profiles=[profile])
        async with app.router.lifespan_context(app), httpx.AsyncClient(
                transport=httpx.ASGITransport(app=app), base_url="http://armserver.test",
                timeout=30.0) as c:
            await wait_ready(app)
            api = "/api/v1/arms/angler"
            detail = (await c.get(api)).json()
            assert detail["homed"] == [False] * 4
            assert detail["calibrated"] == [True, True, False, True]  # theta3's horn
            q = app.state.services["angler"].driver.positions
            assert float(q[2]) == pytest.approx((4096 - 341) / 4096 * 2 * math.pi, abs=1e-3)
            r = await c.post(f"{api}/move/joints", json={"positions": [0.0, 0.0, 0.0, 0.05]})
            assert r.status_code == 409 and r.json()["code"] in ("not_homed", "not_calibrated")
            home = [0.0, 0.0, -0.5236, 0.05]  # where the arm is (measured by the student)
            r = await c.post(f"{api}/home", json={"positions": home})
            assert r.status_code == 200, r.text
            r = await c.post(f"{api}/calibration", json={"positions": home})
            assert r.status_code == 200, r.text
            detail = (await c.get(api)).json()
            assert detail["homed"] == [True] * 4 and detail["calibrated"] == [True] * 4
            goal = [0.005, -0.005, 0.3, 0.06]
            r = await c.post(f"{api}/move/joints", json={"positions": goal, "wait": True})
            assert r.status_code == 200 and r.json()["status"] == "done", r.text
            svc = app.state.services["angler"]
            await wait_for(lambda: abs(float(svc.driver.positions[2]) - 0.3) < 0.01,
                           what="theta3 at 0.3 rad")
            # theta3 at 0.3 rad is 0.3 / (2 pi) * 4096 ticks from where it was declared 0
            s3 = served.call(lambda: bus.servo(3))
            assert s3.get("goal_position") - round(s3.get("present_position")) in range(-8, 9)
        assert app.state.internal_errors == 0
    finally:
        served.close()


def test_readme_commands(tmp_path: Path) -> None:
    """README "From unboxed servos to a first move": the simulator in the factory state and
    setup-servos as the commands are written there (`armserver ...`, as subprocesses)."""
    import os
    import signal
    import subprocess
    import sys

    from _wait import wait_until

    pty = tmp_path / "ttyDXL"
    arm = [sys.executable, "-m", "app.cli"]
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    sim = subprocess.Popen([*arm, "sim", "dynamixel", "--factory", "1", "--pty", str(pty)],
                           stdout=subprocess.PIPE, text=True, env=env)
    try:
        wait_until(lambda: pty.is_symlink(), what="the simulator's pty")
        scan = subprocess.run([*arm, "setup-servos", "--port", str(pty), "--profile", "angler"],
                              capture_output=True, text=True, timeout=60, env=env)
        assert scan.returncode == 0, scan.stderr
        assert "found ID 1 at 57,600 bps" in scan.stdout and "[factory state]" in scan.stdout
        x = subprocess.run([*arm, "setup-servos", "--port", str(pty), "--profile", "angler",
                            "--joint", "x"], capture_output=True, text=True, timeout=60, env=env)
        assert x.returncode == 0, x.stderr
        assert "joint x: set up and verified: ID 2 at 1,000,000 bps" in x.stdout
        again = subprocess.run([*arm, "setup-servos", "--port", str(pty), "--profile", "angler",
                                "--joint", "y"], capture_output=True, text=True, timeout=60,
                               env=env)
        assert again.returncode == EXIT_NONE  # the only servo is x's now
        assert "no servo to set up: only ID 2 (x), already set up" in again.stderr
    finally:
        sim.send_signal(signal.SIGTERM)
        sim.wait(10)
    assert "dynamixel bus of 1 factory servo(s) (ID 1, 57,600 bps)" in (sim.stdout.read()
                                                                          if sim.stdout else "")
