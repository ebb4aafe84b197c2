"""Shared pieces of the routers: the documented error responses, and input checks that turn
shape mistakes into the contract's 422 before anything reaches the planner or a device."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

from fastapi import Response, status

from app.errors import InvalidRequest, describe
from app.motion.executor import MotionRecord
from app.schemas import ErrorBody, Motion
from app.service import ArmService

#: Errors any authenticated arm route may answer.
READ = (401, 404, 422)
#: ... and a route that talks to the device.
DEVICE = (401, 403, 404, 409, 422, 502, 503, 504)


def errors(*statuses: int, extra: dict[int, str] | None = None) -> dict[int | str, dict[str, Any]]:
    """OpenAPI `responses` entries, each an `ErrorBody` described by the codes the error table
    (`app.errors.CODES`) gives its status; `extra` replaces a status's description."""
    out: dict[int | str, dict[str, Any]] = {}
    for st in sorted(set(statuses) | set(extra or {})):
        out[st] = {"model": ErrorBody, "description": (extra or {}).get(st) or describe(st)}
    return out


async def motion_answer(record: MotionRecord, wait: bool, response: Response) -> Motion:
    """A route that starts a motion: 202 with it now, or (`wait`) 200 with its final state when
    it ends."""
    if wait:
        await record.wait()
        response.status_code = status.HTTP_200_OK
    return record.to_schema()


def check_joint_count(svc: ArmService, positions: Sequence[float]) -> None:
    svc.model.joint_vector(positions)


def finite(values: Any, what: str) -> None:
    """Refuse results that overflowed (huge but finite inputs) rather than answer inf/NaN."""
    for v in _flat(values):
        if not math.isfinite(v):
            raise InvalidRequest(f"{what} is not finite for these inputs (values too large)")


def _flat(values: Any) -> list[float]:
    try:
        return [float(x) for x in values.ravel()]  # numpy
    except AttributeError:
        out: list[float] = []
        for v in values:
            out.extend(_flat(v) if isinstance(v, (list, tuple)) else [float(v)])
        return out
