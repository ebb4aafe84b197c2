"""The error table (`app.errors.CODES`) against everything that says an error code.

- each row: a server exception carrying that code with the row's status, a client class;
- OpenAPI: every answered code is in the `ErrorBody.code` enum, and every error status a route
  documents is described by exactly the table's codes for that status (a `busy` under 503 while
  the table and every raise say 409 fails here);
- the source: an ast walk over app/ finds every code literal (`code=` keywords, `code = ...`
  assignments, `{"code": ...}` bodies, the raw ASGI layers' refusals, motion failures) and
  every exception class; each code must be in the table with the same status, and every
  exception class must live in app/errors.py. The walker is tested on a planted bad snippet.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

import httpx
import pytest

from app import errors
from app.client import errors as client_errors
from app.client.core import WS_CLOSE
from app.web.factory import create_app

ROOT = Path(__file__).resolve().parents[1]
APP = ROOT / "app"
#: Helpers that take a code positionally: name -> (index of the code, of the status or None).
#: (`error_response` / `send_error`: the one JSON error writer `core` is moving the raw ASGI
#: layers to.)
CODE_ARG: dict[str, tuple[int, int | None]] = {
    "_body": (1, None), "_refuse": (4, 3), "_finish": (3, None), "error_response": (1, 2),
    "send_error": (3, 1),
}
#: The client's own codes (no server answer carries them).
CLIENT_ONLY = {"connection_failed", "turn_lost"}
SERVER_CLASSES = {name for name, obj in vars(errors).items()
                  if isinstance(obj, type) and issubclass(obj, errors.ArmError)}


# ---------------------------------------------------------------- the table itself


@pytest.mark.parametrize("row", list(errors.CODES.values()), ids=lambda r: r.code)
def test_each_code_has_its_server_class_status_and_client_class(row: errors.ErrorCode) -> None:
    cls = getattr(errors, row.exception)
    assert issubclass(cls, errors.ArmError) and cls.code == row.code
    if row.status is not None:
        assert cls.status_code == row.status
        assert 400 <= row.status < 600
        exc = cls("why")
        assert (exc.code, exc.status_code, exc.detail) == (row.code, row.status, "why")
    assert row.meaning and row.meaning == row.meaning.strip()
    client_cls = getattr(client_errors, row.client)
    assert client_errors.ERRORS[row.code] is client_cls
    made = client_errors.make_error(row.code, "why", row.status or 0)
    assert type(made) is client_cls and made.code == row.code


def test_each_server_class_is_one_row() -> None:
    by_class = {row.exception: row for row in errors.CODES.values()}
    for name in SERVER_CLASSES - {"ArmError"}:
        assert name in by_class, f"app.errors.{name} is not named by a row of the table"
        assert getattr(errors, name).code == by_class[name].code


def test_a_class_with_a_code_outside_the_table_fails_at_definition() -> None:
    with pytest.raises(TypeError, match="not in app.errors.CODES"):
        type("Invented", (errors.Conflict,), {"code": "invented_here"})


def test_a_code_given_at_raise_time_takes_the_table_status() -> None:
    exc = errors.ArmError("closing", code="shutting_down")
    assert (exc.code, exc.status_code) == ("shutting_down", 503)
    assert errors.NotSupported("x", code="no_force_sensing").status_code == 409


def test_busy_is_409_and_nothing_else_is_named_busy() -> None:
    assert errors.CODES["busy"].status == 409
    assert not hasattr(errors, "QueueFull")
    assert "busy" not in errors.describe(503)


def test_client_maps_the_table_and_only_its_own_codes_besides() -> None:
    assert set(client_errors.ERRORS) - set(errors.CODES) == CLIENT_ONLY
    for code, status in WS_CLOSE.values():
        assert errors.CODES[code].status == status, code
    for status, code in client_errors.STATUS_CODES.items():
        assert errors.CODES[code].status == status, code


def test_client_error_without_a_known_code_is_the_base_class() -> None:
    exc = client_errors.error_from_body(409, b'{"code": "no_such_code", "detail": "d"}')
    assert type(exc) is client_errors.ArmServerError and exc.code == "no_such_code"
    gone = client_errors.error_from_body(410, b'{"code": "motion_expired", "detail": "old"}')
    assert isinstance(gone, client_errors.Gone) and isinstance(gone, client_errors.NotFound)


# ---------------------------------------------------------------- OpenAPI


def _spec() -> dict[str, object]:
    return create_app().openapi()


def test_every_answered_code_is_in_the_openapi_error_body() -> None:
    spec = _spec()
    body = spec["components"]["schemas"]["ErrorBody"]["properties"]["code"]  # type: ignore[index]
    answered = [c for c, r in errors.CODES.items() if r.status is not None]
    assert body["enum"] == answered
    for code in answered:
        assert f"`{code}` ({errors.CODES[code].status})" in body["description"]


def test_each_documented_error_status_lists_the_table_codes_of_that_status() -> None:
    spec = _spec()
    seen = 0
    for path, ops in spec["paths"].items():  # type: ignore[attr-defined]
        for method, op in ops.items():
            for status, resp in op["responses"].items():
                if int(status) < 400:
                    continue
                seen += 1
                named = set(re.findall(r"`([a-z_]+)`", resp["description"]))
                assert named, (method, path, status, resp["description"])
                for code in named:
                    assert code in errors.CODES, (method, path, status, code)
                    assert errors.CODES[code].status == int(status), (
                        f"{method} {path}: {status} documents `{code}`, which the table "
                        f"answers with {errors.CODES[code].status}")
    assert seen > 100


async def test_a_refused_request_answers_its_table_code_and_the_client_class() -> None:
    transport = httpx.ASGITransport(app=create_app())
    async with httpx.AsyncClient(transport=transport, base_url="http://foreign.example") as http:
        r = await http.get("/api/v1/arms/nosucharm/state")  # the raw host guard refuses it
    assert r.status_code == 400 and r.json()["code"] == "bad_host"
    exc = client_errors.error_from_body(r.status_code, r.content)
    assert isinstance(exc, client_errors.BadRequest) and exc.status == 400
    async with httpx.AsyncClient(transport=transport, base_url="http://127.0.0.1") as http:
        r = await http.get("/api/v1/arms/nosucharm/state")  # a route raises UnknownArm
    assert r.status_code == 404 and r.json()["code"] == "unknown_arm"
    exc = client_errors.error_from_body(r.status_code, r.content)
    assert isinstance(exc, client_errors.NotFound) and exc.status == 404


# ---------------------------------------------------------------- the source


def _str_consts(node: ast.AST) -> list[str]:
    """The strings an expression may evaluate to: a literal, or either branch of `a if c else
    b` / `a or b` (not strings used inside a call, such as `.get("code")`)."""
    if isinstance(node, ast.Constant):
        return [node.value] if isinstance(node.value, str) else []
    if isinstance(node, ast.IfExp):
        return _str_consts(node.body) + _str_consts(node.orelse)
    if isinstance(node, ast.BoolOp):
        return [c for v in node.values for c in _str_consts(v)]
    return []


def _int_const(node: ast.AST | None) -> int | None:
    if isinstance(node, ast.Constant) and isinstance(node.value, int):
        return node.value
    return None


def _name(node: ast.AST) -> str:
    if isinstance(node, ast.Name):
        return node.id
    if isinstance(node, ast.Attribute):
        return node.attr
    return ""


def problems(source: str, where: str, in_errors_module: bool = False) -> list[str]:
    """Every code literal of `source` not in the table (or with another status), every
    exception class defined outside app/errors.py, every bare `ArmError(...)` without a code."""
    out: list[str] = []

    def check(code: str, status: int | None, line: int) -> None:
        row = errors.CODES.get(code)
        if row is None:
            out.append(f"{where}:{line}: code {code!r} is not in app.errors.CODES")
        elif status is not None and row.status != status:
            out.append(f"{where}:{line}: {code!r} answered {status}, the table says {row.status}")

    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.ClassDef) and not in_errors_module and any(
                _name(b) in SERVER_CLASSES for b in node.bases):
            out.append(f"{where}:{node.lineno}: exception class {node.name} outside app/errors.py")
        elif isinstance(node, ast.Call):
            kw = {k.arg: k.value for k in node.keywords if k.arg}
            if "code" in kw:
                for code in _str_consts(kw["code"]):
                    check(code, _int_const(kw.get("status_code")), node.lineno)
            elif _name(node.func) == "ArmError":
                out.append(f"{where}:{node.lineno}: ArmError(...) without a code")
            where_code = CODE_ARG.get(_name(node.func))
            if where_code is not None and len(node.args) > where_code[0]:
                index, at = where_code
                status = _int_const(node.args[at]) if at is not None else None
                for code in _str_consts(node.args[index]):
                    check(code, status, node.lineno)
        elif isinstance(node, ast.Dict):
            for key, value in zip(node.keys, node.values):
                if isinstance(key, ast.Constant) and key.value == "code" and value is not None:
                    for code in _str_consts(value):
                        check(code, None, node.lineno)
        elif isinstance(node, ast.Assign | ast.AnnAssign):
            targets = node.targets if isinstance(node, ast.Assign) else [node.target]
            names = {_name(t) for t in targets}
            if node.value is not None and ("code" in names or any(
                    n.isupper() and n.endswith("CODES") for n in names)):
                values = (node.value.values if isinstance(node.value, ast.Dict)
                          else [node.value])
                for v in values:
                    for code in _str_consts(v):
                        check(code, None, node.lineno)
    return out


def _server_sources() -> list[Path]:
    return sorted(p for p in APP.rglob("*.py")
                  if not p.relative_to(APP).parts[0].startswith("client"))


def test_the_walker_finds_a_planted_invented_code() -> None:
    planted = '''
class Mine(Conflict):
    code = "mine"
def f():
    raise InvalidRequest("x", code="made_up")
def g():
    raise ArmError("bare")
def h():
    raise ArmError("x", code="busy", status_code=503)
BODY = {"detail": "d", "code": "nope"}
async def i(send):
    await _refuse(None, None, send, 400, "not_a_code", "d")
    await send_error(send, 400, "too big", "too_large")
    return error_response("d", "bad_host", 400)
'''
    found = problems(planted, "planted.py")
    assert len(found) == 8, found
    assert any("'too_large' answered 400, the table says 413" in p for p in found)
    assert any("'made_up'" in p for p in found) and any("'nope'" in p for p in found)
    assert any("'mine'" in p for p in found)
    assert any("answered 503" in p for p in found) and any("Mine" in p for p in found)
    assert any("without a code" in p for p in found) and any("'not_a_code'" in p for p in found)


def test_no_source_file_says_a_code_outside_the_table() -> None:
    sources = _server_sources()
    assert len(sources) > 30 and APP / "arms" / "dynamixel" / "api.py" in sources
    found: list[str] = []
    for path in sources:
        rel = str(path.relative_to(ROOT))
        found += problems(path.read_text(), rel, in_errors_module=rel == "app/errors.py")
    assert not found, "\n".join(found)
