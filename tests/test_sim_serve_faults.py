"""`armserver sim dynamixel --fault ID:FAULT@T --supply V`: faults raised on schedule in a
real simulator process, seen over a real TCP socket."""

from __future__ import annotations

import signal
import socket
import subprocess
import sys
import time

import pytest

from app.sim.serve import main, parse_fault
from protocol import dynamixel as dxl


def test_parse_fault() -> None:
    assert parse_fault("1:overload@2.0") == (1, "overload", 2.0)
    assert parse_fault("all:brown_out@0") == (None, "brown_out", 0.0)
    assert parse_fault("3:electrical-shock@1.5") == (3, "electrical_shock", 1.5)
    for bad in ("1:overload", "overload@2", "1:melted@2", "1:overload@-1", "1:overload@nan",
                "x:overload@1", "1:@1"):
        with pytest.raises(ValueError):
            parse_fault(bad)


def test_bad_fault_flag_exits_2(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["dynamixel", "--listen", "tcp://127.0.0.1:0", "--fault", "1:melted@1"]) == 2
    assert "overload" in capsys.readouterr().out  # names the valid faults
    assert main(["dynamixel", "--listen", "tcp://127.0.0.1:0", "--fault", "9:overload@1"]) == 2
    assert "no servo 9" in capsys.readouterr().out
    assert main(["dynamixel", "--listen", "tcp://127.0.0.1:0", "--supply", "nan"]) == 2


def _exchange(sock: socket.socket, request: bytes) -> dxl.Packet:
    sock.sendall(request)
    parser = dxl.Parser()
    while True:
        parser.feed(sock.recv(256))
        events = list(parser)
        if events:
            assert isinstance(events[0], dxl.Packet)
            return events[0]


def test_fault_flag_raises_the_error_on_schedule_over_tcp() -> None:
    proc = subprocess.Popen(
        [sys.executable, "-m", "app.sim.serve", "dynamixel", "--listen", "tcp://127.0.0.1:0",
         "--ids", "1,2", "--supply", "14.8", "--fault", "2:overheating@0.3"],
        stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None
        line = proc.stdout.readline()
        port = int(line.split("socket://127.0.0.1:")[1].rstrip(")\n"))
        with socket.create_connection(("127.0.0.1", port), timeout=5) as sock:
            assert _exchange(sock, dxl.read(1, 144, 2)).params == dxl.to_bytes(148, 2)
            assert _exchange(sock, dxl.write(2, 64, b"\x01")).error in (0, 0x80)
            for _ in range(200):  # the fault is due 0.3 s after the start
                p = _exchange(sock, dxl.read(2, 70, 1))
                if p.error:
                    break
                time.sleep(0.025)
            assert (p.error, p.params) == (0x80, b"\x04")
            assert _exchange(sock, dxl.read(2, 64, 1)).params == b"\x00"  # shut down
            assert _exchange(sock, dxl.read(1, 70, 1)) == dxl.Packet(1, 0x55, b"\x00", 0)
    finally:
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=10) == 0
