"""What a telemetry client sends is parsed within bounds (issue 22, item 12), over a real uvicorn
server on a loopback port with the `websockets` client, as in test_ws_telemetry.py.

A `{"rate": 1000...0}` of 400 digits used to raise OverflowError out of the socket: a traceback
in the log, the last-resort error handler hit, and the socket dropped with no close code. Now
every malformed or out-of-range message gets a close code and a reason a person can act on
(1008; 1003 for a binary message; 1009 over the size limit), with nothing logged above debug.
"""

from __future__ import annotations

import asyncio
import json
import logging
import time
from collections.abc import Iterator
from typing import Any

import pytest
from conftest import LiveServer, serve_live
from websockets.asyncio.client import ClientConnection, connect
from websockets.exceptions import ConnectionClosed

from app.client.core import ws_close_error
from app.web.routes.telemetry import (
    MAX_MESSAGE_DEPTH,
    MAX_RATE_HZ,
    MIN_RATE_HZ,
    BadMessage,
    parse_message,
)

WS = "/api/v1/arms/{arm}/telemetry"
#: How long a refused socket may take to close, s (it closes at once; the bound is for a busy
#: machine).
CLOSE_WITHIN_S = 10.0

HUGE = "1" + "0" * 400

#: (id, message, close code, a fragment of the reason)
REFUSED: list[tuple[str, str | bytes, int, str]] = [
    ("huge-int-rate", '{"rate": ' + HUGE + "}", 1008, "out of range"),
    ("huge-negative-int-rate", '{"rate": -' + HUGE + "}", 1008, "out of range"),
    ("huge-int-elsewhere", '{"rate": 10, "x": ' + HUGE + "}", 1008, "out of range"),
    ("float-1e400", '{"rate": 1e400}', 1008, "out of range"),
    ("float-minus-1e400", '{"rate": -1e400}', 1008, "out of range"),
    ("NaN", '{"rate": NaN}', 1008, "NaN is not a number"),
    ("Infinity", '{"rate": Infinity}', 1008, "Infinity is not a number"),
    ("minus-Infinity", '{"rate": -Infinity}', 1008, "-Infinity is not a number"),
    ("string-nan", '{"rate": "nan"}', 1008, "finite"),
    ("string-1e400", '{"rate": "1e400"}', 1008, "finite"),
    ("string-word", '{"rate": "fast"}', 1008, "rate must be a number"),
    ("bool", '{"rate": true}', 1008, "rate must be a number"),
    ("list", '{"rate": [10]}', 1008, "rate must be a number"),
    ("object", '{"rate": {"hz": 10}}', 1008, "rate must be a number"),
    ("nested-arrays", "[" * 2000 + "]" * 2000, 1008, "nested deeper"),
    ("nested-objects", '{"a":' * 600 + "1" + "}" * 600, 1008, "nested deeper"),
    ("nested-in-rate", '{"rate": ' + "[" * 9 + "]" * 9 + "}", 1008, "nested deeper"),
    ("unclosed-nesting", "[" * 3000, 1008, "nested deeper"),
    ("not-json", "hello", 1008, "not JSON"),
    ("broken-json", '{"rate": 5', 1008, "not JSON"),
    ("json-array", "[10]", 1008, "JSON object"),
    ("json-number", "10", 1008, "JSON object"),
    ("oversized-text", "x" * 10_000, 1009, ""),
    ("oversized-number", '{"rate": 1' + "0" * 5000 + "}", 1009, ""),
    ("binary", b"\x00\x01", 1003, "binary"),
]

#: Messages the socket takes (a rate, clamped as in the query, or a well-formed object it
#: does not know): it stays open.
TAKEN = [
    ("unknown-object", '{"hello": 1}'),
    ("huge-but-finite", '{"rate": 1e300}'),
    ("negative", '{"rate": -5}'),
    ("null", '{"rate": null}'),
    ("brackets-in-a-string", '{"rate": 10, "note": "' + "[{" * 40 + '\\"]"}'),
    ("numeric-string", '{"rate": "20"}'),
]


@pytest.fixture(scope="module")
def live() -> Iterator[LiveServer]:
    with serve_live() as server:
        yield server


async def _close_of(ws: ClientConnection) -> tuple[int | None, str]:
    """The close code and reason the server sends, reading whatever comes before it."""
    deadline = time.monotonic() + CLOSE_WITHIN_S
    try:
        while (left := deadline - time.monotonic()) > 0:
            await asyncio.wait_for(ws.recv(), left)
    except ConnectionClosed as exc:
        return (exc.rcvd.code, exc.rcvd.reason) if exc.rcvd is not None else (None, "")
    except TimeoutError:
        pass
    raise AssertionError("the socket stayed open")


async def _telemetry_within(ws: ClientConnection, seconds: float, want: int) -> int:
    """Telemetry messages received until `want` have come, or `seconds` pass."""
    got = 0
    deadline = time.monotonic() + seconds
    while got < want and (left := deadline - time.monotonic()) > 0:
        try:
            raw = await asyncio.wait_for(ws.recv(), left)
        except TimeoutError:
            break
        if json.loads(raw)["type"] == "telemetry":
            got += 1
    return got


def _no_error_logged(caplog: pytest.LogCaptureFixture) -> None:
    bad = [r for r in caplog.records if r.levelno >= logging.WARNING or r.exc_info]
    assert not bad, [f"{r.name}: {r.getMessage()}" for r in bad]


@pytest.mark.parametrize(("message", "code", "fragment"),
                         [pytest.param(m, c, f, id=i) for i, m, c, f in REFUSED])
async def test_a_bad_message_gets_a_close_code_and_no_traceback(
        live: LiveServer, caplog: pytest.LogCaptureFixture, message: str | bytes, code: int,
        fragment: str) -> None:
    caplog.set_level(logging.DEBUG)
    errors = live.app.state.internal_errors
    async with connect(live.ws_url + WS.format(arm="rbe3001") + "?rate=5") as ws:
        assert json.loads(await ws.recv())["type"] == "telemetry"
        await ws.send(message)
        got, reason = await _close_of(ws)
    assert got == code, (got, reason)
    assert fragment in reason, reason
    assert len(reason.encode()) <= 123
    assert live.app.state.internal_errors == errors, "the last-resort error handler was hit"
    _no_error_logged(caplog)


async def test_a_binary_message_closes_with_an_error_body_the_client_reads(
        live: LiveServer) -> None:
    async with connect(live.ws_url + WS.format(arm="angler")) as ws:
        await ws.recv()
        await ws.send(b"\xff" * 16)
        with pytest.raises(ConnectionClosed) as exc:
            async with asyncio.timeout(CLOSE_WITHIN_S):
                while True:
                    await ws.recv()
    assert exc.value.rcvd is not None and exc.value.rcvd.code == 1003
    err = ws_close_error(exc.value)
    assert err is not None and err.code == "invalid_request" and "binary" in err.detail


@pytest.mark.parametrize("message", [pytest.param(m, id=i) for i, m in TAKEN])
async def test_a_good_message_keeps_the_socket(live: LiveServer,
                                               caplog: pytest.LogCaptureFixture,
                                               message: str) -> None:
    caplog.set_level(logging.DEBUG)
    errors = live.app.state.internal_errors
    async with connect(live.ws_url + WS.format(arm="rbe3001") + "?rate=2") as ws:
        await ws.recv()
        await ws.send(message)
        await ws.send(json.dumps({"rate": 50}))
        # 2 Hz would give at most ~4 in 2 s: 20 messages say the socket is open and took the
        # last rate
        assert await _telemetry_within(ws, 10.0, 20) == 20
    assert live.app.state.internal_errors == errors
    _no_error_logged(caplog)


@pytest.mark.parametrize(("path", "code", "fragment"), [
    pytest.param(WS.format(arm="rbe3001") + "?rate=" + "x" * 400, 1008, "rate must be a number",
                 id="long-word-rate"),
    pytest.param(WS.format(arm="rbe3001") + "?rate=" + HUGE, 1008, "finite", id="huge-rate"),
    pytest.param(WS.format(arm="rbe3001") + "?rate=" + "%C3%A9" * 200, 1008, "rate",
                 id="long-non-ascii-rate"),
    pytest.param(WS.format(arm="%C3%A9" * 64), 4404, "unknown arm", id="long-non-ascii-arm"),
])
async def test_a_long_query_value_gets_a_short_close_reason(
        live: LiveServer, caplog: pytest.LogCaptureFixture, path: str, code: int,
        fragment: str) -> None:
    """A close reason over 123 bytes made the protocol library raise: no close code."""
    caplog.set_level(logging.DEBUG)
    errors = live.app.state.internal_errors
    async with connect(live.ws_url + path) as ws:
        got, reason = await _close_of(ws)
    assert got == code and fragment in reason, (got, reason)
    assert len(reason.encode()) <= 123
    assert live.app.state.internal_errors == errors
    _no_error_logged(caplog)


# ------------------------------------------------------------------ the parser alone


@pytest.mark.parametrize(("message", "fragment"),
                         [pytest.param(m, f, id=i) for i, m, c, f in REFUSED
                          if c == 1008 and isinstance(m, str)])
def test_parse_message_refuses(message: str, fragment: str) -> None:
    with pytest.raises(BadMessage, match=fragment.replace("[", r"\[")):
        parse_message(message, 10.0)


def test_parse_message_takes_rates_and_ignores_unknown_objects() -> None:
    assert parse_message('{"rate": 25}', 10.0) == 25.0
    assert parse_message('{"rate": 2.5e1, "x": [1, {"y": "[[[[[[[[[[["}]}', 10.0) == 25.0
    assert parse_message('{"rate": 1e300}', 10.0) == MAX_RATE_HZ
    assert parse_message('{"rate": -5}', 10.0) == MIN_RATE_HZ
    assert parse_message('{"rate": null}', 10.0) == 10.0
    assert parse_message('{"hello": 1}', 10.0) is None
    deep_ok = '{"a": ' + "[" * (MAX_MESSAGE_DEPTH - 1) + "]" * (MAX_MESSAGE_DEPTH - 1) + "}"
    assert parse_message(deep_ok, 10.0) is None
    with pytest.raises(BadMessage, match="nested deeper"):
        parse_message('{"a": ' + "[" * MAX_MESSAGE_DEPTH + "]" * MAX_MESSAGE_DEPTH + "}", 10.0)


def test_parse_message_is_quick_on_the_worst_message() -> None:
    """A 4 KiB message of brackets, digits or escapes parses in well under a millisecond each
    on an idle machine; the bound here is loose (a busy one) but catches a quadratic parse."""
    worst: list[Any] = ["[" * 4096, "1" * 4096, '{"a": "' + "\\\\" * 2040 + '"}',
                        '{"rate": "' + "[" * 4080 + '"}']
    t0 = time.perf_counter()
    for _ in range(20):
        for m in worst:
            try:
                parse_message(m, 10.0)
            except BadMessage:
                pass
    assert time.perf_counter() - t0 < 2.0
