"""Servo set-up from the factory state in the dashboard (API.md "Calibration (v1.2)", servo
set-up): scan a port, give the one servo on it a joint's ID and settings, and the practice
bus (a simulated factory-state bus the server serves on a pseudo-terminal)."""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import Field

from app.schemas.common import Bool, Int, Model

#: A port: an absolute path of a serial device, or socket://HOST:PORT (loopback only).
Port = Field(min_length=1, max_length=256, pattern=r"^(/|socket://)[^\x00-\x1f]*$",
             description="an absolute path of a serial device (/dev/ttyUSB0, "
             "/dev/serial/by-id/..., the practice bus's pty) or a loopback "
             "socket://127.0.0.1:PORT (`armserver sim dynamixel --listen`)")
ProfileName = Field(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9][A-Za-z0-9_.-]*$",
                    description="a built-in profile's name or a hosted arm's profile name")
#: The standard Dynamixel rates (e-manual, "Baud Rate(8)").
Rate = Literal[9600, 57600, 115200, 1000000, 2000000, 3000000, 4000000, 4500000]


class ServoScanRequest(Model):
    port: str = Port
    profile: str = ProfileName
    timeout: Annotated[float, Field(gt=0.0, le=2.0, allow_inf_nan=False, strict=True)] | None = \
        Field(None, description="how long a broadcast PING waits for answers at each rate, s "
              "(default 0.3; the CLI's --timeout); a servo heard may take up to 1 s to answer")
    baudrates: list[Rate] | None = Field(
        None, min_length=1, max_length=8,
        description="rates to scan, in this order (default: 57,600, 1,000,000, then the "
        "others); a socket:// port carries none: one broadcast PING there")


class ServoAssignRequest(ServoScanRequest):
    joint: str = Field(min_length=1, max_length=32, description="the joint whose servo is the "
                       "one servo on the bus that is not another joint's")


class FoundServo(Model):
    id: Int = Field(description="its ID (7)")
    baudrate: Int = Field(description="the rate it answers at, bit/s (its Baud Rate (8))")
    model: Int = Field(description="Model Number (0): 30 MX-28(2.0), 1020 XM430-W350")
    model_name: str
    firmware: Int = Field(description="Firmware Version (6)")
    torque: Bool = Field(description="Torque Enable (64): EEPROM is written only with it off")
    mode: Int = Field(description="Operating Mode (11)")
    joint: str | None = Field(description="the profile's joint this servo already is (its ID "
                              "at the profile's rate), or null")
    factory: Bool = Field(description="ID 1 at 57,600 bps: as shipped")
    note: str = Field(description="what it is against the profile, in words")


class ServoScan(Model):
    port: str
    profile: str
    servos: list[FoundServo]
    collisions: list[str] = Field(description="garbled answers: two servos on one ID answer "
                                  "at once (connect one servo at a time)")
    garbled: list[str] = Field(description="rates where only garbled bytes came: a UART at "
                               "another rate than a servo's reads its replies so (told apart "
                               "from silence; not refused)")
    joints: dict[str, Int] = Field(description="the profile's joints and their IDs")
    profile_baudrate: Int = Field(description="the rate the profile's link runs at, bit/s")
    todo: list[str] = Field(description="the profile's joints no servo found is yet, in order")


class ServoAssigned(Model):
    port: str
    profile: str
    joint: str
    servo: FoundServo = Field(description="the servo as set up and read back")
    said: list[str] = Field(description="what the set-up found and did, line by line")


class PracticeServo(Model):
    id: Int
    baudrate: Int


class PracticeBus(Model):
    running: Bool
    port: str | None = Field(description="the path of its pseudo-terminal while running")
    servos: list[PracticeServo] = Field(description="what is plugged in, in that order")


class PracticeBusRequest(Model):
    servos: Int = Field(1, ge=0, le=8, description="factory servos plugged in at the start")


class ServoSetupInfo(Model):
    profiles: list[str] = Field(description="profiles of Dynamixel arms a set-up can follow")
    ports_in_use: dict[str, str] = Field(description="ports the server's arms own: port -> "
                                         "arm (never scanned nor written here)")
    practice: PracticeBus
