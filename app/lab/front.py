"""The lab's front: one ASGI app on the public address that hands each request to the worker
process owning its arm (app/lab/supervisor.py) and answers the lab-wide endpoints for all.

- `/api/v1/arms/{arm}` and everything under it (HTTP, and the telemetry WebSocket through
  app/lab/ws_relay.py) go to the arm's worker, headers and body as they came: the worker checks
  the token, the Host and Origin, the lease and every limit exactly as a single server does,
  so access and leases are today's (a lease lives in the worker that owns its arm).
- `GET /api/v1/arms` and `GET /api/v1/health` ask every ready worker (with the caller's
  headers) and merge their answers in config order; an arm whose worker is down or restarting
  shows in health as link `down` with the reason (and health says `degraded`), and in the
  list with its last known summary (or its profile's), link `down`. Where no worker answers
  (none ready, or none of those that are) the front checks the caller as a worker would (the
  Host rule, a viewer's token) and answers the lists itself, every arm and camera down.
- `/api/v1/cameras/{cam}/...` goes to the worker of the camera's arm, and `GET
  /api/v1/cameras` is merged like the arms.
- Teleoperation and recordings go where the arms they name live (app/lab/across.py): a
  session to its follower's worker, a recording to its arms' (409 `different_workers` across
  workers); their lists are merged, a session's stop asks each worker until one has it.
- Everything else (`/api/v1/me`, the audit log, which every worker reads from the one store in
  ARMSERVER_DATA_DIR, the dashboard, `/openapi.json`, an unknown arm's 404) goes to the first
  ready worker: each serves the same routes and tokens.
- A request for an arm whose worker is down is 503 `link_down` ("the server cannot talk to
  the arm now"), as is any other request when no worker is ready. An estop press so refused is kept
  and sent to the worker as it comes back, before any other request (app/lab/supervisor.py
  `Worker.keep_press`) and written to the lab's store as the arm's latch, which the worker
  reads as it starts: the arm comes back latched however long its worker takes and whether or
  not the front restarts meanwhile, as an arm whose link is down on a single server is
  latched by a press.

Why a front in the project and not nginx or Caddy: the two lab-wide lists are merges of the
workers' answers, which a reverse proxy cannot make without a program of its own beside it;
and a proxy's health checks would not know which arm lives where. The front costs one more hop
on loopback, over a Unix socket with kept-alive connections (app/lab/upstream.py: a general
HTTP client cost about 1 ms of Python a request there); bench/lab.py measures it.
"""

from __future__ import annotations

import asyncio
import json
import logging
from typing import Any

from starlette.types import Receive, Scope, Send

from app.arms import describe
from app.cameras.config import CameraConfig
from app.config import Settings
from app.errors import ArmError, DifferentWorkers
from app.lab.across import RECORDINGS, TELEOP, Across, handles
from app.lab.headers import HOP, credentials, forwarded_headers
from app.lab.placement import LabPlan
from app.lab.supervisor import Supervisor, Worker
from app.lab.upstream import UpstreamError, UpstreamResponse
from app.lab.ws_relay import relay_websocket
from app.store import CALIBRATION_KEY, CAMERA_SCOPE, Store, StoreError, saved_within
from app.web.error_responses import arm_error_response
from app.web.hostguard import REFUSALS, HostPolicy
from app.web.middleware import API_PREFIX
from app.web.security import Access, Role, bearer_token_of

log = logging.getLogger("armserver.lab")

ARMS = API_PREFIX + "/arms"
CAMERAS = API_PREFIX + "/cameras"
HEALTH = API_PREFIX + "/health"
#: A worker's response headers the front writes itself: uvicorn puts Date and Server on every
#: answer it sends, so a worker's are dropped (passed on, each answer had two of each; Date is
#: one field line, RFC 9110 6.6.1).
FRONT_OWN = frozenset({b"date", b"server"})
#: Response headers a relayed answer keeps but these (its bytes pass as they came, framing too).
HOP_STREAM = FRONT_OWN | {b"connection", b"keep-alive", b"transfer-encoding", b"te", b"trailer",
                          b"upgrade"}
#: Response headers of an answer read whole that the front does not pass back (it sets the
#: length).
HOP_WHOLE = HOP | FRONT_OWN
#: ... and of one it reads decoded (it frames the body itself).
HOP_BACK = HOP_WHOLE | {b"content-encoding"}


#: An HTTP answer: status, headers, body.
Answer = tuple[int, list[tuple[bytes, bytes]], bytes]


def _json_response(status: int, body: Any,
                   headers: list[tuple[bytes, bytes]] | None = None) -> Answer:
    data = json.dumps(body, separators=(",", ":")).encode()
    return status, [(b"content-type", b"application/json"), *(headers or [])], data


#: How long a forwarded request may wait for its answer's head, s: a `wait: true` move answers
#: when the motion ends.
REQUEST_TIMEOUT_S = 600.0
#: How long a lab-wide list waits for each worker, s.
ASK_TIMEOUT_S = 10.0
#: An answer whose head gives a length up to this many bytes is read whole and sent in one
#: piece (every JSON answer); a longer one, or one of no stated length (an MJPEG stream,
#: chunked), is relayed chunk by chunk as it comes, until the client goes.
WHOLE_BODY = 256 * 1024


async def _relay_body(r: UpstreamResponse, send: Send) -> None:
    try:
        async for chunk in r.chunks():
            await send({"type": "http.response.body", "body": chunk, "more_body": True})
    except UpstreamError as exc:  # the worker went away mid-answer: end what was sent
        log.warning("a relayed answer broke off: %r", exc)
    await send({"type": "http.response.body", "body": b"", "more_body": False})


async def _disconnected(receive: Receive) -> None:
    """Until the client goes (after the body, `receive` waits for exactly that)."""
    while (await receive())["type"] != "http.disconnect":
        pass


def _target(scope: Scope) -> str:
    """The request's target (path and query) as the client sent it."""
    url = scope.get("raw_path") or scope["path"].encode()
    if scope.get("query_string"):
        url += b"?" + scope["query_string"]
    return str(url.decode("latin-1"))


def _arm_in(path: str) -> str | None:
    """The arm `{ARMS}/{arm}...` names (None: not an arm's path)."""
    return path[len(ARMS) + 1:].split("/", 1)[0] if path.startswith(ARMS + "/") else None


def _press(scope: Scope) -> bool:
    """An estop press (`POST .../arms/{arm}/estop`): sent twice it does what it does once (a
    press on a latched estop changes nothing; a release between the two, someone else's, is
    latched again: the safe side), so it goes again on a new connection when a kept-alive one
    turns out broken. Not the release: a second one could undo a press made between them."""
    path: str = scope["path"]
    return scope["method"] == "POST" and path.startswith(ARMS + "/") and path.endswith("/estop")


def down_link(plan: LabPlan, arm: str, reason: str) -> dict[str, Any]:
    """The health entry (`LinkStatus`) of an arm whose worker is not answering."""
    link = plan.profile(arm).link
    return {"kind": link.kind, "address": link.address, "state": "down", "connected": False,
            "last_error": reason}


class LabFront:
    """The ASGI app of the front (see the module doc). `workers[k]` hosts `plan.workers[k]`."""

    def __init__(self, plan: LabPlan, supervisor: Supervisor, settings: Settings) -> None:
        self.plan = plan
        self.supervisor = supervisor
        self.workers = supervisor.workers
        self.max_body = settings.max_body_bytes
        #: The lab's tokens (the workers' own) and an open lab's Host and Origin rules: whose
        #: estop press may be kept, and written to the store (`_keep`).
        self._access = Access(settings)
        self._hosts = HostPolicy(settings)
        #: The lab's store (the workers' own): a press kept for a down worker latches there.
        self.store = Store(settings.data_dir)
        self.auth = settings.auth_enabled
        self.grace = settings.shutdown_timeout_s
        self._by_index = {w.index: w for w in self.workers}
        self.across = Across(plan, settings.data_dir)
        self._by_arm = {name: self._by_index[k] for name, k in plan.worker_of.items()}
        self._by_camera = {name: self._by_index[k] for name, k in plan.camera_worker.items()
                           if k in self._by_index}
        #: The last entry each camera's worker gave (`GET /cameras`), shown while it is down.
        self._cameras: dict[str, dict[str, Any]] = {}
        #: The last summary each arm's worker gave (`GET /arms`), shown while it is down.
        self._summaries: dict[str, dict[str, Any]] = {}

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        kind = scope["type"]
        if kind == "lifespan":
            return await self._lifespan(receive, send)
        worker = self._worker_for(scope["path"])
        if kind == "websocket":
            return await relay_websocket(scope, receive, send, worker)
        path, method = scope["path"], scope["method"]
        if handles(path):
            answer = await self._across(scope, receive, send)
            if answer is None:
                return
            status, headers, body = answer
        elif method == "GET" and path in (ARMS, HEALTH, CAMERAS):
            status, headers, body = await (self._arms(scope) if path == ARMS
                                           else self._cameras_list(scope) if path == CAMERAS
                                           else self._health(scope))
        else:
            answer = await self._forward(scope, receive, send, worker)
            if answer is None:  # relayed as it came (a stream)
                return
            status, headers, body = answer
        await send({"type": "http.response.start", "status": status,
                    "headers": [*headers, (b"content-length", str(len(body)).encode())]})
        await send({"type": "http.response.body", "body": body})

    async def _lifespan(self, receive: Receive, send: Send) -> None:
        while True:
            message = await receive()
            if message["type"] == "lifespan.startup":
                # before the workers: the first process to open a fresh store makes it
                # (Supervisor._first_ready), and they start on what the front has kept there
                self.store.open()
                self.supervisor.start()
                await send({"type": "lifespan.startup.complete"})
            elif message["type"] == "lifespan.shutdown":
                await self.supervisor.stop(self.grace)
                await asyncio.to_thread(self.store.close)
                await send({"type": "lifespan.shutdown.complete"})
                return

    def _worker_for(self, path: str) -> Worker | None:
        """The worker of the arm named in `path`, else the first ready one (None: none)."""
        arm = _arm_in(path)
        if arm is not None:
            if arm in self._by_arm:
                return self._by_arm[arm]
        elif path.startswith(CAMERAS + "/"):
            camera = path[len(CAMERAS) + 1:].split("/", 1)[0]
            if camera in self._by_camera:
                return self._by_camera[camera]
        return next((w for w in self.workers if w.ready), None)

    async def _read_body(self, receive: Receive) -> bytes | None:
        """The request body, or None once it is over max_body_bytes."""
        chunks, size = [], 0
        while True:
            message = await receive()
            if message["type"] == "http.disconnect":
                return b""
            chunk = message.get("body", b"")
            size += len(chunk)
            if size > self.max_body:
                return None
            chunks.append(chunk)
            if not message.get("more_body", False):
                return b"".join(chunks)

    def _too_large(self) -> Answer:
        return _json_response(413, {"detail": f"the request body is over {self.max_body} "
                                    "bytes (max_body_bytes)", "code": "too_large"})

    async def _across(self, scope: Scope, receive: Receive, send: Send) -> Answer | None:
        """Teleoperation and recordings, placed by the arms they name (app/lab/across.py)."""
        path, method = scope["path"], scope["method"]
        if method == "GET" and path in (TELEOP, RECORDINGS):
            answers, refusal = await self._ask_all(scope, path)
            if refusal is not None:
                return refusal
            if not answers:
                return self._down(None)
            merged = (self.across.merge_teleop(answers) if path == TELEOP
                      else self.across.merge_recordings(answers))
            return _json_response(200, merged)
        body = await self._read_body(receive)
        if body is None:
            return self._too_large()
        if method == "DELETE" and path.startswith(TELEOP + "/"):
            return await self._first_that_knows(scope, body)
        try:
            k = await self.across.place(method, path, body)
        except DifferentWorkers as exc:
            return _json_response(exc.status_code, {"detail": exc.detail, "code": exc.code})
        worker = self._worker_for(path) if k is None else self._by_index.get(k)
        return await self._forward(scope, receive, send, worker, body)

    async def _first_that_knows(self, scope: Scope, body: bytes) -> Answer:
        """The request to each ready worker in turn until one answers other than 404 (a
        teleoperation session lives in its follower's worker); else the last 404."""
        last: Answer | None = None
        for w in [w for w in self.workers if w.ready]:
            try:
                r = await w.client.request(scope["method"], _target(scope),
                                           forwarded_headers(scope), body, ASK_TIMEOUT_S)
                data = await r.read()
            except (UpstreamError, TimeoutError) as exc:
                log.warning("worker %d: %r", w.index, exc)
                continue
            last = r.status_code, [(k, v) for k, v in r.headers if k not in HOP_BACK], data
            if r.status_code != 404:
                return last
        return last if last is not None else self._down(None)

    async def _forward(self, scope: Scope, receive: Receive, send: Send,
                       worker: Worker | None, body: bytes | None = None) -> Answer | None:
        """Pass the request to `worker` and its answer back as it comes, chunk by chunk (an
        MJPEG stream never ends: it ends when the client goes). None once relayed; else the
        answer to send (a refusal of the front's, or a 404 to rename). `body`: already read."""
        body = await self._read_body(receive) if body is None else body
        if body is None:
            return self._too_large()
        press = _press(scope)
        if worker is None or not worker.ready:
            return self._down(worker, press and await self._keep(scope, worker, body))
        try:
            r = await worker.client.request(scope["method"], _target(scope),
                                            forwarded_headers(scope), body, REQUEST_TIMEOUT_S,
                                            retry=True if press else None)
        except UpstreamError as exc:  # its socket refused or broke twice: the worker is gone
            log.warning("worker %d: %r", worker.index, exc)
            return self._down(worker, press and await self._keep(scope, worker, body))
        except TimeoutError as exc:
            log.warning("worker %d: %r", worker.index, exc)
            return self._down(worker)
        try:
            if r.status_code == 404:  # small: read whole, maybe renamed
                data = self._all_arms_named(scope["path"], await r.read())
                return r.status_code, [(k, v) for k, v in r.headers if k not in HOP_BACK], data
            if r.length is not None and r.length <= WHOLE_BODY:  # a JSON answer: its bytes
                # as they came, read whole (no relay task and disconnect watch a request)
                return r.status_code, [(k, v) for k, v in r.headers if k not in HOP_WHOLE], \
                    await r.read()
            await send({"type": "http.response.start", "status": r.status_code,
                        "headers": [(k, v) for k, v in r.headers if k not in HOP_STREAM]})
            relay = asyncio.ensure_future(_relay_body(r, send))
            gone = asyncio.ensure_future(_disconnected(receive))
            await asyncio.wait([relay, gone], return_when=asyncio.FIRST_COMPLETED)
            for t in (relay, gone):
                t.cancel()
            await asyncio.gather(relay, gone, return_exceptions=True)
            return None
        finally:
            await r.aclose()

    def _all_arms_named(self, path: str, body: bytes) -> bytes:
        """A worker's 404 `unknown_arm` names its own arms (`no arm 'x'; this server hosts
        a, b`, app/web/deps.py, app/recording/manager.py): the lab's names them all."""
        arm = _arm_in(path)
        if arm in self._by_arm or b'"unknown_arm"' not in body:
            return body
        if arm is not None:
            detail = f"no arm {arm[:64]!r}"
        else:  # named in a body (teleoperation, recordings): keep the worker's own words
            try:
                detail = str(json.loads(body)["detail"]).split("; this server hosts", 1)[0]
            except (ValueError, KeyError, TypeError):
                return body
        return json.dumps({"detail": f"{detail}; this server hosts "
                           f"{', '.join(self.plan.names)}", "code": "unknown_arm"}).encode()

    async def _keep(self, scope: Scope, worker: Worker | None, body: bytes) -> bool:
        """Keep an estop press for `worker`, down now (True if kept): one whose token grants a
        role here (anyone authenticated may press; the worker checks it again, and the Host
        and Origin), so a caller without one cannot fill the worker's kept presses.

        A press the worker would take (the Host and Origin pass here too) is also written to
        the lab's store as the arm's latch, which the worker reads as it starts: the arm
        comes back latched however long its worker takes, the front restarted or not.
        Answered once that is on disk (as a press the worker answers)."""
        if worker is None or body:
            return False  # (a press with a body: the route takes none)
        headers = forwarded_headers(scope)
        auth = credentials(headers)
        if self._access.identify(bearer_token_of(auth)) is None:
            return False
        arm = _arm_in(scope["path"])
        saved = None
        if arm in worker.arms and self._hosts.refusal(scope, say=False) is None:
            saved = self.store.put_latch(arm, True)
            log.warning("%s: an estop press while worker %d is down: latched in the store",
                        arm, worker.index)
        kept = worker.keep_press(_target(scope), headers)
        if not kept:
            log.warning("worker %d: too many estop presses kept; this one is not", worker.index)
        await saved_within(saved)
        return kept or saved is not None

    def _down(self, worker: Worker | None, kept: bool = False) -> Answer:
        what = (f"worker {worker.index} (arms {', '.join(worker.arms)}) is restarting"
                if worker is not None else "no worker process is ready")
        if kept:
            what += (": this estop press is kept and goes to it as it comes back, before any "
                     "other request (the arm comes back latched)")
        return _json_response(503, {"detail": f"{what}: retry shortly", "code": "link_down"},
                              [(b"retry-after", b"1")])

    async def _ask_all(self, scope: Scope, path: str) -> tuple[dict[int, Any], Answer | None]:
        """`GET path` of every ready worker with the caller's headers: the parsed answers by
        worker, or the first refusal (401, 403, 400 ...) to answer as is."""
        headers = forwarded_headers(scope)

        async def ask(w: Worker) -> Answer:
            r = await w.client.request("GET", path, headers, timeout=ASK_TIMEOUT_S)
            data = await r.read()
            return r.status_code, [(k, v) for k, v in r.headers if k not in HOP_BACK], data

        ready = [w for w in self.workers if w.ready]
        got = await asyncio.gather(*(ask(w) for w in ready), return_exceptions=True)
        answers: dict[int, Any] = {}
        for w, r in zip(ready, got, strict=True):
            if isinstance(r, UpstreamError | TimeoutError):
                continue
            if isinstance(r, BaseException):
                raise r
            if r[0] != 200:
                return answers, r
            answers[w.index] = json.loads(r[2])
        return answers, None

    async def _ask_or_check(self, scope: Scope, path: str,
                            token: bool = True) -> tuple[dict[int, Any], Answer | None]:
        """`_ask_all`; where no worker answered (none ready, or none of the ready ones), the
        checks a worker makes first, made by the front (`_refused`): a list the front then
        answers from the plan alone is given to no caller a worker would refuse."""
        answers, refusal = await self._ask_all(scope, path)
        if refusal is None and not answers:
            refusal = self._refused(scope, token)
        return answers, refusal

    def _refused(self, scope: Scope, token: bool = True) -> Answer | None:
        """What a worker refuses a lab-wide list with before its route (an open lab's Host
        rule, then with `token` a viewer's token: app/web/hostguard.py, app/web/routes/arms.py;
        health needs none); None if it would answer."""
        refused = self._hosts.refusal(scope)
        if refused is not None:
            status, detail = REFUSALS[refused]
            return _json_response(status, {"detail": detail, "code": refused})
        if not token:
            return None
        try:
            self._access.require(bearer_token_of(credentials(forwarded_headers(scope))),
                                 Role.VIEWER)
        except ArmError as exc:
            r = arm_error_response(exc)
            return r.status_code, [(k, v) for k, v in r.raw_headers
                                   if k != b"content-length"], bytes(r.body)
        return None

    async def _arms(self, scope: Scope) -> Answer:
        answers, refusal = await self._ask_or_check(scope, ARMS)
        if refusal is not None:
            return refusal
        for listed in answers.values():
            for summary in listed:
                self._summaries[summary["name"]] = summary
        out = []
        for name in self.plan.names:
            k = self.plan.worker_of[name]
            if k in answers:
                out.append(self._summaries[name])
            else:  # its worker is down: its last summary, or (never given) its profile's
                w = self._by_index[k]
                known = self._summaries.get(name) or self._summary_of(name)
                out.append({**known,
                            "link": down_link(self.plan, name, w.last_error or "worker down")})
        return _json_response(200, out)

    def _summary_of(self, name: str) -> dict[str, Any]:
        """An arm's summary from its profile (link set by the caller): for an arm whose worker
        has not answered since the front started; every arm of the plan is listed (a client
        that presses every arm it lists, `armserver estop`, misses none)."""
        p = self.plan.profile(name)
        return {"name": name, "model": p.model, "description": p.description,
                "capabilities": describe.capabilities(p).model_dump(mode="json")}

    async def _cameras_list(self, scope: Scope) -> Answer:
        """Every worker's cameras in config order; a down worker's with their last entry and
        `up` false."""
        answers, refusal = await self._ask_or_check(scope, CAMERAS)
        if refusal is not None:
            return refusal
        for listed in answers.values():
            for entry in listed:
                self._cameras[entry["name"]] = entry
        out = []
        where = self.plan.camera_worker
        for cam in self.plan.cameras:
            k = where.get(cam.name)
            if k in answers:
                if cam.name in self._cameras:
                    out.append(self._cameras[cam.name])
            elif cam.name in self._cameras:
                out.append({**self._cameras[cam.name], "up": False})
            elif k is not None:  # its worker never answered since the front started
                out.append(await self._camera_of(cam))
        return _json_response(200, out)

    async def _camera_of(self, cam: CameraConfig) -> dict[str, Any]:
        """A down worker's camera from its config (not up) and the store (calibrated)."""
        try:
            stored = await self.store.get_setting(CAMERA_SCOPE.format(cam.name),
                                                  CALIBRATION_KEY)
        except StoreError:
            stored = None
        return {"name": cam.name, "arm": cam.arm, "kind": cam.kind, "width": cam.width,
                "height": cam.height, "fps": cam.fps, "up": False,
                "calibrated": stored is not None}

    async def _health(self, scope: Scope) -> Answer:
        answers, refusal = await self._ask_or_check(scope, HEALTH, token=False)
        if refusal is not None:
            return refusal
        bodies = answers
        first: dict[str, Any] = next(iter(bodies.values()), {})
        arms: dict[str, Any] = {}
        ok = True
        for name in self.plan.names:
            k = self.plan.worker_of[name]
            if k in bodies and name in bodies[k].get("arms", {}):
                arms[name] = bodies[k]["arms"][name]
            else:
                w = self._by_index[k]
                arms[name] = down_link(self.plan, name,
                                       w.last_error or f"worker {k} is starting")
                ok = False
        ok = ok and all(b.get("status") == "ok" for b in bodies.values())
        for key, value in first.items():  # per-arm maps of other parts (cameras ...): all
            if key != "arms" and isinstance(value, dict) and all(
                    isinstance(b.get(key), dict) for b in bodies.values()):
                first[key] = {k: v for b in bodies.values() for k, v in b[key].items()}
        out = {"auth": self.auth, **first, "status": "ok" if ok else "degraded", "arms": arms}
        return _json_response(200, out)
