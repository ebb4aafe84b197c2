"""The protocol pass-through models (rbe3001, dynamixel); their raw fields say their units
in their names."""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import Field

from app.schemas.common import Bool, DxlIdValue, Finite, Int, Model, Unit

# ---------------------------------------------------------------- rbe3001 pass-through


class PidSetpoint(Model):
    position_ticks: Finite
    velocity_ticks_s: Finite = 0.0
    force: Finite = 0.0


class SetPid(Model):
    joints: list[PidSetpoint] = Field(min_length=3, max_length=3)


class SetPidReply(Model):
    position_ticks: list[float]


class Rbe3001Status(Model):
    position_ticks: list[float]
    velocity_ticks_s: list[float]
    strain_adc: list[float]


#: A PID gain in the firmware's units (the default kp is 0.005; the output saturates at 0.2,
#: so 1000 already means full output at 0.0002 ticks of error). A negative gain makes the loop
#: unstable and is refused.
Gain = Annotated[float, Field(ge=0.0, le=1000.0, allow_inf_nan=False, strict=True)]


class SetGain(Model):
    axis: Int = Field(ge=0, le=2)
    kp: Gain
    ki: Gain
    kd: Gain


class SetClaw(Model):
    value: Unit


class Ack(Model):
    ok: bool = True
    command: str
    reply: Literal["acknowledged", "sent", "other"] | None = Field(
        None, description="rbe3001 SET_GAIN / SET_CLAW, which \"do not provide any return "
        "values\" (design document): `acknowledged` (zeros or the echo), `other` (other "
        "bytes, logged), `sent` (no reply within the quiet wait of one timeout)")


# ---------------------------------------------------------------- dynamixel pass-through


class PingRequest(Model):
    id: DxlIdValue | None = Field(None, description="one id, or none for every id")


class PingDevice(Model):
    id: int
    model_number: int
    firmware_version: int


class PingResult(Model):
    devices: list[PingDevice]


class RegisterValue(Model):
    id: int
    name: str
    address: int
    size: int
    raw: int
    unit: str | None = None
    value: float | None = Field(None, description="raw converted to the item's unit, if any")


class RegisterWrite(Model):
    raw: Int


class RebootRequest(Model):
    load_supported: Bool = Field(
        False, description="the load of a joint that falls without torque (the profile's "
        "`falls_without_torque`) rests or is held: its servo may be rebooted while it holds "
        "torque (the reboot switches it off until the servo is set up again)")


class SyncReadRequest(Model):
    name: str
    ids: list[DxlIdValue] = Field(min_length=1, max_length=32)


class SyncReadResult(Model):
    name: str
    values: dict[int, int]


class SyncWriteRequest(Model):
    name: str
    # keys are JSON object keys, so strings: "1" is id 1; the values are strict
    values: dict[Annotated[int, Field(ge=0, le=252)], Int] = Field(min_length=1, max_length=32)
