"""The app factory: routers, error handlers, middleware and the lifespan that runs the arms.

Errors: every error body is `{"detail": ..., "code": ...}` (app/web/error_responses.py: the handlers
and the one writer). A body over `max_body_bytes` is 413 `too_large` before the app reads it;
anything else is a bug: logged with its traceback, counted in `app.state.internal_errors`
(tests assert it stays 0) and answered 502 `internal_error`, never a 500 (app/web/middleware.py).
The console entry point is app/cli.py's; this module never imports it.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from pathlib import Path
from typing import Any

from fastapi import FastAPI
from fastapi.middleware.cors import CORSMiddleware
from pydantic.json_schema import models_json_schema
from starlette.routing import Match, Mount
from starlette.staticfiles import StaticFiles
from starlette.types import Scope

from app import schemas
from app.arms import arm_fast_paths, arm_routers
from app.arms.loading import load_arms
from app.cameras.config import CameraConfig, load_cameras
from app.cameras.hub import CameraHub
from app.classroom.audit import AuditLog
from app.classroom.lease import LeaseManager
from app.classroom.queue import Classroom
from app.config import ArmProfile, Settings
from app.recording.feeds import open_recordings
from app.runtime.control_thread import ControlThread
from app.runtime.gc_policy import Collector, moving
from app.service import ArmService
from app.store import Store
from app.telemetry.mqtt import start_mqtt_bridge
from app.teleop.config import load_teleop
from app.web.error_responses import install_error_handlers
from app.web.hostguard import HostOriginGuard, HostPolicy
from app.web.middleware import API_PREFIX, BodyLimit, HeadAsGet, InternalErrors, TokenGate
from app.web.routes import (
    arms,
    audit,
    calibration,
    cameras,
    classroom,
    force,
    homing,
    kinematics,
    lease,
    motion,
    recordings,
    replay,
    safety,
    setup_servos,
    telemetry,
    teleop,
    torque,
    world,
)
from app.web.security import Access, install_log_redaction
from app.web.warm import warm_routes

log = logging.getLogger("armserver")

STATIC_DIR = Path(__file__).parent / "static"


def create_app(settings: Settings | None = None,
               profiles: list[ArmProfile] | None = None,
               camera_configs: list[CameraConfig] | None = None) -> FastAPI:
    """The server for `profiles` (default: the arms of `settings.config`, else the two
    simulated arms) and `camera_configs` (default: the config's `[[cameras]]`, else one
    simulated camera per simulated arm). The arms and cameras start in the lifespan."""
    settings = settings if settings is not None else Settings()
    config_profiles = profiles is None
    profiles = profiles if profiles is not None else load_arms(settings.config)
    if camera_configs is None:
        camera_configs = load_cameras(settings.config if config_profiles else None, profiles)
    # teleoperation's per-pair defaults ([[teleop]], app/teleop/config.py), checked at start
    teleop_pairs = load_teleop(settings.config if config_profiles else None, profiles)
    install_log_redaction()

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        services: dict[str, ArmService] = {}
        store = Store(settings.data_dir, audit_max_rows=settings.audit_max_rows)
        leases = LeaseManager(services, settings.lease_ttl_s, store)
        app.state.services = services
        app.state.leases = leases
        app.state.store = store
        # The arms run on the control thread's loop (app.runtime.control_thread); HTTP stays on
        # this one.
        control = ControlThread() if settings.control_thread else None
        app.state.control = control
        if control is not None:
            control.start()
        room = Classroom(services, leases, store, settings.claim_s, settings.slot_s)
        app.state.classroom = room
        # full GC pauses every thread (app/runtime/gc_policy.py)
        collector = Collector(moving(services))
        app.state.collector = collector
        try:
            store.open()  # blocking, before anything is served; errors go to health
            for p in profiles:
                svc = ArmService(p)
                safety.load_stored(svc, store)
                svc.keep_latch_in(store)  # a latch from before this start holds
                calibration.use_store(svc, store)  # found at connect, by hardware identity
                services[p.name] = svc
                svc.bind_fanout()
                await _on_control(control, svc.start())
                log.info("arm %s (%s) on %s link %s", p.name, p.model, p.link.kind,
                         svc.link_status().address or "-")
            leases.start()
            # cameras: a thread each, off the control thread and this loop (app/cameras)
            app.state.cameras = CameraHub(camera_configs, services, store)
            app.state.cameras.start(asyncio.get_running_loop())
            # datasets under the data folder (app/recording), after the arms and cameras
            app.state.recordings = await open_recordings(settings.data_dir, services,
                                                         app.state.cameras)
            app.state.mqtt = start_mqtt_bridge(settings, services)
            room.load(app.state.access.names)  # entries of names no token has: dropped
            leases.load(skip=room.queued_arms())  # a lease held when this process stopped
            room.start()
            # every route built now, not by its first request (an estop press: app/web/warm.py)
            if settings.warm_start:
                await warm_routes(app.router, API_PREFIX)
            collector.start(collect=settings.warm_start)  # after start-up: what exists is frozen
            access: Access = app.state.access
            log.log(logging.INFO if access.enabled else logging.WARNING, "access: %s",
                    access.describe())
            yield
        finally:
            if getattr(app.state, "recordings", None) is not None:  # an episode is written
                await app.state.recordings.close()
            if getattr(app.state, "teleop", None) is not None:  # the followers hold first
                await app.state.teleop.close()
            await collector.close()
            if getattr(app.state, "mqtt", None) is not None:
                await app.state.mqtt.close()
            await room.close()
            if getattr(app.state, "cameras", None) is not None:
                await app.state.cameras.close()
            await leases.close()
            for svc in services.values():
                try:
                    await _on_control(control, svc.close())
                except Exception:  # close the other arms all the same
                    log.exception("%s: close failed", svc.name)
            store.close()
            if getattr(app.state, "practice_bus", None) is not None:  # servo set-up's
                await asyncio.to_thread(app.state.practice_bus.close)
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
    app.state.teleop_pairs = teleop_pairs
    app.state.access = Access(settings)
    app.state.services = {}
    app.state.internal_errors = 0
    app.state.mqtt = None
    app.state.cameras = None

    for r in (arms, motion, kinematics, lease, telemetry, safety, force, classroom, audit,
              cameras, recordings):
        app.include_router(r.router, prefix=API_PREFIX)
    for router in arm_routers():  # each arm type's pass-through routes (app/arms)
        app.include_router(router, prefix=API_PREFIX)
    app.include_router(homing.router, prefix=API_PREFIX)  # faults and homing (v1.1)
    app.include_router(torque.router, prefix=API_PREFIX)  # the joints' torque (addition)
    app.include_router(calibration.router, prefix=API_PREFIX)  # joint calibration (v1.2)
    app.include_router(teleop.router, prefix=API_PREFIX)  # teleoperation (v1.2)
    app.include_router(replay.router, prefix=API_PREFIX)  # replay of recordings (v1.2)
    app.include_router(world.router, prefix=API_PREFIX)  # simulated world (v1.2)
    app.include_router(setup_servos.router, prefix=API_PREFIX)  # servo set-up (issue 24)
    _document_websocket_messages(app)
    install_error_handlers(app)

    for layer in arm_fast_paths():  # innermost, inside every gate (a goal's write: issue 23)
        app.add_middleware(layer, app_ref=app)
    app.add_middleware(BodyLimit, max_bytes=settings.max_body_bytes)
    app.add_middleware(TokenGate, access=app.state.access)
    hosts = HostPolicy(settings)  # one policy for the guard and the state fast path
    app.add_middleware(HostOriginGuard, policy=hosts)  # open servers: own Host, own Origin
    origins = [o.strip() for o in settings.cors_origins.split(",") if o.strip()]
    if origins:
        app.add_middleware(CORSMiddleware, allow_origins=origins, allow_methods=["*"],
                           allow_headers=["*"])
    # Outermost of our middleware: nothing below it escapes as a bare 500.
    app.add_middleware(InternalErrors, app_ref=app)
    # Outside it: every changing request's outcome, refusals and bugs included
    # (app/classroom/audit.py).
    app.add_middleware(AuditLog, app_ref=app, access=app.state.access)
    # GET state from the bytes encoded at publish time (app/web/routes/arms.py), outside the rest.
    arms.install_fast_paths(app, API_PREFIX, hosts)
    # Outermost: HEAD as GET without the body (a GET state's fast path included).
    app.add_middleware(HeadAsGet)

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

    app.openapi = openapi  # type: ignore[method-assign]  # FastAPI's documented override
