"""Bearer-token access: who may read, who may move.

Tokens come from the settings (ARMSERVER_OPERATOR_TOKENS, ARMSERVER_VIEWER_TOKENS,
ARMSERVER_INSTRUCTOR_TOKENS, comma separated). With none configured the server is open: every
client is an instructor (it may also change the safety envelope: on an open server anyone who
can reach it could as well restart it with another profile). With any configured, a request
must carry `Authorization: Bearer <token>` (a WebSocket may instead pass `?token=`), and

- a viewer token reads: health, arms, state, telemetry, kinematics, plans, motions, and may
  latch the emergency stop (the stop is open to every authenticated client);
- an operator token may also move the arm and send protocol commands;
- an instructor token may do all an operator may, and also change an arm's safety envelope.

Every presented token is compared against every configured one with `hmac.compare_digest` over
SHA-256 digests, so the time taken says neither which token nor how much of one matched.
"""

from __future__ import annotations

import enum
import hashlib
import hmac
import logging
import re
from urllib.parse import unquote_plus

from app.config import Settings
from app.errors import Forbidden, Unauthorized

log = logging.getLogger(__name__)


class Role(enum.IntEnum):
    VIEWER = 1
    OPERATOR = 2
    INSTRUCTOR = 3


def _digest(token: str) -> bytes:
    return hashlib.sha256(token.encode("utf-8", "surrogatepass")).digest()


class Access:
    """The configured tokens of one server and the checks against them."""

    def __init__(self, settings: Settings) -> None:
        self._operators = [_digest(t) for t in sorted(settings.operator_set)]
        self._viewers = [_digest(t) for t in sorted(settings.viewer_set)]
        self._instructors = [_digest(t) for t in sorted(settings.instructor_set)]
        self.enabled = bool(self._operators or self._viewers or self._instructors)

    def describe(self) -> str:
        """A start-up line saying whether the server is open (never the tokens)."""
        if not self.enabled:
            return "no tokens configured: the server is OPEN to anyone who can reach it"
        return (f"token-protected: {len(self._instructors)} instructor, "
                f"{len(self._operators)} operator and {len(self._viewers)} viewer token(s)")

    def role_of(self, token: str | None) -> Role | None:
        """The role a token grants, None if it grants none. Open servers grant instructor."""
        if not self.enabled:
            return Role.INSTRUCTOR
        if not token:
            return None
        d = _digest(token)
        operator = False
        viewer = False
        instructor = False
        for t in self._instructors:
            instructor |= hmac.compare_digest(d, t)
        for t in self._operators:  # no early exit: constant time over the token list
            operator |= hmac.compare_digest(d, t)
        for t in self._viewers:
            viewer |= hmac.compare_digest(d, t)
        if instructor:
            return Role.INSTRUCTOR
        if operator:
            return Role.OPERATOR
        if viewer:
            return Role.VIEWER
        return None

    def require(self, token: str | None, need: Role) -> Role:
        """The caller's role, or 401 (no or unknown token) / 403 (viewer where operator needed)."""
        role = self.role_of(token)
        if role is None:
            raise Unauthorized("missing bearer token" if not token else "invalid bearer token")
        if role < need and need is Role.INSTRUCTOR:
            raise Forbidden("this needs an instructor token (changing the safety envelope); "
                            f"this token is a {role.name.lower()}'s")
        if role < need:
            raise Forbidden("this needs an operator token; a viewer token may read state and "
                            "telemetry and latch the emergency stop")
        return role


def bearer_token(authorization: str | None) -> str | None:
    """The token of an `Authorization: Bearer <token>` header value, else None."""
    if not authorization:
        return None
    scheme, _, token = authorization.strip().partition(" ")
    if scheme.lower() != "bearer":
        return None
    return token.strip() or None


#: Query parameters that carry a token. A name is compared after percent-decoding, as the
#: server decodes it: `?tok%65n=...` is `?token=...` to Starlette, so it is to the log filter.
TOKEN_PARAMS = frozenset({"token", "access_token"})
#: Header names whose value is a secret, in logs that print headers as ("name", "value") pairs
#: (uvicorn's WebSocket handshake at debug level: `< %s: %s`).
SECRET_HEADERS = frozenset({"authorization", "proxy-authorization", "cookie", "x-arm-lease"})
_QUERY_PARAM = re.compile(r"([?&;])([^=&;\s\"'#]*)=([^&;\s\"'#]*)")
_CREDENTIALS = re.compile(r"(?i)\b(bearer|basic)(\s+)[^\s\"',;]+")
_HEADER_LINE = re.compile(r"(?im)^([<> ]*(?:" + "|".join(SECRET_HEADERS) + r")\s*:\s*).+$")


def _param(m: re.Match[str]) -> str:
    if unquote_plus(m.group(2)).strip().lower() in TOKEN_PARAMS:
        return f"{m.group(1)}{m.group(2)}=***"
    return m.group(0)


def redact(text: str) -> str:
    """`text` with every token blanked: token query parameters (names percent-decoded),
    `Bearer`/`Basic` credentials, and the values of secret header lines."""
    text = _QUERY_PARAM.sub(_param, text)
    text = _HEADER_LINE.sub(r"\1***", text)
    return _CREDENTIALS.sub(r"\1\2***", text)


class RedactTokens(logging.Filter):
    """Blank tokens in log records: uvicorn logs each request's and each WebSocket handshake's
    path, query string included (a browser can only pass a WebSocket token in the query), and
    at debug level the handshake's headers, `authorization` included. Arguments are redacted
    one by one (uvicorn's access formatter unpacks them); an argument that follows a secret
    header's name is blanked whole. Installed by `install_log_redaction`."""

    def filter(self, record: logging.LogRecord) -> bool:
        if isinstance(record.msg, str):
            record.msg = redact(record.msg)
        if isinstance(record.args, tuple):
            out: list[object] = []
            secret_next = False
            for a in record.args:
                if secret_next:
                    out.append("***")
                else:
                    out.append(redact(a) if isinstance(a, str) else a)
                secret_next = isinstance(a, str) and a.strip().lower() in SECRET_HEADERS
            record.args = tuple(out)
        return True


def install_log_redaction() -> None:
    """Add RedactTokens to the loggers that print request paths (idempotent)."""
    for name in ("uvicorn.access", "uvicorn.error", "uvicorn", "websockets", "websockets.server",
                 "websockets.legacy.server"):
        logger = logging.getLogger(name)
        if not any(isinstance(f, RedactTokens) for f in logger.filters):
            logger.addFilter(RedactTokens())
