"""The lease, the classroom (people, queue, audit) and the safety envelope."""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import Field

from app.config import KeepOutBox
from app.schemas.common import Model

# ---------------------------------------------------------------- lease


class Lease(Model):
    id: str
    arm: str
    expires: float = Field(description="Unix time the lease lapses unless renewed")
    ttl: float


# ---------------------------------------------------------------- classroom: people, queue, audit


class Me(Model):
    name: str = Field(description="the caller's name (never the token)")
    role: Literal["viewer", "operator", "instructor"]


class QueueEntry(Model):
    id: str
    arm: str
    name: str
    position: int | None = Field(None, description="1 = next; 0 = offered or holding; None "
                                 "once ended")
    status: Literal["waiting", "offered", "holding", "done", "expired"]
    created: float
    lease_id: str | None = Field(None, description="the offered lease's id, for its owner only: "
                                 "renew it (PUT /lease/{id}) within the claim window to hold it")
    offered_until: float | None = Field(None, description="Unix time the offer passes on")
    started: float | None = None
    slot_end: float | None = Field(None, description="Unix time the slot ends, renewed or not")
    ended: float | None = None
    reason: str | None = None


class QueueStatus(Model):
    arm: str
    holder: str | None = Field(None, description="who holds the arm's lease now")
    slot_left: float | None = Field(None, description="seconds left in the holder's slot")
    entries: list[QueueEntry] = Field(description="the current (offered or holding) entry "
                                      "first, then the waiting ones in order")
    handing_off: bool
    blocked: str | None = Field(None, description="why the last hand-off failed (the arm is "
                                "left with nobody until an instructor's DELETE /lease)")
    last_handoff: dict[str, Any] | None = None
    claim_s: float
    slot_s: float


class QueueOrder(Model):
    order: list[Annotated[str, Field(max_length=64)]] = Field(
        max_length=1000, description="every waiting entry's id, in the new order")


class AuditRecord(Model):
    """One record of the audit log (README "Reading the log")."""

    time: float = Field(description="Unix time the request started (for `refusals`: the "
                        "first refused one; for `dropped`: the first lost record)")
    name: str
    role: str
    arm: str | None = Field(description="the arm named in the route, when it is one of the "
                            "server's arms")
    method: str
    route: str = Field(description="the route (for `refusals`: the first refused one's)")
    summary: str
    status: int | None = Field(description="the answer's status; null while the request runs "
                               "(and for good if the server died under it: code "
                               "`interrupted`)")
    code: str | None
    kind: Literal["request", "refusals", "dropped"] = Field(
        "request", description="`request`: one request; `refusals`: requests refused by the "
        "gates (400 bad_host, 401, 403, 404 not_found or unknown_arm, 405, 413) from one "
        "address for one reason, counted over an interval; `dropped`: records lost while the "
        "database refused writes")
    count: int = Field(1, description="requests (or lost records) this record stands for")
    ended: float | None = Field(None, description="Unix time the request ended (for "
                                "`refusals` and `dropped`: the last one); null while it runs")
    address: str | None = Field(None, description="the client's IP address")


# ---------------------------------------------------------------- safety envelope


class SafetyUpdate(Model):
    """A change of an arm's safety envelope: each field given replaces the current one, each
    omitted keeps it (`floor_z: null` removes the floor)."""

    zones: list[KeepOutBox] | None = Field(None, max_length=32)
    floor_z: Annotated[
        float, Field(ge=-10.0, le=10.0, allow_inf_nan=False, strict=True)] | None = None
    speed_override: Annotated[
        float, Field(ge=0.05, le=1.0, allow_inf_nan=False, strict=True)] | None = None


class Safety(Model):
    zones: list[KeepOutBox]
    floor_z: float | None = Field(description="no body point below this height, m")
    speed_override: float = Field(description="0.05..1: scales every planned limit")
    tool_margin: float = Field(description="zones and floor grown by this for the tip, m "
                               "(profile)")
    body_margin: float = Field(description="the same for the other body points, m (profile)")
    body_points: list[str] = Field(description="the points checked: every joint origin and "
                                   "the tip")
    source: Literal["profile", "stored"]
    persisted: bool = Field(description="false while a change waits for the database")
    editable: bool = Field(description="whether the caller may change it (instructor)")
    store_error: str | None = None
