"""Write the reference pages that are made from the code, so that they cannot drift from it.

- ``docs/reference/settings.md`` from ``app/config/settings.py``: every field of ``Settings``
  as its ``ARMSERVER_*`` variable, with its type, default, the bounds checked at start-up and
  its description (the ``#:`` comment above the field, else its ``Field(description=...)``,
  else the help of its ``armserver serve`` flag, else a line in ``NOTES`` below);
- ``docs/reference/errors.md`` from ``app/errors.py`` (``CODES``: each code's HTTP status,
  meaning, server exception and client exception) and ``app/client/errors.py`` (the client's
  classes and its own codes).

Usage, from the repository root::

    python tools/gen_reference.py           # write both files
    python tools/gen_reference.py --check   # exit 1, naming the file, if either differs

``tests/test_docs_reference.py`` fails when the committed files differ from what this writes:
after changing a setting or an error code, run it and commit the result.
"""

from __future__ import annotations

import argparse
import ast
import difflib
import sys
import typing
from collections.abc import Callable
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

SETTINGS_SOURCE = ROOT / "app" / "config" / "settings.py"
SETTINGS_MD = ROOT / "docs" / "reference" / "settings.md"
ERRORS_MD = ROOT / "docs" / "reference" / "errors.md"

#: Descriptions of the settings whose field in app/config/settings.py has none (no `#:`
#: comment, no `Field(description=...)`, no `armserver serve` flag with a help). A comment
#: added in settings.py wins over the line here; a line here for a setting that no longer
#: exists fails the generator.
NOTES: dict[str, str] = {
    "operator_tokens": "Operator tokens, comma-separated, each `name:token` or a bare token "
    "(named by the first 8 hex digits of its SHA-256): read, move the arm, send protocol "
    "commands. With no token of any kind configured the server is open.",
    "viewer_tokens": "Viewer tokens, comma-separated (as operator tokens): read state and "
    "telemetry.",
    "instructor_tokens": "Instructor tokens, comma-separated (as operator tokens): all an "
    "operator may do, and change the safety envelope, revoke leases, reorder the queue, "
    "read the audit log.",
    "cors_origins": "Origins (comma-separated) of dashboards served elsewhere: CORS answers, "
    "writes and WebSockets from them are accepted.",
    "max_body_bytes": "Largest request body, bytes; more is 413 `too_large`.",
    "max_ws_message_bytes": "Largest message a telemetry WebSocket client may send, bytes; "
    "more closes the socket with 1009.",
    "lease_ttl_s": "Lifetime of a control lease between two renewals (heartbeats), s.",
    "log_level": "Log level of the server.",
    "mqtt_prefix": "MQTT topic prefix; give each server of a lab its own under one root, "
    "e.g. `armserver/bench3`.",
    "max_subscribers": "Telemetry WebSocket subscribers in all, over every arm; more are "
    "closed with 1013 `busy`.",
}


# ------------------------------------------------------------------ settings


def field_comments(source: str, class_name: str = "Settings") -> dict[str, str]:
    """Field name -> its `#:` comment (the comment lines right above the field, joined)."""
    tree = ast.parse(source)
    lines = source.splitlines()
    cls = next(n for n in tree.body if isinstance(n, ast.ClassDef) and n.name == class_name)
    out: dict[str, str] = {}
    for node in cls.body:
        if not (isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name)):
            continue
        comment: list[str] = []
        i = node.lineno - 2  # the line above, 0-based
        while i >= 0 and lines[i].strip().startswith("#:"):
            comment.insert(0, lines[i].strip()[2:].strip())
            i -= 1
        if comment:
            out[node.target.id] = " ".join(comment)
    return out


def flag_helps() -> dict[str, tuple[str, str]]:
    """Setting name -> (`armserver serve` flag, its help), from the CLI's own parser."""
    import argparse as ap

    from app import cli

    parser = cli._parser()
    sub = next(a for a in parser._actions if isinstance(a, ap._SubParsersAction))
    serve = sub.choices["serve"]
    out: dict[str, tuple[str, str]] = {}
    for action in serve._actions:
        if action.option_strings and action.dest not in ("help",):
            flag = max(action.option_strings, key=len)
            out[action.dest] = (flag, action.help or "")
    return out


def written_default(value: Any) -> str:
    """A default as the reference writes it (as tests/test_settings_readme.py reads it)."""
    if value is None or value == "":
        return "none"
    if isinstance(value, bool):
        return f"`{str(value).lower()}`"
    if isinstance(value, float) and value.is_integer():
        return f"`{int(value)}`"
    return f"`{value}`"


def _number(x: float) -> str:
    return str(int(x)) if float(x).is_integer() else str(x)


def bounds(name: str, annotation: Any, metadata: list[Any]) -> str:
    """What start-up checks of a setting's value, from the model and its validator's tables."""
    from app.config.settings import _QUANTITY_SUFFIXES, LOG_LEVELS, SETTING_RANGES

    parts: list[str] = []
    low = high = ""
    for m in metadata:
        for attr, sign in (("gt", ">"), ("ge", ">=")):
            if getattr(m, attr, None) is not None:
                low = f"{sign} {_number(getattr(m, attr))}"
        for attr, sign in (("lt", "<"), ("le", "<=")):
            if getattr(m, attr, None) is not None:
                high = f"{sign} {_number(getattr(m, attr))}"
        if getattr(m, "pattern", None):
            parts.append(f"matches `{m.pattern}`")
    if low or high:
        parts.append(" and ".join(p for p in (low, high) if p))
    numeric = annotation in (int, float)
    if name in SETTING_RANGES:
        parts.append(SETTING_RANGES[name][2])
    elif numeric and not (low or high) and (name.endswith(_QUANTITY_SUFFIXES)
                                            or name.startswith("max_")):
        parts.append(">= 0")
    if annotation is bool:
        parts.append("`true` or `false`")
    if name == "log_level":
        parts.append("one of " + ", ".join(f"`{level}`" for level in LOG_LEVELS))
    if name == "host":
        parts.append("not empty")
    if name == "mqtt_url":
        from app.telemetry.mqtt import parse_broker_url

        doc = (parse_broker_url.__doc__ or "").strip().rstrip(".")
        parts.append(f"a broker URL: {doc}" if doc else "a broker URL")
    return "; ".join(parts) if parts else "-"


def _type(annotation: Any) -> str:
    """`str`, `int`, ...; `str, or unset` for an optional one."""
    args = typing.get_args(annotation)
    if args:
        named = [_type(a) for a in args if a is not type(None)]
        return " or ".join(named) + (", or unset" if type(None) in args else "")
    return annotation.__name__ if isinstance(annotation, type) else str(annotation)


def _cell(text: str) -> str:
    return text.replace("|", "\\|").replace("\n", " ")


def render_settings() -> str:
    from app.config.settings import Settings, env_name, is_secret

    comments = field_comments(SETTINGS_SOURCE.read_text(encoding="utf-8"))
    flags = flag_helps()
    stale = sorted(set(NOTES) - set(Settings.model_fields))
    if stale:
        raise SystemExit(f"tools/gen_reference.py NOTES names no setting: {', '.join(stale)}")
    rows: list[str] = []
    undescribed: list[str] = []
    for name, info in Settings.model_fields.items():
        text = (comments.get(name) or info.description or flags.get(name, ("", ""))[1]
                or NOTES.get(name, ""))
        if not text:
            undescribed.append(name)
            continue
        text = text[0].upper() + text[1:]
        if not text.endswith("."):
            text += "."
        extra: list[str] = []
        if name in flags:
            extra.append(f"Flag: `armserver serve {flags[name][0]}`.")
        if is_secret(name):
            extra.append("A secret: shown as `***` in any message.")
        desc = " ".join([text, *extra])
        checked = bounds(name, info.annotation, list(info.metadata))
        rows.append(f"| `{env_name(name)}` | {written_default(info.default)} | "
                    f"{_type(info.annotation)} | {_cell(checked)} | {_cell(desc)} |")
    if undescribed:
        raise SystemExit("settings without a description: " + ", ".join(undescribed)
                         + " (add a `#:` comment above the field in app/config/settings.py)")
    head = [
        "# Settings",
        "",
        "<!-- Generated by tools/gen_reference.py from app/config/settings.py: do not edit by",
        "     hand; run `python tools/gen_reference.py` (tests/test_docs_reference.py checks). -->",
        "",
        "Every setting of the server (`app.config.Settings`), from the environment (the variable",
        "names below) or, for the few that have one, a flag of `armserver serve` (a flag wins).",
        "Every setting is checked at start-up: `armserver serve` exits 2 with one message naming",
        "the variable, its value and what it must be, never a traceback. Besides the bounds",
        "listed, every number must be finite; a setting that says token, secret or password is",
        "shown as `***` in any message, and so is the password of a URL (`user:***@`).",
        "",
        f"{len(rows)} settings, in the order of `app/config/settings.py`:",
        "",
        "| variable | default | type | checked at start-up | description |",
        "|---|---|---|---|---|",
    ]
    return "\n".join([*head, *rows]) + "\n"


# ------------------------------------------------------------------ errors


def _client_chain(cls: type) -> str:
    """`Gone` < `NotFound` < `ArmServerError`: the class and its bases in app.client.errors."""
    from app.client.errors import ArmServerError

    chain = [c.__name__ for c in cls.__mro__ if issubclass(c, ArmServerError)]
    return " < ".join(f"`{n}`" for n in chain)


def render_errors() -> str:
    from app.client import errors as client_errors
    from app.errors import CODES

    lines = [
        "# Error codes",
        "",
        "<!-- Generated by tools/gen_reference.py from app/errors.py and app/client/errors.py:",
        "     do not edit by hand; run `python tools/gen_reference.py`",
        "     (tests/test_docs_reference.py checks). -->",
        "",
        "Every refusal is answered `{\"detail\": ..., \"code\": ...}` with one of the codes below",
        "(`app.errors.CODES`, the one table the server's exceptions, the OpenAPI document and the",
        "client's exceptions are made from). The server raises the exception of `app.errors`",
        "named here; the Python client (`app.client`) raises the client exception, whose",
        "`status`, `code` and `detail` are the answer's. A class to the left of `<` is a",
        "subclass of the one to its right: `except Conflict` catches `EstopLatched`.",
        "",
        "| code | HTTP | meaning | server exception | client exception |",
        "|---|---|---|---|---|",
    ]
    for row in sorted(CODES.values(), key=lambda r: (r.status is None, r.status or 0)):
        status = str(row.status) if row.status is not None else "- (a motion's end)"
        cls = client_errors.ERRORS[row.code]
        lines.append(f"| `{row.code}` | {status} | {_cell(row.meaning)} | "
                     f"`{row.exception}` | {_client_chain(cls)} |")
    lines += [
        "",
        "A code with no HTTP status never answers a request: it is the `code` of a motion that",
        "ended without success (`GET .../motions/{id}`, the `motion_ended` and `watchdog`",
        "events).",
        "",
        "## The client's own codes",
        "",
        "| code | client exception | when |",
        "|---|---|---|",
    ]
    for code, cls in client_errors.ERRORS.items():
        if code in CODES:
            continue
        doc = " ".join((cls.__doc__ or "").split())
        when = doc.split(": ", 1)[1] if ": " in doc else doc
        lines.append(f"| `{code}` | {_client_chain(cls)} | {_cell(when)} |")
    lines += [
        "",
        "An error answer that carries no code (a proxy's page, say) is given one by its status:",
        "",
        "| HTTP | code |",
        "|---|---|",
        *(f"| {s} | `{c}` |" for s, c in sorted(client_errors.STATUS_CODES.items())),
        "",
    ]
    return "\n".join(lines)


# ------------------------------------------------------------------ main

TARGETS: dict[Path, Callable[[], str]] = {SETTINGS_MD: render_settings, ERRORS_MD: render_errors}


def diff(path: Path, expected: str) -> str:
    """A unified diff of the committed file against what the generator writes ('' if equal)."""
    actual = path.read_text(encoding="utf-8") if path.exists() else ""
    if actual == expected:
        return ""
    rel = path.relative_to(ROOT)
    return "".join(difflib.unified_diff(actual.splitlines(keepends=True),
                                        expected.splitlines(keepends=True),
                                        f"{rel} (committed)", f"{rel} (generated)"))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0] if __doc__ else None)
    ap.add_argument("--check", action="store_true",
                    help="write nothing; exit 1 if a file differs from what would be written")
    args = ap.parse_args(argv)
    status = 0
    for path, render in TARGETS.items():
        text = render()
        if args.check:
            d = diff(path, text)
            if d:
                print(d, end="")
                status = 1
        else:
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(text, encoding="utf-8")
            print(f"wrote {path.relative_to(ROOT)}")
    return status


if __name__ == "__main__":
    sys.exit(main())
