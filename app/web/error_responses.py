"""The JSON error answers: every error body is `{"detail": ..., "code": ...}`.

- `ArmError` (and subclasses): its own status and code.
- Validation: 422 `invalid_request` with pydantic's error list (JSON-safe: `ctx` values as
  strings, `input` dropped where it is not plain JSON, e.g. a NaN). Malformed JSON is 422
  `invalid_json` (one code for "the body is not JSON", same status as any other bad body).
- Starlette's 404/405: `not_found` / `method_not_allowed`.

`send_error` writes the same answer on a raw ASGI `send` (the middlewares of app/web/middleware.py
and app/web/hostguard.py), byte for byte what the handlers' JSONResponse sends.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Mapping
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.types import Send

from app.errors import ArmError, Unauthorized

log = logging.getLogger("armserver")


def error_response(detail: Any, code: str, status: int,
                   headers: Mapping[str, str] | None = None) -> JSONResponse:
    """The JSON error response every path answers with."""
    return JSONResponse(_body(detail, code), status, headers=headers)


def arm_error_response(exc: ArmError) -> JSONResponse:
    """The answer to an `ArmError`: its status and code (401 with `WWW-Authenticate`). The
    app's handler and the layers that answer below no handler (app/arms/dynamixel/api.py's
    goal) both use it."""
    headers = {"WWW-Authenticate": "Bearer"} if isinstance(exc, Unauthorized) else None
    return error_response(exc.detail, exc.code, exc.status_code, headers)


async def send_error(send: Send, status: int, detail: Any, code: str,
                     headers: Mapping[str, str] | None = None) -> None:
    """Write `error_response(...)` on a raw ASGI `send` (an HTTP response not yet started)."""
    response = error_response(detail, code, status, headers)
    await send({"type": "http.response.start", "status": response.status_code,
                "headers": response.raw_headers})
    await send({"type": "http.response.body", "body": response.body})


def _body(detail: Any, code: str) -> dict[str, Any]:
    return {"detail": _encodable(detail), "code": code}


def _encodable(value: Any) -> Any:
    """`value` with every string made UTF-8 encodable: a lone surrogate (JSON `"\\ud800"`,
    valid JSON but not text) is shown as the escape `\\ud800`, so echoing a client's input
    back in an error body cannot fail to encode (that was a 502 with a traceback)."""
    if isinstance(value, str):
        try:
            value.encode("utf-8")
        except UnicodeEncodeError:
            return value.encode("utf-8", "backslashreplace").decode("utf-8")
        return value
    if isinstance(value, dict):
        return {_encodable(k): _encodable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_encodable(v) for v in value]
    return value


def _has_surrogate(value: Any) -> bool:
    return bool(_encodable(value) != value)


def _json_safe(value: Any) -> bool:
    try:
        json.dumps(value, allow_nan=False)
    except (TypeError, ValueError):
        return False
    return True


def validation_errors(errors: Any) -> list[dict[str, Any]]:
    """Pydantic's errors, made JSON-safe: ctx values as strings, unsafe inputs dropped."""
    out = []
    for e in errors:
        item: dict[str, Any] = {"type": e.get("type"), "loc": list(e.get("loc", ())),
                                "msg": e.get("msg")}
        if "ctx" in e:
            item["ctx"] = {k: v if isinstance(v, (int, str)) and not isinstance(v, bool)
                           else str(v) for k, v in e["ctx"].items()}
        if "input" in e and _json_safe(e["input"]) and len(repr(e["input"])) <= 256:
            item["input"] = e["input"]
        out.append(item)
    return out


_HTTP_CODES = {400: "bad_request", 404: "not_found", 405: "method_not_allowed",
               413: "too_large", 415: "unsupported_media_type"}


def install_error_handlers(app: FastAPI) -> None:
    @app.exception_handler(ArmError)
    async def arm_error(request: Request, exc: ArmError) -> JSONResponse:
        return arm_error_response(exc)

    @app.exception_handler(RequestValidationError)
    async def invalid(request: Request, exc: RequestValidationError) -> JSONResponse:
        errs = validation_errors(exc.errors())
        code = ("invalid_json" if any(e["type"] == "json_invalid" for e in errs)
                else "invalid_request")
        if _has_surrogate(errs):  # one short line, no traceback: the body says the rest
            log.warning("%s %s: 422 %s, the request carries a lone surrogate (not text)",
                        request.method, request.url.path, code)
        return error_response(errs, code, 422)

    @app.exception_handler(StarletteHTTPException)
    async def http_error(request: Request, exc: StarletteHTTPException) -> JSONResponse:
        code = _HTTP_CODES.get(exc.status_code, "http_error")
        detail = exc.detail if isinstance(exc.detail, str) else str(exc.detail)
        return error_response(detail, code, exc.status_code, getattr(exc, "headers", None))
