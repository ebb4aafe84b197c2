"""Baud-rate mismatch as a UART gives it (issue 24): app/sim/uart.py's `resample` (the bytes a
UART at one rate reads from a stream sent at another), the simulated bus whose servos read the
host's bytes through it (silence between the standard rates, garbled bytes where a header
survives), a real pty carrying any rate (termios2), and the scans that tell garbled answers
from silence and still find the servos' rate: the link's on connect, `armserver setup-servos`.
"""

from __future__ import annotations

import os
import threading
from pathlib import Path

import httpx
import pytest
import serial
from _tcp import LoopThread
from _wait import TIMEOUT_S, wait_for, wait_until
from test_setup_servos import Served

from app.arms.dynamixel.setup import EXIT_OK
from app.arms.dynamixel.sim_bus import DynamixelBus
from app.arms.loading import load_profile
from app.cli import main
from app.sim.servers import serve_pty
from app.sim.uart import resample
from app.web.factory import create_app
from protocol import dynamixel as dxl
from tests.conftest import IN_PROCESS_REPLY_S, make_settings

RATES = (9_600, 57_600, 115_200, 1_000_000, 2_000_000, 3_000_000, 4_000_000, 4_500_000)
STATUS = dxl.encode_status(1, 0, bytes((30, 0, 45)))  # an MX-28's answer to PING


# ------------------------------------------------------------------ the UART


def test_equal_rates_read_what_was_sent() -> None:
    assert resample(STATUS, 57_600, 57_600) == STATUS
    assert resample(STATUS, 57_600, 57_600 * 1.02) == STATUS  # 2 % apart: both sides agree
    assert resample(b"", 57_600, 1_000_000) == b""


def test_a_receiver_twice_as_fast_reads_ff_as_fe() -> None:
    # start bit 2 receiver bits long: bit 0 is sampled inside it, bits 1-7 from data bits 0-6
    assert resample(b"\xff", 57_600, 115_200) == b"\xfe"
    assert resample(b"\xff\xff\xfd\x00", 1_000_000, 2_000_000).startswith(b"\xfe\xfe")


def test_a_much_faster_receiver_reads_breaks_and_a_slower_one_few_bytes() -> None:
    # 1 Mbps reading 57,600: every low run is a frame read all low (a break: 0x00), more bytes
    fast = resample(STATUS, 57_600, 1_000_000)
    assert set(fast) == {0} and len(fast) > len(STATUS)
    # 57,600 reading 1 Mbps: one frame spans many of the sender's bytes
    slow = resample(STATUS, 1_000_000, 57_600)
    assert 0 < len(slow) <= 2


def test_between_standard_rates_no_packet_survives() -> None:
    """Why a servo at another standard rate is silent: the host's instruction, read at the
    servo's rate, is never a valid packet (the reply, read at the host's, neither)."""
    for tx in RATES:
        for rx in RATES:
            if tx == rx:
                continue
            for packet in (dxl.ping(1), dxl.ping(dxl.BROADCAST_ID), STATUS):
                parser = dxl.Parser()
                parser.feed(resample(packet, tx, rx))
                assert not [e for e in parser if isinstance(e, dxl.Packet)], (tx, rx, packet)


# ------------------------------------------------------------------ the simulated bus


def _heard(servo_rate: int, host_rate: int, packet: bytes) -> bytes:
    bus = DynamixelBus(ids=(1,), baudrate=servo_rate)
    bus.set_host_baudrate(host_rate)
    return b"".join(reply for _, reply in bus.receive(packet, 0.0))


def test_the_bus_is_silent_between_standard_rates_but_one_pair_garbles() -> None:
    answers = {(s, h): _heard(s, h, dxl.ping(1)) for s in RATES for h in RATES}
    for (s, h), got in answers.items():
        if s == h:
            assert got == STATUS, (s, h)
        elif (s, h) == (4_500_000, 4_000_000):
            # the header survives 12.5 %, the CRC does not: the servo answers its CRC error
            # status at 4.5 Mbps, which the host at 4 Mbps reads as bytes that are no packet
            parser = dxl.Parser()
            parser.feed(got)
            events = list(parser)
            assert got and all(isinstance(e, dxl.ParseError) for e in events), got.hex()
        else:
            assert got == b"", (s, h, got.hex())
    # a broadcast PING draws nothing from a servo at another rate (a CRC error on ID 254)
    assert _heard(4_500_000, 4_000_000, dxl.ping(dxl.BROADCAST_ID)) == b""


@pytest.fixture
def at_4m5(tmp_path: Path) -> object:
    """One servo at 4.5 Mbps (Baud Rate 7) on a pty: a rate with no termios constant."""
    served = Served(DynamixelBus(ids=(1,), baudrate=4_500_000), tmp_path / "ttyDXL")
    try:
        yield served
    finally:
        served.close()


def test_on_a_pty_the_host_reads_silence_garbage_or_the_answer(at_4m5: Served) -> None:
    def ask(rate: int, heard: bool = True) -> bytes:
        """What the host reads after its PING: where it is `heard`, the first byte waited for
        (up to the tests' bound: beside stress-ng the bus's thread answered later than 0.2 s)
        and what follows it within 0.2 s; where not, what comes within 0.2 s (a time under
        test: silence)."""
        port = serial.serial_for_url(at_4m5.url, baudrate=rate,
                                     timeout=TIMEOUT_S if heard else 0.2)
        try:
            port.write(dxl.ping(1))
            first = bytes(port.read(1))
            port.timeout = 0.2
            return first + bytes(port.read(13)) if first else first
        finally:
            port.close()

    assert ask(4_500_000) == STATUS  # termios2 carries the rate
    assert ask(57_600, heard=False) == b""  # silence
    garbled = ask(4_000_000)
    parser = dxl.Parser()
    parser.feed(garbled)
    assert garbled and all(isinstance(e, dxl.ParseError) and e.kind == "garbage"
                           for e in parser), garbled.hex()


#: The broadcast PING's window in the set-up's scan here, s: the simulated bus answers from
#: this test's own process, and beside stress-ng (`make test-loaded`) its answer came after a
#: window of 0.5 s ("nothing answered at any standard rate"); a real bus answers within its
#: Return Delay Time. (A broadcast waits its whole window at each rate: three rates a scan.)
SCAN_WINDOW_S = 1.5


def test_setup_servos_finds_the_rate_past_the_garbled_one(
        at_4m5: Served, capsys: pytest.CaptureFixture[str]) -> None:
    argv = ["setup-servos", "--port", at_4m5.url, "--profile", "angler",
            "--timeout", str(SCAN_WINDOW_S), "--baudrates", "57600,4000000,4500000"]
    assert main(argv) == EXIT_OK
    out = capsys.readouterr().out
    assert "found ID 1 at 4,500,000 bps: MX-28(2.0)" in out
    # set up from there, to 1 Mbps (the rate found: the scan past the garbled one is above)
    assert main([*argv[:-1], "4500000", "--joint", "x"]) == EXIT_OK
    assert "joint x: set up and verified: ID 2 at 1,000,000 bps" in capsys.readouterr().out


async def test_the_link_tells_garbled_answers_from_silence(tmp_path: Path) -> None:
    """Servos at 4.5 Mbps, the profile at 4 Mbps: the set-up's PINGs come back garbled, the
    connect scan says so and where the servos answer. The reply timeout is conftest's
    IN_PROCESS_REPLY_S (0.3 s), not the profile's 50 ms: the simulated bus answers from this
    test's own process, and beside the parallel part's busy workers its garbled reply came
    after 50 ms and read as silence (a real bus's bytes wait in the UART for a late reader;
    these were not yet written)."""
    bus = DynamixelBus(ids=(1, 2, 3, 4), baudrate=4_500_000, operating_modes={1: 4, 2: 4, 4: 4})
    path = tmp_path / "ttyDXL"
    server = await serve_pty(bus, path)
    p = load_profile("angler")
    profile = p.model_copy(update={"link": p.link.model_copy(update={
        "kind": "serial", "address": str(path), "baudrate": 4_000_000,
        "homed_at_start": True, "timeout_s": IN_PROCESS_REPLY_S})})
    app = create_app(make_settings(), profiles=[profile])  # never ready: no wait_ready
    try:
        async with app.router.lifespan_context(app), httpx.AsyncClient(
                transport=httpx.ASGITransport(app=app), base_url="http://armserver.test") as c:
            svc = app.state.services["angler"]
            await wait_for(lambda: "servos answer at" in (svc.driver.link.last_error or ""),
                           what="the scan's finding", timeout=20.0)
            error = (await c.get("/api/v1/arms/angler")).json()["link"]["last_error"]
            assert "no servo answers at the profile's 4,000,000 bps (garbled answers at " \
                   "4,000,000 bps" in error, error
            assert "servos answer at 4,500,000 bps (ID 1, 2, 3, 4)" in error, error
            assert "set link.baudrate = 4500000" in error
    finally:
        await server.close()


# ------------------------------------------------------------------ a scan held up


class HeldUpClock:
    """`time` for app.arms.dynamixel.setup whose every reading after the first is taken by a
    thread held up past any window (a busy machine): it returns once the servo's reply is in
    the port's buffer, and far later than the window's end."""

    def __init__(self, port: serial.SerialBase) -> None:
        self.port, self.readings = port, 0

    def monotonic(self) -> float:
        self.readings += 1
        if self.readings == 1:
            return 0.0
        wait_until(lambda: self.port.in_waiting > 0, 10, "the reply in the port's buffer")
        return 1e6


def test_a_reply_that_came_within_the_window_counts_when_the_reader_is_held_up(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A broadcast PING's window, and a servo's reply timeout, end after the replies that came
    within them are read: the reader held up past the end once dropped them with the buffer
    (the scan of the README's practice bus, read as empty, once, beside six busy workers)."""
    from app.arms.dynamixel import setup

    served = Served(DynamixelBus.factory(1, baudrate=57_600), tmp_path / "ttyDXL")
    try:
        bus = setup.Bus(served.url, timeout=0.3)
        try:
            monkeypatch.setattr(setup, "time", HeldUpClock(bus.port))
            packets, errors = bus.exchange(dxl.ping(dxl.BROADCAST_ID))
            assert ([(p.id, p.params) for p in packets], errors) == ([(1, bytes((30, 0, 45)))], [])
            monkeypatch.setattr(setup, "time", HeldUpClock(bus.port))
            assert bus.read(1, setup._T["baud_rate"]) == 1  # code 1: 57,600 bps
        finally:
            bus.close()
    finally:
        served.close()


def test_a_late_answer_to_an_earlier_request_is_not_taken_for_this_ones(tmp_path: Path) -> None:
    """Protocol 2.0's status names no instruction: a PING's answer (3 bytes) that comes late,
    in a READ's time, is skipped by its size, and the READ's own answer taken (it once failed
    the set-up: "READ operating_mode: servo 1 answered 3 bytes, expected 1")."""
    import os
    import tty

    from app.arms.dynamixel import setup

    master, slave = os.openpty()
    tty.setraw(slave)
    link = tmp_path / "ttyLATE"
    link.symlink_to(os.ttyname(slave))
    heard = bytearray()

    def servo() -> None:  # answers the one READ with the late PING status first
        while len(heard) < 14:  # a READ of 1 byte is 14 bytes
            heard.extend(os.read(master, 64))
        os.write(master, STATUS + dxl.encode_status(1, 0, bytes((3,))))

    thread = threading.Thread(target=servo, daemon=True)
    bus = setup.Bus(str(link), timeout=2.0)
    try:
        thread.start()
        assert bus.read(1, setup._T["operating_mode"]) == 3
        assert bytes(heard) == dxl.read(1, setup._T["operating_mode"].address, 1)
    finally:
        bus.close()
        thread.join(5)
        os.close(master)
        os.close(slave)


class StarvedBus(Served):
    """The factory servo on a pty, behind a bus process that reads the host's Baud Rate WRITE
    late, once (starved beside a load: `make test-loaded`): the WRITE and whatever follows it
    are taken in `LATE_S` after they came, at the rate the pty has by then, as the practice
    bus reads them (app/sim/servers.py `PtyServer._on_readable`)."""

    #: Past the set-up's broadcast window (`--timeout`, IN_PROCESS_REPLY_S), 0.4 s inside its
    #: wait for a reply (REPLY_TIMEOUT_S, 1 s): at 3 x the window, 0.1 s inside it, the late
    #: status missed that wait beside stress-ng (`make test-loaded`, session 35).
    LATE_S = 2 * IN_PROCESS_REPLY_S

    def __init__(self, path: Path) -> None:
        from app.arms.dynamixel.setup import _T
        from app.sim.servers import PtyServer, pty_baudrate

        LoopThread.__init__(self)  # (Served's own would serve the bus as it comes)
        self.bus = DynamixelBus.factory(1, baudrate=57_600)
        self.held: list[bytes] = []
        self.late: list[int] = []  # the rate (the pty's) each held chunk was taken in at
        baud = _T["baud_rate"].address
        outer = self

        class Late(PtyServer):
            def _on_readable(self) -> None:
                data = os.read(self.master, 4096)
                parser = dxl.Parser()
                parser.feed(data)
                writes_baud = any(isinstance(p, dxl.Packet)
                                  and p.instruction == dxl.Instruction.WRITE
                                  and dxl.decode_write(p.params)[0] == baud for p in parser)
                if outer.held or (writes_baud and not outer.late):
                    outer.held.append(data)
                    if len(outer.held) == 1:
                        self._loop.call_later(outer.LATE_S, self.release)
                    return
                self.take(data)

            def take(self, data: bytes) -> None:
                self.device.set_host_baudrate(pty_baudrate(self.slave))
                self._pump.on_data(data)

            def release(self) -> None:
                for data in outer.held:
                    outer.late.append(pty_baudrate(self.slave))
                    self.take(data)
                outer.held.clear()

        async def start() -> PtyServer:
            return Late(self.bus, path)

        self.server = self.run(start())
        self.url = str(path)


def test_the_host_changes_its_rate_only_once_the_servo_has_read_the_baud_rate_write(
        tmp_path: Path) -> None:
    """The servo's status to the WRITE of its Baud Rate comes at the old rate (it answers the
    packet it read at that rate): the set-up waits for it before it sets the port to the new
    rate, as ROBOTIS's Dynamixel2Arduino `setBaudrate` (a WRITE that waits for its status)
    before `begin(new_rate)`. It used to wait only the broadcast window; a bus that read the
    WRITE after it read it at the new rate, as noise, and the servo stayed at 57,600 ("READ
    id: servo 2: no reply", the README's practice bus beside stress-ng)."""
    served = StarvedBus(tmp_path / "ttyDXL")
    try:
        argv = ["setup-servos", "--port", served.url, "--profile", "angler", "--timeout",
                str(IN_PROCESS_REPLY_S), "--baudrates", "57600,1000000", "--joint", "x"]
        assert main(argv) == EXIT_OK
        assert served.late and served.late[0] == 57_600  # the WRITE was read late, at 57,600
        [servo] = served.bus.servos
        assert (servo.id, servo.get("baud_rate"), servo.get("operating_mode")) == (2, 3, 4)
    finally:
        served.close()
