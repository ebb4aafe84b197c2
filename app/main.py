"""The app factory: routers, error handlers, middleware and the lifespan that runs the arms.

Errors: every error body is `{"detail": ..., "code": ...}`.

- `ArmError` (and subclasses): its own status and code.
- Validation: 422 `invalid_request` with pydantic's error list (JSON-safe: `ctx` values as
  strings, `input` dropped where it is not plain JSON, e.g. a NaN). Malformed JSON is 422
  `invalid_json` (one code for "the body is not JSON", same status as any other bad body).
- Starlette's 404/405: `not_found` / `method_not_allowed`.
- A body over `max_body_bytes`: 413 `too_large`, before the app reads it.
- Anything else is a bug: logged with its traceback, counted in `app.state.internal_errors`
  (tests assert it stays 0) and answered 502 `internal_error`, never a 500 (API.md).
"""

from __future__ import annotations

import json
import logging
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from pathlib import Path
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.middleware.cors import CORSMiddleware
from fastapi.responses import JSONResponse
from pydantic.json_schema import models_json_schema
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.routing import Match, Mount
from starlette.staticfiles import StaticFiles
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from app import schemas
from app.api import (
    arms,
    audit,
    classroom,
    force,
    homing,
    kinematics,
    lease,
    motion,
    safety,
    telemetry,
)
from app.arms import arm_routers
from app.audit import AuditLog
from app.auth import Access, bearer_token, install_log_redaction
from app.classroom import Classroom
from app.config import ArmProfile, Settings, load_arms
from app.control import ControlThread
from app.errors import ArmError, Unauthorized
from app.hostguard import HostOriginGuard
from app.lease import LeaseManager
from app.mqtt import start_mqtt_bridge
from app.service import ArmService
from app.store import Store

log = logging.getLogger("armserver")

API_PREFIX = "/api/v1"
STATIC_DIR = Path(__file__).parent / "static"


def create_app(settings: Settings | None = None,
               profiles: list[ArmProfile] | None = None) -> FastAPI:
    """The server for `profiles` (default: the arms of `settings.config`, else the two
    simulated arms). The arms start in the lifespan, not here."""
    settings = settings if settings is not None else Settings()
    profiles = profiles if profiles is not None else load_arms(settings.config)
    install_log_redaction()

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        services: dict[str, ArmService] = {}
        leases = LeaseManager(services, settings.lease_ttl_s)
        app.state.services = services
        app.state.leases = leases
        store = Store(settings.data_dir)
        app.state.store = store
        # The arms run on the control thread's loop (app.control); HTTP stays on this one.
        control = ControlThread() if settings.control_thread else None
        app.state.control = control
        if control is not None:
            control.start()
        room = Classroom(services, leases, store, settings.claim_s, settings.slot_s)
        app.state.classroom = room
        try:
            store.open()  # blocking, before anything is served; errors go to health
            for p in profiles:
                svc = ArmService(p)
                safety.load_stored(svc, store)
                services[p.name] = svc
                svc.hub.bind_fanout()
                await _on_control(control, svc.start())
                log.info("arm %s (%s) on %s link %s", p.name, p.model, p.link.kind,
                         svc.driver.link.address or "-")
            leases.start()
            app.state.mqtt = start_mqtt_bridge(settings, services)
            room.load()
            room.start()
            access: Access = app.state.access
            log.log(logging.INFO if access.enabled else logging.WARNING, "access: %s",
                    access.describe())
            yield
        finally:
            if getattr(app.state, "mqtt", None) is not None:
                await app.state.mqtt.close()
            await room.close()
            await leases.close()
            for svc in services.values():
                try:
                    await _on_control(control, svc.close())
                except Exception:  # close the other arms all the same
                    log.exception("%s: close failed", svc.name)
            store.close()
            if control is not None:
                control.stop()

    app = FastAPI(
        title="armserver",
        version="1.0.0",
        summary="REST and WebSocket API over RBE3001 (USB HID) and Dynamixel (serial) arms",
        description="SI units on the wire (m, rad, s, N, N m); raw device units only under the "
        "protocol pass-through routes, named so. Errors are `{detail, code}`.\n\n"
        "Telemetry (not listed below: OpenAPI has no WebSockets): "
        "`WS /api/v1/arms/{arm}/telemetry?rate=HZ` (token: `Authorization` header or "
        "`?token=`) sends `TelemetryMessage` batches every 1/rate s and `EventMessage`s as they "
        "come; close codes 4401 unauthorized, 4404 unknown arm, 1008 bad rate, 1009 message "
        "too big. A client may send `{\"rate\": HZ}`.",
        lifespan=lifespan,
    )
    app.state.settings = settings
    app.state.access = Access(settings)
    app.state.services = {}
    app.state.internal_errors = 0
    app.state.mqtt = None

    for r in (arms, motion, kinematics, lease, telemetry, safety, force, classroom, audit):
        app.include_router(r.router, prefix=API_PREFIX)
    for router in arm_routers():  # each arm type's pass-through routes (app/arms)
        app.include_router(router, prefix=API_PREFIX)
    arms.install_fast_paths(app, API_PREFIX)  # GET state from the encoded sample
    app.include_router(homing.router, prefix=API_PREFIX)  # faults and homing (v1.1)
    _document_websocket_messages(app)
    _install_error_handlers(app)

    app.add_middleware(BodyLimit, max_bytes=settings.max_body_bytes)
    app.add_middleware(TokenGate, access=app.state.access)
    app.add_middleware(HostOriginGuard, settings=settings)  # open servers: own Host, own Origin
    origins = [o.strip() for o in settings.cors_origins.split(",") if o.strip()]
    if origins:
        app.add_middleware(CORSMiddleware, allow_origins=origins, allow_methods=["*"],
                           allow_headers=["*"])
    # Outermost of our middleware: nothing below it escapes as a bare 500.
    app.add_middleware(InternalErrors, app_ref=app)
    # Outside it: every changing request's outcome, refusals and bugs included (app/audit.py).
    app.add_middleware(AuditLog, app_ref=app, access=app.state.access)

    if (STATIC_DIR / "index.html").is_file():
        app.router.routes.append(_Dashboard("/", StaticFiles(directory=STATIC_DIR, html=True),
                                            name="dashboard"))
    return app


async def _on_control(control: ControlThread | None, coro: Any) -> Any:
    """Await `coro` on the control thread's loop (or here, without a control thread)."""
    return await (control.run(coro) if control is not None else coro)


class _Dashboard(Mount):
    """The static dashboard at "/", never answering under /api (so the API keeps its own 404
    and 405 answers instead of the file server's)."""

    def matches(self, scope: Scope) -> tuple[Match, Scope]:
        if scope.get("path", "").startswith(API_PREFIX + "/") or scope["type"] != "http":
            return Match.NONE, {}
        return super().matches(scope)


def _document_websocket_messages(app: FastAPI) -> None:
    """Add the telemetry socket's message models to /openapi.json's components (OpenAPI
    describes no WebSockets, but clients generate models from the components)."""
    plain = app.openapi

    def openapi() -> dict[str, Any]:
        if app.openapi_schema:
            return app.openapi_schema
        spec = plain()
        _, top = models_json_schema([(schemas.TelemetryMessage, "serialization"),
                                     (schemas.EventMessage, "serialization")],
                                    ref_template="#/components/schemas/{model}")
        found = spec.setdefault("components", {}).setdefault("schemas", {})
        for name, schema in top.get("$defs", {}).items():
            found.setdefault(name, schema)
        app.openapi_schema = spec
        return spec

    app.openapi = openapi  # type: ignore[method-assign]


# ---------------------------------------------------------------- errors


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
    return _encodable(value) != value


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


def _install_error_handlers(app: FastAPI) -> None:
    @app.exception_handler(ArmError)
    async def arm_error(request: Request, exc: ArmError) -> JSONResponse:
        headers = {"WWW-Authenticate": "Bearer"} if isinstance(exc, Unauthorized) else None
        return JSONResponse(_body(exc.detail, exc.code), exc.status_code, headers=headers)

    @app.exception_handler(RequestValidationError)
    async def invalid(request: Request, exc: RequestValidationError) -> JSONResponse:
        errs = validation_errors(exc.errors())
        code = ("invalid_json" if any(e["type"] == "json_invalid" for e in errs)
                else "invalid_request")
        if _has_surrogate(errs):  # one short line, no traceback: the body says the rest
            log.warning("%s %s: 422 %s, the request carries a lone surrogate (not text)",
                        request.method, request.url.path, code)
        return JSONResponse(_body(errs, code), 422)

    @app.exception_handler(StarletteHTTPException)
    async def http_error(request: Request, exc: StarletteHTTPException) -> JSONResponse:
        code = _HTTP_CODES.get(exc.status_code, "http_error")
        detail = exc.detail if isinstance(exc.detail, str) else str(exc.detail)
        return JSONResponse(_body(detail, code), exc.status_code,
                            headers=getattr(exc, "headers", None))


class InternalErrors:
    """Last resort for bugs: log with traceback, count, answer 502 `internal_error` (if the
    response has not started). Fix the cause; tests assert the count stays 0."""

    def __init__(self, app: ASGIApp, app_ref: FastAPI) -> None:
        self.app = app
        self.ref = app_ref

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] not in ("http", "websocket"):
            await self.app(scope, receive, send)
            return
        started = False

        async def _send(message: Message) -> None:
            nonlocal started
            if message["type"] in ("http.response.start", "websocket.accept"):
                started = True
            await send(message)

        try:
            await self.app(scope, receive, _send)
        except Exception:
            self.ref.state.internal_errors += 1
            log.exception("internal error on %s %s", scope.get("method", "WS"), scope.get("path"))
            if scope["type"] == "http" and not started:
                body = json.dumps(_body("internal error (logged); please report it",
                                        "internal_error")).encode()
                await send({"type": "http.response.start", "status": 502,
                            "headers": [(b"content-type", b"application/json"),
                                        (b"content-length", str(len(body)).encode())]})
                await send({"type": "http.response.body", "body": body})


class BodyLimit:
    """413 `too_large` for a request body over `max_bytes`, declared or streamed. The body is
    read here (it is small by definition) and replayed to the app."""

    def __init__(self, app: ASGIApp, max_bytes: int) -> None:
        self.app = app
        self.max_bytes = max_bytes

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        declared = dict(scope.get("headers", ())).get(b"content-length")
        if declared is not None:
            try:
                if int(declared) > self.max_bytes:
                    await self._too_large(send)
                    return
            except ValueError:
                pass
        chunks: list[bytes] = []
        size = 0
        while True:
            message = await receive()
            if message["type"] != "http.request":  # disconnect: let the app see it
                chunks = []
                replay: Message | None = message
                break
            size += len(message.get("body", b""))
            if size > self.max_bytes:
                await self._too_large(send)
                return
            chunks.append(message.get("body", b""))
            if not message.get("more_body", False):
                replay = None
                break
        body = b"".join(chunks)
        sent = False

        async def _receive() -> Message:
            nonlocal sent
            if replay is not None:
                return replay
            if not sent:
                sent = True
                return {"type": "http.request", "body": body, "more_body": False}
            return await receive()

        await self.app(scope, _receive, send)

    async def _too_large(self, send: Send) -> None:
        body = json.dumps(_body(f"request body over {self.max_bytes} bytes",
                                "too_large")).encode()
        await send({"type": "http.response.start", "status": 413,
                    "headers": [(b"content-type", b"application/json"),
                                (b"content-length", str(len(body)).encode())]})
        await send({"type": "http.response.body", "body": body})


class TokenGate:
    """401 `unauthorized` for an API request with no valid token, before the body is read or
    parsed: without it a malformed body would answer 422 to a client that may not even ask.
    Roles (403) stay with the routes' dependencies; health, docs and the dashboard are open;
    WebSockets check their token (header or `?token=`) in their route."""

    def __init__(self, app: ASGIApp, access: Access) -> None:
        self.app = app
        self.access = access

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        path = scope.get("path", "")
        if (scope["type"] != "http" or not self.access.enabled or scope.get("method") == "OPTIONS"
                or not path.startswith(API_PREFIX + "/") or path == API_PREFIX + "/health"):
            await self.app(scope, receive, send)
            return
        header = dict(scope.get("headers", ())).get(b"authorization")
        token = bearer_token(header.decode("latin-1") if header is not None else None)
        if self.access.role_of(token) is not None:
            await self.app(scope, receive, send)
            return
        # the very answer the routes give (`Access.require` through the ArmError handler):
        # same detail, same serializer, same headers, byte for byte
        exc = Unauthorized("missing bearer token" if not token else "invalid bearer token")
        response = JSONResponse(_body(exc.detail, exc.code), exc.status_code,
                                headers={"WWW-Authenticate": "Bearer"})
        await response(scope, receive, send)


def cli() -> None:
    """Console entry point `armserver` (see app.cli)."""
    from app.cli import main

    raise SystemExit(main())

