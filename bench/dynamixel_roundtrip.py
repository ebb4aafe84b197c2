"""Round trips per second of a 4-servo SYNC_READ: our angler driver next to DynamixelSDK,
both against the same simulated MX-28 bus on a real pseudo-terminal.

The bus runs in its own process (`armserver sim dynamixel --pty`), as hardware would: the SDK
busy-waits on a core while it polls (timeout 0), which would starve a simulator sharing its
interpreter. The simulator adds the wire time (10 bits a byte at 1 Mbps) and each servo's Return
Delay Time, so the figures are bus-limited, like the reference's: ~320 Hz with the default RDT
of 250 (500 us), ~890 Hz with RDT 0. Each row reads Present Load/Velocity/Position (10 bytes
from address 126) of ids 1-4, as the driver's poll does.

    python bench/dynamixel_roundtrip.py --seconds 3
"""

from __future__ import annotations

import argparse
import asyncio
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

IDS = [1, 2, 3, 4]
ADDR, LEN = 126, 10


def sdk_rate(path: str, seconds: float) -> tuple[float, int, float]:
    import dynamixel_sdk as sdk

    port = sdk.PortHandler(path)
    ph = sdk.PacketHandler(2.0)
    assert port.openPort() and port.setBaudRate(1_000_000)
    group = sdk.GroupSyncRead(port, ph, ADDR, LEN)
    for i in IDS:
        group.addParam(i)
    n = fails = 0
    t0, c0 = time.perf_counter(), time.process_time()
    while time.perf_counter() - t0 < seconds:
        if group.txRxPacket() == sdk.COMM_SUCCESS:
            n += 1
        else:
            fails += 1
    rate = n / (time.perf_counter() - t0)
    cpu = (time.process_time() - c0) / max(n, 1)
    port.closePort()
    return rate, fails, cpu


def sdk_write_rdt(path: str, rdt: int) -> None:
    """Torque off and Return Delay Time on every servo (EEPROM: torque must be off)."""
    import dynamixel_sdk as sdk

    port = sdk.PortHandler(path)
    ph = sdk.PacketHandler(2.0)
    assert port.openPort() and port.setBaudRate(1_000_000)
    for i in IDS:
        ph.write1ByteTxRx(port, i, 64, 0)
        ph.write1ByteTxRx(port, i, 9, rdt)
    port.closePort()


async def driver_rate(path: str, seconds: float) -> tuple[float, int, float]:
    from app.arms.dynamixel.driver import DynamixelDriver
    from app.arms.loading import load_profile
    from app.links.serial import SerialLink
    from app.telemetry.hub import TelemetryHub
    from protocol import mx28

    profile = load_profile("angler")
    profile.link.poll_hz = 1.0  # the bench drives the requests itself
    driver = DynamixelDriver(profile, SerialLink(path), TelemetryHub("angler"))
    await driver.start()
    assert await driver.wait_connected(10.0), driver.link.last_error
    item = mx28.ControlItem("present_state", ADDR, LEN, "ram", "r", None, None, 1.0, False, 0, 0)
    n = fails = 0
    t0, c0 = time.perf_counter(), time.process_time()
    while time.perf_counter() - t0 < seconds:
        try:
            await driver.sync_read(item, IDS)
            n += 1
        except Exception:  # noqa: BLE001 - a benchmark counts failures, whatever they are
            fails += 1
    rate = n / (time.perf_counter() - t0)
    cpu = (time.process_time() - c0) / max(n, 1)
    await driver.close()
    return rate, fails, cpu


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--seconds", type=float, default=3.0)
    a = p.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "ttyDXL")
        sim = subprocess.Popen([sys.executable, "-c", "from app.cli import run; run()", "sim",
                                "dynamixel", "--pty", path, "--mode", "1:4", "--mode", "2:4",
                                "--mode", "4:4"], cwd=ROOT)
        try:
            deadline = time.monotonic() + 10
            while not os.path.exists(path) and time.monotonic() < deadline:
                time.sleep(0.05)
            rows = []
            for rdt in (250, 0):
                sdk_write_rdt(path, rdt)
                rows.append((rdt, *sdk_rate(path, a.seconds),
                             *asyncio.run(driver_rate(path, a.seconds))))
        finally:
            sim.terminate()
            sim.wait(5)
    print(f"4-servo SYNC_READ of {LEN} bytes at 1 Mbps over a pty, {a.seconds:g} s each "
          "(simulated bus adds wire time and Return Delay Time)")
    print("(CPU is this process's CPU time per round trip: the SDK busy-waits while it polls)")
    print(f"{'RDT':>5} {'SDK /s':>7} {'fails':>5} {'CPU/rt':>8} {'driver /s':>9} {'fails':>5} "
          f"{'CPU/rt':>8} {'rate ratio':>10} {'CPU ratio':>9}")
    for rdt, sr, sf, sc, dr, df, dc in rows:
        print(f"{rdt * 2:>3}us {sr:>7.0f} {sf:>5} {sc * 1e6:>6.0f}us {dr:>9.0f} {df:>5} "
              f"{dc * 1e6:>6.0f}us {dr / sr:>10.2f} {dc / sc:>9.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
