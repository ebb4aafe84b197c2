"""GET /audit: the audit log, newest first, JSON or CSV (instructor; app/classroom/audit.py
records).

The CSV is for spreadsheets, which run a cell that starts with `=`, `+`, `-`, `@`, a tab or a
carriage return as a formula: such a cell is written with a leading `'` (OWASP's rule for CSV
injection), so `=HYPERLINK(...)` in any column is text. The JSON is as recorded.
"""

from __future__ import annotations

import csv
import io
from typing import Annotated

from fastapi import APIRouter, Header, Query, Request, Response

from app import schemas as s
from app.errors import StoreUnavailable
from app.store import AUDIT_COLUMNS, Store, StoreError
from app.web.deps import InstructorCaller
from app.web.routes.common import errors

router = APIRouter(tags=["audit"])

#: A cell starting with one of these is a formula to a spreadsheet.
FORMULA_START = ("=", "+", "-", "@", "\t", "\r")


def csv_cell(value: object) -> str:
    """A value as a CSV cell a spreadsheet shows as text: None is empty, a formula is quoted."""
    text = "" if value is None else str(value)
    return "'" + text if text.startswith(FORMULA_START) else text


@router.get("/audit", response_model=list[s.AuditRecord], summary="The audit log",
            description="Instructor token. Records of every changing request, newest first, "
            "filtered by arm, caller name (`who`) and Unix time (`since`, `until`). A request "
            "is recorded when it starts (`status` null) and completed when it ends; refusals "
            "by the gates are counted per address and reason (`kind: refusals`, `count`). "
            "`Accept: text/csv` answers CSV with a header row, formula cells quoted with a "
            "leading `'`. 503 `store_unavailable` when the database cannot be read (records "
            "not yet written are kept and retried).",
            responses={**errors(401, 403, 422, 503),
                       200: {"content": {"text/csv": {}}, "description": "records"}})
async def audit(
    _: InstructorCaller,
    request: Request,
    arm: Annotated[str | None, Query(max_length=64)] = None,
    who: Annotated[str | None, Query(max_length=64)] = None,
    since: Annotated[float | None, Query(allow_inf_nan=False)] = None,
    until: Annotated[float | None, Query(allow_inf_nan=False)] = None,
    limit: Annotated[int, Query(ge=1, le=10_000)] = 100,
    accept: Annotated[str | None, Header(max_length=256)] = None,
) -> Response | list[s.AuditRecord]:
    store: Store | None = getattr(request.app.state, "store", None)
    if store is None:
        raise StoreUnavailable("this server has no store")
    try:
        rows = await store.query_audit(arm=arm, who=who, since=since, until=until, limit=limit)
    except StoreError as exc:
        raise StoreUnavailable(f"the audit log cannot be read: {exc}") from exc
    if accept is not None and "text/csv" in accept:
        out = io.StringIO()
        writer = csv.writer(out)
        writer.writerow(AUDIT_COLUMNS)
        for r in rows:
            writer.writerow([csv_cell(r[c]) for c in AUDIT_COLUMNS])
        return Response(out.getvalue(), media_type="text/csv; charset=utf-8")
    return [s.AuditRecord(**r) for r in rows]
