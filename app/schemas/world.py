"""The simulated world's contract (API.md "Simulated world (v1.2, simulated arms only)"):
objects and bins in the arm's base frame, metres."""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import Field

from app.schemas.arms import Vec3
from app.schemas.common import Bool, Finite, Model

Name = Annotated[str, Field(min_length=1, max_length=64)]
Color = Annotated[str, Field(min_length=1, max_length=32,
                             description="a named colour: red, green, blue or yellow")]


class WorldObject(Model):
    id: Name
    kind: Literal["ball", "block", "target"] = Field(
        description="`ball` or `block` for a claw, `target` (magnetic) for a magnet")
    color: Color
    position: Vec3 = Field(description="centre, m, base frame; a PUT's z is not used: the "
                           "object settles on what is below it (a bin's floor or the table)")
    held: Bool = Field(False, description="in the end effector now (ignored by PUT)")


class WorldBin(Model):
    name: Name
    color: Color
    min: Vec3 = Field(description="the box's min corner, m, base frame")
    max: Vec3 = Field(description="the box's max corner, m, base frame")


class WorldTable(Model):
    """The table's top (read only): a rectangle at height z, m."""

    x_min: float
    x_max: float
    y_min: float
    y_max: float
    z: float


class WorldScene(Model):
    objects: list[WorldObject] = Field(max_length=64)
    bins: list[WorldBin] = Field(max_length=16)
    table: WorldTable | None = Field(None, description="the table (answers only; ignored by "
                                     "PUT)")
    tip: Vec3 | None = Field(None, description="where the simulated tip is (answers only)")
    gripper: float | None = Field(None, description="the claw's opening as the simulated "
                                  "hardware holds it, 0 open .. 1 closed; null for a magnet "
                                  "(answers only)")


class HandMoveRequest(Model):
    """Move a simulated arm's joints as a hand moves an arm whose servos' torque is off (an
    addition to API.md's "Simulated world")."""

    positions: list[Finite] | None = Field(
        None, min_length=1, max_length=16, description="the joints' goal (rad or m, the arm's "
        "joint order), within its joint limits; absent: where they are (the hand takes hold "
        "of the arm, moving nothing: allowed with its torque on)")
    speed: Annotated[float, Field(gt=0.0, le=4.0, allow_inf_nan=False, strict=True)] = Field(
        0.5, description="rad/s or m/s on the joint with the longest way; every joint arrives "
        "together")
    wait: Bool = Field(False, description="answer when the hand has arrived (or let go)")


class HandState(Model):
    positions: list[float] = Field(description="the goal asked (rad or m)")
    speed: float
    moving: bool = Field(description="the hand is still on its way (false once arrived, or let "
                         "go: a joint's torque came on)")
