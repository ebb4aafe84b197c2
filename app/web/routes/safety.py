"""The safety envelope of an arm: keep-out zones, floor and speed override (app/safety/envelope.py).

Any viewer reads it; an instructor changes it. A change is applied at once, on the control
thread (one that tightens it is refused while the arm moves), and kept in the store
(app/store.py) across restarts; a store that cannot take it right now keeps it in memory and
retries, and the answer says `persisted: false`.
"""

from __future__ import annotations

import logging

from fastapi import APIRouter, Request
from pydantic import ValidationError

from app import schemas as s
from app.config import SafetySettings
from app.errors import InvalidRequest
from app.service import ArmService
from app.store import ARM_SCOPE, Store, StoreError
from app.web.deps import InstructorArm, ViewerArm, ViewerRole
from app.web.routes.common import READ, errors
from app.web.security import Role

log = logging.getLogger(__name__)

router = APIRouter(prefix="/arms/{arm}/safety", tags=["safety"])

KEY = "safety"


def _store(request: Request) -> Store | None:
    return getattr(request.app.state, "store", None)


def describe(svc: ArmService, store: Store | None, editable: bool) -> s.Safety:
    health = store.health() if store is not None else None
    if health is None or store is None:
        return svc.safety_view(False, "no store", 0, editable)
    # on disk when no setting waits: the audit log's own trouble (health.ok covers it too, and
    # its retry lands after this answer) is said in store_error, not as this setting unsaved
    return svc.safety_view(True, health.error, store.settings_pending(), editable)


def load_stored(svc: ArmService, store: Store) -> None:
    """At start-up: the instructor's last settings replace the profile's (PUT replaces)."""
    try:
        stored = store.get_setting_sync(ARM_SCOPE.format(svc.name), KEY)
        if stored is not None:
            svc.restore_safety(SafetySettings.model_validate(stored))
            cfg = svc.safety_settings
            log.info("%s: safety envelope from the store (%d zone(s), floor %s, speed %g)",
                     svc.name, len(cfg.zones), cfg.floor_z, cfg.speed_override)
    except (StoreError, ValidationError, ValueError) as exc:
        log.error("%s: stored safety settings not used (the profile's apply): %s",  # noqa: TRY400
                  svc.name, exc)


@router.get(
    "",
    response_model=s.Safety,
    summary="The arm's safety envelope",
    description="Keep-out boxes (base frame, m), the floor height, the speed override, the "
    "margins from the profile and the body points every motion is checked through. `editable` "
    "says whether the caller may change it.",
    responses=errors(*READ),
)
async def get_safety(svc: ViewerArm, role: ViewerRole, request: Request) -> s.Safety:
    return describe(svc, _store(request), role >= Role.INSTRUCTOR)


@router.put(
    "",
    response_model=s.Safety,
    summary="Change the arm's safety envelope (instructor)",
    description="Each field given replaces the current one; omitted fields are kept; "
    "`floor_z: null` removes the floor. Applies at once and is kept across restarts. A change "
    "that adds or moves a zone or raises the floor is refused with 409 `busy` while a motion "
    "runs or is queued or the arm moves (stop it first: the running plan was checked against "
    "the old envelope); removing a zone, lowering the floor and the speed override apply "
    "whatever the arm does (the override to motions planned after it). 422 `keep_out` if the "
    "arm is now inside a new zone or below the new floor, or its pending pass-through path "
    "enters it (move it out first: no motion could leave). 403 for an operator or viewer "
    "token. "
    "`persisted: false` when the database cannot take it right now (kept and retried; the "
    "reason is in /api/v1/health).",
    responses=errors(*READ, 403),
)
async def put_safety(svc: InstructorArm, req: s.SafetyUpdate, request: Request) -> s.Safety:
    cur = svc.safety_settings
    given = req.model_fields_set
    try:
        new = SafetySettings(
            zones=cur.zones if req.zones is None else req.zones,
            floor_z=req.floor_z if "floor_z" in given else cur.floor_z,
            speed_override=cur.speed_override if req.speed_override is None
            else req.speed_override)
    except ValidationError as exc:
        raise InvalidRequest("; ".join(str(e["msg"]) for e in exc.errors())) from None
    await svc.apply_safety(new)
    store = _store(request)
    if store is not None:
        await store.put_setting(ARM_SCOPE.format(svc.name), KEY, new.model_dump(mode="json"))
    svc.event("safety", zones=len(new.zones), floor_z=new.floor_z,
              speed_override=new.speed_override)
    log.info("%s: safety envelope changed: %d zone(s), floor %s, speed %g", svc.name,
             len(new.zones), new.floor_z, new.speed_override)
    return describe(svc, store, True)
