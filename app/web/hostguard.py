"""Host and Origin checks for an open server (no tokens): no web page may drive the arm.

Without tokens, anyone who can reach the port is an operator; a web page a lab user opens can
reach it too, through the user's browser: a cross-site `<form>` POST needs no preflight, a
WebSocket is not subject to CORS at all, and DNS rebinding points a name the attacker owns at
127.0.0.1. So, on an open server:

- **Host**: only the names the server is bound to are accepted: `127.0.0.1`, `localhost`,
  `[::1]`, the configured `host`, and `ARMSERVER_ALLOWED_HOSTS` (comma separated, `*` for any).
  Bound to a wildcard (`0.0.0.0`, `::`), IP literals and this machine's own host name are
  accepted as well (a rebinding attack needs a name the attacker controls, never an IP
  literal). Anything else: 400 `bad_host`.
- **Origin**: a request that changes something (anything but GET, HEAD, OPTIONS) from a browser
  whose `Origin` is not the server's own (same scheme, host and port as the request) and not in
  `ARMSERVER_CORS_ORIGINS` is 403 `cross_origin`; without `Origin`, a `Sec-Fetch-Site` other
  than `same-origin` or `none` is refused the same way. Clients that are not browsers (curl,
  scripts, the Python client) send neither header and are not affected.
- **WebSocket**: an upgrade from a foreign `Origin` is accepted and closed at once with code
  4403 (so the client sees why), before any telemetry is sent.

With tokens configured these checks are off: a browser cannot attach a bearer token to a
cross-site request without the token, and the token check stands in front of every route.
"""

from __future__ import annotations

import ipaddress
import logging
import socket
from urllib.parse import urlsplit

from starlette.types import ASGIApp, Receive, Scope, Send

from app.config import Settings
from app.web.error_responses import send_error

log = logging.getLogger(__name__)

LOOPBACK_NAMES = frozenset({"127.0.0.1", "localhost", "::1", "localhost.localdomain"})
WILDCARD_BINDS = frozenset({"0.0.0.0", "::", ""})
SAFE_METHODS = frozenset({"GET", "HEAD", "OPTIONS"})
SAME_SITE_FETCH = frozenset({"same-origin", "none"})
CLOSE_CROSS_ORIGIN = 4403


def split_host(value: str) -> str:
    """The host name of a `Host` header value, lower case, without port or IPv6 brackets."""
    value = value.strip().lower()
    if value.startswith("["):
        return value[1:].partition("]")[0]
    if value.count(":") > 1:  # a bare IPv6 literal (not valid in Host, but be exact)
        return value
    return value.partition(":")[0].rstrip(".")


def _is_ip(host: str) -> bool:
    try:
        ipaddress.ip_address(host)
    except ValueError:
        return False
    return True


def _split_list(v: str) -> list[str]:
    return [t.strip() for t in v.split(",") if t.strip()]


class HostPolicy:
    """Which Host names and Origins an open server accepts (built once from the settings)."""

    def __init__(self, settings: Settings) -> None:
        self.enabled = not settings.auth_enabled
        allowed = [split_host(h) if h != "*" else "*" for h in _split_list(settings.allowed_hosts)]
        self.any_host = "*" in allowed
        bind = split_host(settings.host)
        self.wildcard = bind in WILDCARD_BINDS
        names = set(LOOPBACK_NAMES) | set(allowed)
        if not self.wildcard:
            names.add(bind)
        else:
            names |= {socket.gethostname().lower(), socket.getfqdn().lower()}
        self.hosts = frozenset(n for n in names if n and n != "*")
        origins = _split_list(settings.cors_origins)
        self.any_origin = "*" in origins
        self.origins = frozenset(o.rstrip("/").lower() for o in origins if o != "*")

    def host_ok(self, host_header: str | None) -> bool:
        if self.any_host:
            return True
        if not host_header:  # HTTP/1.0 without Host: only a non-browser client does this
            return True
        host = split_host(host_header)
        return host in self.hosts or (self.wildcard and _is_ip(host))

    def refusal(self, scope: Scope, say: bool = True) -> str | None:
        """The error code an open server refuses the request (or upgrade) `scope` with
        (`bad_host`, `cross_origin`; logged if `say`), None if it passes or the policy is
        off."""
        if not self.enabled:
            return None
        headers = dict(scope.get("headers", ()))
        host = headers.get(b"host")
        if not self.host_ok(host.decode("latin-1") if host is not None else None):
            if say:
                log.warning("refused %s %s: Host %r is not a name this server is bound to",
                            scope.get("method", "WS"), scope.get("path"),
                            (host or b"").decode("latin-1")[:80])
            return "bad_host"
        origin = headers.get(b"origin")
        site = headers.get(b"sec-fetch-site")
        unsafe = scope["type"] == "websocket" or scope.get("method") not in SAFE_METHODS
        if unsafe and not self.origin_ok(
                scope, origin.decode("latin-1") if origin is not None else None,
                site.decode("latin-1") if site is not None else None):
            if say:
                log.warning("refused %s %s from Origin %r (Sec-Fetch-Site %r): cross-origin",
                            scope.get("method", "WS"), scope.get("path"),
                            (origin or b"-").decode("latin-1")[:80],
                            (site or b"-").decode("latin-1")[:20])
            return "cross_origin"
        return None

    def origin_ok(self, scope: Scope, origin: str | None, fetch_site: str | None) -> bool:
        """Whether a browser request (or upgrade) comes from the server's own page or an
        allowed origin. No Origin and no Sec-Fetch-Site: not a browser, allowed."""
        if origin is None:
            return fetch_site is None or fetch_site.lower() in SAME_SITE_FETCH
        origin = origin.strip().rstrip("/").lower()
        if self.any_origin or origin in self.origins:
            return True
        if origin == "null":  # sandboxed frames, file:// pages
            return False
        parts = urlsplit(origin)
        host = dict(scope.get("headers", ())).get(b"host", b"").decode("latin-1").lower()
        scheme = {"ws": "http", "wss": "https"}.get(scope.get("scheme", "http"),
                                                   scope.get("scheme", "http"))
        return parts.scheme == scheme and parts.netloc == host and bool(host)


#: Each refusal's (status, detail) by its code (`HostPolicy.refusal`): the middleware's answer,
#: and the lab's front's where it answers for its workers (app/lab/front.py).
REFUSALS: dict[str, tuple[int, str]] = {
    "bad_host": (400, "this server does not answer to that Host name; allow it with "
                      "ARMSERVER_ALLOWED_HOSTS (or configure tokens)"),
    "cross_origin": (403, "a page from another origin may not change anything on this server; "
                          "allow that origin with ARMSERVER_CORS_ORIGINS"),
}


class HostOriginGuard:
    """ASGI middleware applying :class:`HostPolicy` to HTTP requests and WebSocket upgrades."""

    def __init__(self, app: ASGIApp, policy: HostPolicy) -> None:
        self.app = app
        self.policy = policy

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] not in ("http", "websocket") or not self.policy.enabled:
            await self.app(scope, receive, send)
            return
        refused = self.policy.refusal(scope)
        if refused is not None:
            status, detail = REFUSALS[refused]
            await self._refuse(scope, receive, send, status, refused, detail)
            return
        await self.app(scope, receive, send)

    @staticmethod
    async def _refuse(scope: Scope, receive: Receive, send: Send, status: int, code: str,
                      detail: str) -> None:
        if scope["type"] == "websocket":
            message = await receive()  # websocket.connect
            if message["type"] != "websocket.connect":
                return
            await send({"type": "websocket.accept"})
            await send({"type": "websocket.close", "code": CLOSE_CROSS_ORIGIN,
                        "reason": f"{code}: refused"})
            return
        await send_error(send, status, detail, code)
