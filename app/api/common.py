"""Shared pieces of the routers: the documented error responses, and input checks that turn
shape mistakes into the contract's 422 before anything reaches the planner or a device."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

from app.errors import InvalidRequest
from app.schemas import ErrorBody
from app.service import ArmService

_WHY = {
    400: "bad request",
    401: "missing or invalid bearer token (`unauthorized`)",
    403: "a viewer token where an operator token is needed (`forbidden`)",
    404: "unknown arm (`unknown_arm`) or resource",
    409: "conflict: `estop_latched`, `leased`, `busy`, `not_supported`, `no_gripper`",
    413: "request body too large (`too_large`)",
    422: "invalid request (`invalid_request`, `invalid_json`) or refused by a check "
         "(`joint_limit`, `unreachable`, `velocity_limit`)",
    502: "the device answered with an error (`device_error`, `corrupt_reply`)",
    503: "the link is down (`link_down`) or the request queue is full (`busy`)",
    504: "the device did not answer in time (`device_timeout`)",
}

#: Errors any authenticated arm route may answer.
READ = (401, 404, 422)
#: ... and a route that talks to the device.
DEVICE = (401, 403, 404, 409, 422, 502, 503, 504)


def errors(*statuses: int, extra: dict[int, str] | None = None) -> dict[int | str, dict[str, Any]]:
    """OpenAPI `responses` entries, each an `ErrorBody`."""
    out: dict[int | str, dict[str, Any]] = {}
    for st in sorted(set(statuses) | set(extra or {})):
        out[st] = {"model": ErrorBody, "description": (extra or {}).get(st, _WHY.get(st, ""))}
    return out


def check_joint_count(svc: ArmService, positions: Sequence[float]) -> None:
    n = svc.model.n
    if len(positions) != n:
        raise InvalidRequest(f"{svc.name} has {n} joints ({', '.join(svc.model.names)}); "
                             f"got {len(positions)} positions")


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
