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


def _status(sock: socket.socket) -> tuple[float, ...]:
    """One rbe3001 STATUS exchange: the reply's 15 floats (its id echoed)."""
    from protocol import rbe3001

    sock.sendall(rbe3001.encode_packet(rbe3001.CommandId.STATUS))
    data = b""
    while len(data) < rbe3001.PACKET_SIZE:
        data += sock.recv(rbe3001.PACKET_SIZE - len(data))
    packet = rbe3001.decode_packet(data)
    assert packet.command_id == rbe3001.CommandId.STATUS
    return packet.values


def test_several_listen_addresses_serve_one_device_each_from_one_process() -> None:
    """`armserver sim rbe3001 --listen A --listen B`: two firmwares in one process (a lab's
    arms, bench/lab.py), each on its own address; a command to one leaves the other as it
    was, and a burst of requests gets every reply, whole and in order."""
    from protocol import rbe3001

    proc = subprocess.Popen(
        [sys.executable, "-m", "app.sim.serve", "rbe3001", "--listen", "tcp://127.0.0.1:0",
         "--listen", "tcp://127.0.0.1:0"], stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None
        ports = [int(proc.stdout.readline().split("socket://127.0.0.1:")[1].rstrip(")\n"))
                 for _ in range(2)]
        assert ports[0] != ports[1]
        with socket.create_connection(("127.0.0.1", ports[0]), timeout=5) as a, \
                socket.create_connection(("127.0.0.1", ports[1]), timeout=5) as b:
            start_a, start_b = _status(a)[:3], _status(b)[:3]
            # SET_PID: the base joint 300 ticks on, on arm a only
            goal = [start_a[0] + 300.0, 0.0, 0.0, start_a[1], 0.0, 0.0, start_a[2], 0.0, 0.0]
            a.sendall(rbe3001.encode_packet(rbe3001.CommandId.SET_PID, goal))
            data = b""
            while len(data) < rbe3001.PACKET_SIZE:
                data += a.recv(rbe3001.PACKET_SIZE - len(data))
            assert rbe3001.decode_packet(data).command_id == rbe3001.CommandId.SET_PID
            for _ in range(400):
                if abs(_status(a)[0] - start_a[0]) > 100:
                    break
                time.sleep(0.01)
            assert abs(_status(a)[0] - start_a[0]) > 100
            # the other firmware's base did not turn (its shoulder and elbow may sag: no
            # setpoint holds them yet)
            assert _status(b)[0] == start_b[0]
            # a burst of 50 requests at once: 50 replies, whole, in order
            b.sendall(rbe3001.encode_packet(rbe3001.CommandId.STATUS) * 50)
            data = b""
            while len(data) < 50 * rbe3001.PACKET_SIZE:
                data += b.recv(4096)
            assert len(data) == 50 * rbe3001.PACKET_SIZE
            ids = {rbe3001.decode_packet(data[k:k + 64]).command_id
                   for k in range(0, len(data), 64)}
            assert ids == {rbe3001.CommandId.STATUS}
    finally:
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=10) == 0
