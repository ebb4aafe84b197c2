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

People (API.md "People and roles"): a token may carry a name, `alice:tok1`; a bare token is named
by the first 8 hex digits of its SHA-256. `ARMSERVER_TOKENS_FILE` (TOML, `[[tokens]] name, role,
token`) adds a class's worth. Names, never tokens, go into the queue, events, logs and audit.
"""

from __future__ import annotations

import enum
import hashlib
import hmac
import logging
import re
import tomllib
from dataclasses import dataclass
from pathlib import Path
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


_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.@-]{0,63}$")
#: The identity of every caller of a server configured without tokens.
OPEN_NAME = "anyone"


@dataclass(frozen=True)
class Identity:
    """Who is calling: a name (never the token) and a role."""

    name: str
    role: Role


def token_name(token: str) -> str:
    """The name of a bare token: the first 8 hex digits of its SHA-256."""
    return hashlib.sha256(token.encode("utf-8", "surrogatepass")).hexdigest()[:8]


def parse_named(entry: str) -> tuple[str, str]:
    """`name:token` -> (name, token); a bare token -> (its hash name, token)."""
    name, sep, token = entry.partition(":")
    if sep and token and _NAME.match(name):
        return name, token
    return token_name(entry), entry


def load_tokens_file(path: str | Path) -> list[tuple[str, Role, str]]:
    """(name, role, token) of each `[[tokens]]` table of a TOML file; ValueError if malformed."""
    data = tomllib.loads(Path(path).read_text())
    out: list[tuple[str, Role, str]] = []
    for i, entry in enumerate(data.get("tokens", [])):
        if not isinstance(entry, dict):
            raise ValueError(f"{path}: tokens[{i}] is not a table")  # noqa: TRY004
        name, role, token = entry.get("name"), entry.get("role", "operator"), entry.get("token")
        if not isinstance(token, str) or not token:
            raise ValueError(f"{path}: tokens[{i}] has no token")
        if not isinstance(name, str) or not _NAME.match(name):
            raise ValueError(f"{path}: tokens[{i}] needs a name of letters, digits, _.@-")
        if not isinstance(role, str) or role.upper() not in Role.__members__:
            raise ValueError(f"{path}: tokens[{i}] role must be viewer, operator or instructor")
        out.append((name, Role[role.upper()], token))
    return out


class Access:
    """The configured tokens of one server and the checks against them."""

    def __init__(self, settings: Settings) -> None:
        people: list[tuple[str, Role, str]] = []
        for role, entries in ((Role.INSTRUCTOR, settings.instructor_set),
                              (Role.OPERATOR, settings.operator_set),
                              (Role.VIEWER, settings.viewer_set)):
            people += [(name, role, tok) for name, tok in map(parse_named, sorted(entries))]
        if settings.tokens_file:
            people += load_tokens_file(settings.tokens_file)
        # (digest, name, role), highest role first: a token given twice takes its highest role
        self._people = sorted(((_digest(tok), name, role) for name, role, tok in people),
                              key=lambda p: -p[2])
        self._operators = [d for d, _, r in self._people if r is Role.OPERATOR]
        self._viewers = [d for d, _, r in self._people if r is Role.VIEWER]
        self._instructors = [d for d, _, r in self._people if r is Role.INSTRUCTOR]
        self.enabled = bool(self._people)

    @property
    def names(self) -> frozenset[str]:
        """The names the configured tokens have (none on an open server)."""
        return frozenset(n for _, n, _ in self._people)

    def identify(self, token: str | None) -> Identity | None:
        """The caller's name and role, None if the token grants none. Constant time over the
        configured tokens: every one is compared, no early exit."""
        if not self.enabled:
            return Identity(OPEN_NAME, Role.INSTRUCTOR)
        if not token:
            return None
        d = _digest(token)
        found: Identity | None = None
        for digest, name, role in self._people:
            match = hmac.compare_digest(d, digest)
            if match and found is None:
                found = Identity(name, role)
        return found

    def describe(self) -> str:
        """A start-up line saying whether the server is open (never the tokens)."""
        if not self.enabled:
            return "no tokens configured: the server is OPEN to anyone who can reach it"
        return (f"token-protected: {len(self._instructors)} instructor, "
                f"{len(self._operators)} operator and {len(self._viewers)} viewer token(s) "
                f"({len({n for _, n, _ in self._people})} name(s))")

    def role_of(self, token: str | None) -> Role | None:
        """The role a token grants, None if it grants none. Open servers grant instructor."""
        who = self.identify(token)
        return None if who is None else who.role

    def require(self, token: str | None, need: Role) -> Role:
        """The caller's role, or 401 (no or unknown token) / 403 (viewer where operator needed)."""
        return self.require_identity(token, need).role

    def require_identity(self, token: str | None, need: Role) -> Identity:
        """The caller, or 401 (no or unknown token) / 403 (a role below `need`)."""
        who = self.identify(token)
        if who is None:
            raise Unauthorized("missing bearer token" if not token else "invalid bearer token")
        role = who.role
        if role < need and need is Role.INSTRUCTOR:
            raise Forbidden("this needs an instructor token (safety envelope, revoking leases, "
                            f"reordering queues, the audit log); this token is a "
                            f"{role.name.lower()}'s")
        if role < need:
            raise Forbidden("this needs an operator token; a viewer token may read state and "
                            "telemetry and latch the emergency stop")
        return who


def bearer_token(authorization: str | None) -> str | None:
    """The token of an `Authorization: Bearer <token>` header value, else None."""
    if not authorization:
        return None
    scheme, _, token = authorization.strip().partition(" ")
    if scheme.lower() != "bearer":
        return None
    return token.strip() or None


def bearer_token_of(header: bytes | None) -> str | None:
    """`bearer_token` of a raw `authorization` header value (an ASGI scope's, latin-1), or
    None: what a layer that reads the scope's headers itself gets (the token gate, the
    estop's and the state's fast path, the audit log, a lab's front)."""
    return bearer_token(header.decode("latin-1") if header is not None else None)


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
