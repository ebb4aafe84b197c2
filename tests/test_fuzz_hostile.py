"""Hostile inputs over every operation (issue 11): valid bodies with one thing made hostile.

Schemathesis draws a valid case for every operation (on both arms), then one of these is
done to it before it is sent:

- a number in the body becomes `true`, `false` or a numeric string (`"1"`): 422;
- a string in the body (or a key) gets a lone surrogate (`"\\ud800"`): a 4xx;
- a move's `speed` becomes tiny (1e-12 .. 3e-5): never a 5xx (422 when ruckig refuses);
- the `Host` becomes a foreign name: 400 `bad_host` on the open server;
- a write comes with a foreign `Origin` or `Sec-Fetch-Site: cross-site`: 403 `cross_origin` on
  the open server.

Whatever is sent: no 500, no `internal_error`, every error body is `{detail, code}`, and
afterwards both arms are alive and the last-resort handler was never hit. (A lone surrogate
travels as the JSON escape `\\ud800`: valid JSON, but not text.)
Cases per operation and arm: ARMSERVER_FUZZ_CASES, at least 6 (so that every hostile kind
is drawn); `make fuzz` runs 300.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import pytest
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st
from schemathesis import GenerationMode
from schemathesis.python import asgi as st_asgi
from test_fuzz_api import ARMS, CALL_TIMEOUT_S, CASES, DETERMINISTIC, DEVICE_CODES, Target
from test_fuzz_api import _strategy as valid_case

pytestmark = pytest.mark.slow

UNSAFE = {"POST", "PUT", "DELETE", "PATCH"}
FOREIGN_HOSTS = ["evil.example", "evil.example:8000", "127.0.0.1.nip.io", "localhost.evil.example"]
FOREIGN_ORIGINS = [{"Origin": "http://evil.example"}, {"Origin": "null"},
                   {"Origin": "http://testserver:8081"}, {"Sec-Fetch-Site": "cross-site"}]
NOT_NUMBERS = [True, False, "1", "0.5", "1e3"]
SURROGATES = ["\ud800", "\udfff", "a\ud83d", "\udc00z"]
TINY_SPEEDS = [1e-12, 1e-9, 1e-6, 3e-5]
MOVES = ("/move/joints", "/move/pose", "/plan/joints", "/plan/pose")


def _leaves(v: Any, path: tuple[Any, ...] = ()) -> Iterator[tuple[tuple[Any, ...], Any]]:
    if isinstance(v, dict):
        for k, x in v.items():
            yield from _leaves(x, (*path, k))
    elif isinstance(v, list):
        for i, x in enumerate(v):
            yield from _leaves(x, (*path, i))
    else:
        yield path, v


def _set(body: Any, path: tuple[Any, ...], value: Any) -> None:
    for p in path[:-1]:
        body = body[p]
    body[path[-1]] = value


def _numbers(body: Any) -> list[tuple[Any, ...]]:
    return [p for p, v in _leaves(body) if isinstance(v, (int, float))
            and not isinstance(v, bool) and p]


def _strings(body: Any) -> list[tuple[Any, ...]]:
    return [p for p, v in _leaves(body) if isinstance(v, str) and p]


@st.composite
def hostile(draw: st.DrawFn, op: Any, arm: str | None) -> tuple[Any, str, Any, dict[str, str]]:
    """(case, what was done, expected status or None, headers)."""
    case = draw(valid_case(op, arm, GenerationMode.POSITIVE))
    body = case.body if isinstance(case.body, (dict, list)) else None
    kinds = ["host"]
    if op.method.upper() in UNSAFE:
        kinds.append("origin")
    if body is not None and _numbers(body):
        kinds.append("number")
    if body is not None:
        kinds.append("surrogate")
    if isinstance(body, dict) and op.path.endswith(MOVES):
        kinds.append("speed")
    kind = draw(st.sampled_from(kinds))
    headers: dict[str, str] = {}
    expect: Any = None
    if kind == "host":
        headers["Host"] = draw(st.sampled_from(FOREIGN_HOSTS))
        expect = (400, "bad_host")
    elif kind == "origin":
        headers.update(draw(st.sampled_from(FOREIGN_ORIGINS)))
        expect = (403, "cross_origin")
    elif kind == "number":
        _set(body, draw(st.sampled_from(_numbers(body))), draw(st.sampled_from(NOT_NUMBERS)))
        expect = (422, "invalid_request")
    elif kind == "surrogate":
        bad = draw(st.sampled_from(SURROGATES))
        strings = _strings(body)
        if strings and draw(st.booleans()):
            path = draw(st.sampled_from(strings))
            _set(body, path, bad)
        elif isinstance(body, dict):
            body[bad] = 1  # an unknown key, and not text
        else:
            case.body = [bad]
        expect = "4xx"
    elif kind == "speed":
        body["speed"] = draw(st.sampled_from(TINY_SPEEDS))
        body.pop("duration", None)
        body["wait"] = False
        if op.path.endswith("/pose") and draw(st.booleans()):
            body["path"] = "line"  # a line is sampled densely: the slow case that hurt most
    return case, kind, expect, headers


@pytest.fixture(scope="module")
def open_target() -> Iterator[Target]:
    t = Target()
    try:
        yield t
    finally:
        st_asgi.shutdown_lifespans()


def test_hostile_inputs_never_crash_anything(open_target: Target) -> None:
    t = open_target
    seen: dict[str, int] = {}
    for result in t.schema.get_all_operations():
        op = result.ok()
        arms = ARMS if "{arm}" in op.path else (None,)
        for arm in arms:
            @settings(max_examples=max(CASES, 6), deadline=None, database=None,
                      derandomize=DETERMINISTIC, phases=[Phase.generate],
                      suppress_health_check=list(HealthCheck))
            @given(drawn=hostile(op, arm))
            def one(drawn: tuple[Any, str, Any, dict[str, str]]) -> None:
                case, kind, expect, headers = drawn
                r = case.call(headers=headers, timeout=CALL_TIMEOUT_S)
                seen[kind] = seen.get(kind, 0) + 1
                where = (f"{kind}: {case.method} {case.formatted_path} headers={headers} "
                         f"body={case.body!r:.300} -> {r.status_code} {r.text[:300]}")
                assert r.status_code != 500, where
                if r.status_code >= 500:
                    assert r.json().get("code") in DEVICE_CODES.get(r.status_code, set()), where
                if r.status_code >= 400:
                    body = r.json()
                    assert isinstance(body, dict) and set(body) == {"detail", "code"}, where
                if expect == "4xx":
                    assert 400 <= r.status_code < 500, where
                elif isinstance(expect, tuple):
                    assert (r.status_code, r.json()["code"]) == expect, where
                t.reset()

            one()
    t.check_alive()
    assert {"host", "origin", "number", "surrogate", "speed"} <= set(seen), seen
