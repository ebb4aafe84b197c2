"""A Dynamixel register write's HTTP side (issue 23): `RegisterWriteFastPath`
(app/arms/dynamixel/api.py) answers `PUT .../dynamixel/{id}/registers/{name}` inside every
gate without FastAPI's router and dependency solving, with the route's own functions.

What it must not change, each tested here through the real app and the simulated bus: every
answer byte for byte what the router gives (a query string sends a request down to the router,
so the same request is asked both ways), every refusal (token, role, lease, arm, Host, body,
the register's and the pass-through's checks, the estop) as before, the audit record of each
write in order, and what reaches the servo."""

from __future__ import annotations

import asyncio
import json
import time
from typing import Any

import httpx
import pytest
from _wait import wait_for
from fastapi import FastAPI

from app.arms.dynamixel.api import RegisterWriteFastPath
from tests.conftest import make_settings, running_client

API = "/api/v1"
DX = f"{API}/arms/angler/dynamixel"
GOAL = f"{DX}/3/registers/goal_position"
ALICE, BOB, TEACH, VIEW = "tok-alice-1", "tok-bob-2", "tok-teach-4", "tok-view-5"


def _settings(**over: Any) -> Any:
    return make_settings(operator_tokens=f"alice:{ALICE},bob:{BOB}",
                         instructor_tokens=f"teach:{TEACH}", viewer_tokens=VIEW,
                         lease_ttl_s=30.0, **over)


def H(token: str | None = None, lease: str | None = None) -> dict[str, str]:
    h = {"Authorization": f"Bearer {token}"} if token else {}
    if lease is not None:
        h["X-Arm-Lease"] = lease
    return h


async def both(c: httpx.AsyncClient, path: str, body: Any = None, *,
               headers: dict[str, str] | None = None, content: bytes | None = None,
               ) -> tuple[httpx.Response, httpx.Response]:
    """The same PUT through the layer and down to the router (a query string: the router
    ignores it, the layer does not take it)."""
    kw: dict[str, Any] = {"headers": headers or {}}
    if content is not None:
        kw["content"] = content
    else:
        kw["json"] = body
    fast = await c.put(path, **kw)
    full = await c.put(path + "?via=router", **kw)
    return fast, full


def same(fast: httpx.Response, full: httpx.Response) -> None:
    assert (fast.status_code, fast.content) == (full.status_code, full.content)
    for name in ("content-type", "content-length", "www-authenticate"):
        assert fast.headers.get(name) == full.headers.get(name), name


class _Below:
    """What lies below the layer (the router), as far as the layer can tell: counts calls and
    answers 599."""

    def __init__(self) -> None:
        self.calls: list[tuple[str, bytes]] = []

    async def __call__(self, scope: Any, receive: Any, send: Any) -> None:
        message = await receive()
        self.calls.append((scope["path"], message.get("body", b"")))
        await send({"type": "http.response.start", "status": 599, "headers": []})
        await send({"type": "http.response.body", "body": b""})


async def _call(layer: Any, path: str, body: bytes, headers: list[tuple[bytes, bytes]],
                query: bytes = b"") -> tuple[int, bytes]:
    scope = {"type": "http", "method": "PUT", "path": path, "raw_path": path.encode(),
             "query_string": query, "root_path": "", "headers": headers,
             "client": ("127.0.0.1", 1), "server": ("127.0.0.1", 2), "scheme": "http",
             "http_version": "1.1", "asgi": {"version": "3.0"}}
    got: list[Any] = []

    async def receive() -> Any:
        return {"type": "http.request", "body": body, "more_body": False}

    async def send(m: Any) -> None:
        got.append(m)
    await layer(scope, receive, send)
    return got[0]["status"], b"".join(m.get("body", b"") for m in got[1:])


async def test_which_requests_the_layer_takes(
        app_and_client: tuple[FastAPI, httpx.AsyncClient]) -> None:
    app, _ = app_and_client
    below = _Below()
    layer = RegisterWriteFastPath(below, app_ref=app)
    json_ct = [(b"content-type", b"application/json")]
    # a write it takes: answered here (the LED: no motion), the router never called
    status, body = await _call(layer, f"{DX}/1/registers/led", b'{"raw": 1}', json_ct)
    assert status == 200 and json.loads(body)["raw"] == 1 and below.calls == []
    # everything else goes below, the body replayed whole
    down = [
        (f"{DX}/1/registers/led", b'{"raw": 1}', json_ct, b"via=router"),  # a query string
        (f"{DX}/1/registers/led", b'{"raw": 1}', [(b"content-type", b"text/plain")], b""),
        (f"{DX}/1/registers/led", b'{"raw": 1}', [], b""),  # no content type
        (f"{DX}/253/registers/led", b'{"raw": 1}', json_ct, b""),  # id over 252
        (f"{DX}/+1/registers/led", b'{"raw": 1}', json_ct, b""),  # not plain digits
        (f"{DX}/1/registers/" + "x" * 65, b'{"raw": 1}', json_ct, b""),  # name over 64
        (f"{DX}/1/registers/led", b'{"raw": "1"}', json_ct, b""),  # the body refused
        (f"{DX}/1/registers/led", b'{"raw": 1.5}', json_ct, b""),
        (f"{DX}/1/registers/led", b'{"raw": 1, "x": 2}', json_ct, b""),
        (f"{DX}/1/registers/led", b'{"raw": 1', json_ct, b""),  # not JSON
        (f"{DX}/1/registers/led/", b'{"raw": 1}', json_ct, b""),
        (f"{DX}/1/registers/led", b'{"raw": 1}', json_ct + [(b"x-arm-lease", b"l" * 129)],
         b""),
    ]
    for path, b, headers, query in down:
        status, _ = await _call(layer, path, b, headers, query)
        assert status == 599 and below.calls[-1] == (path, b), (path, b, headers, query)
    assert len(below.calls) == len(down)


async def test_answers_as_the_router_does(
        app_and_client: tuple[FastAPI, httpx.AsyncClient]) -> None:
    """Byte for byte, success and every refusal of the route's own checks."""
    app, c = app_and_client
    same(*await both(c, f"{DX}/1/registers/led", {"raw": 1}))
    same(*await both(c, f"{DX}/1/registers/led", {"raw": 0}))
    for path, body, code in [
        (f"{DX}/1/registers/no_such_item", {"raw": 1}, "unknown_register"),
        (f"{DX}/1/registers/present_position", {"raw": 1}, "read_only"),
        (f"{DX}/1/registers/led", {"raw": 7}, "out_of_range"),
        (f"{DX}/9/registers/goal_position", {"raw": 100}, "unknown_id"),
        (f"{DX}/1/registers/baud_rate", {"raw": 1}, "in_use"),
        (GOAL, {"raw": 4000}, "joint_limit"),  # theta3's limit is 1.57 rad
        (f"{API}/arms/nope/dynamixel/1/registers/led", {"raw": 1}, "unknown_arm"),
        (f"{API}/arms/rbe3001/dynamixel/1/registers/led", {"raw": 1}, "not_supported"),
    ]:
        fast, full = await both(c, path, body)
        same(fast, full)
        assert fast.json()["code"] == code, (path, fast.text)
    # the router's own 422s, for what the layer leaves to it
    for content, code in [(b'{"raw": "1"}', "invalid_request"), (b'{"raw": 1', "invalid_json"),
                          (b"", "invalid_request")]:
        r = await c.put(f"{DX}/1/registers/led", content=content,
                        headers={"content-type": "application/json"})
        assert r.status_code == 422 and r.json()["code"] == code, r.text
    # the estop: a goal refused, torque off allowed, both ways alike
    assert (await c.post(f"{API}/arms/angler/estop")).status_code == 200
    fast, full = await both(c, GOAL, {"raw": 10})
    same(fast, full)
    assert fast.json()["code"] == "estop_latched"
    same(*await both(c, f"{DX}/3/registers/torque_enable", {"raw": 0}))
    assert app.state.internal_errors == 0


async def test_tokens_roles_leases_and_host_as_before() -> None:
    async with running_client(_settings()) as (_, c):
        for headers, status, code in [
            (H(), 401, "unauthorized"), (H("not-a-token"), 401, "unauthorized"),
            (H(VIEW), 403, "forbidden"),
        ]:
            fast, full = await both(c, f"{DX}/1/registers/led", {"raw": 1}, headers=headers)
            same(fast, full)
            assert (fast.status_code, fast.json()["code"]) == (status, code)
        # alice leases the angler: bob is refused with or without an id, alice with a wrong one
        r = await c.post(f"{API}/arms/angler/lease", headers=H(ALICE))
        assert r.status_code == 201, r.text
        lid = r.json()["id"]
        for headers in (H(BOB), H(BOB, lid[:-1] + "x"), H(ALICE, "wrong"), H(ALICE)):
            fast, full = await both(c, f"{DX}/1/registers/led", {"raw": 1}, headers=headers)
            same(fast, full)
            assert (fast.status_code, fast.json()["code"]) == (409, "leased")
        fast, full = await both(c, f"{DX}/1/registers/led", {"raw": 1}, headers=H(ALICE, lid))
        same(fast, full)
        assert fast.status_code == 200
        # a Host the server does not answer to (open server): refused outside the layer
    async with running_client(make_settings()) as (_, c):
        r = await c.put(f"{DX}/1/registers/led", json={"raw": 1},
                        headers={"host": "evil.example"})
        assert r.status_code == 400 and r.json()["code"] == "bad_host"
        r = await c.put(f"{DX}/1/registers/led", json={"raw": 1},
                        headers={"origin": "http://evil.example"})
        assert r.status_code == 403 and r.json()["code"] == "cross_origin"
        r = await c.put(f"{DX}/1/registers/led", content=b'{"raw": 1' + b" " * 70_000 + b"}",
                        headers={"content-type": "application/json"})
        assert r.status_code == 413 and r.json()["code"] == "too_large"


async def test_a_goal_moves_the_servo_and_is_audited_in_order() -> None:
    async with running_client(_settings()) as (_, c):
        async def reg(name: str) -> int:
            r = await c.get(f"{DX}/3/registers/{name}", headers=H(ALICE))
            assert r.status_code == 200, r.text
            raw: int = r.json()["raw"]
            return raw
        start = await reg("present_position")
        t0 = time.time()
        goals = [start + 20, start + 40, start + 60]
        for g in goals:
            # each goal once the last has been taken up (the step rule paces pass-through)
            r = await c.put(GOAL, json={"raw": g}, headers=H(ALICE))
            assert r.status_code == 200, r.text
            assert r.json()["raw"] == g and r.json()["name"] == "goal_position"
            assert await reg("goal_position") == g  # on the servo, read back over the bus
            await wait_for(lambda g=g: _near(reg("present_position"), g),
                           what=f"servo 3 at its goal {g}")
        r = await c.put(GOAL, json={"raw": 4000}, headers=H(BOB))  # refused: joint limit
        assert r.status_code == 422
        r = await c.put(GOAL, json={"raw": start}, headers=H(VIEW))  # refused: a gate's
        assert r.status_code == 403

        async def rows() -> list[dict[str, Any]]:
            r = await c.get(f"{API}/audit", params={"since": t0}, headers=H(TEACH))
            assert r.status_code == 200, r.text
            out: list[dict[str, Any]] = r.json()
            return out
        got = await wait_for(lambda: _complete(rows), what="the goals' records, completed")
        assert [(x["name"], x["method"], x["route"], x["status"], x["code"], x["summary"])
                for x in reversed(got) if x["kind"] != "refusals"] == [
            ("alice", "PUT", GOAL, 200, None, f'{{"raw":{g}}}') for g in goals] + [
            ("bob", "PUT", GOAL, 422, "joint_limit", '{"raw":4000}')]
        assert any(x["kind"] == "refusals" and x["code"] == "forbidden" for x in got)
        assert all(x["arm"] == "angler" for x in got if x["kind"] != "refusals")


async def _near(value: Any, goal: int) -> bool:
    return abs(await value - goal) < 2


async def _complete(rows: Any) -> list[dict[str, Any]] | None:
    got: list[dict[str, Any]] = await rows()
    mine = [x for x in got if x["kind"] != "refusals"]
    return got if len(mine) == 4 and all(x["status"] is not None for x in mine) else None


@pytest.mark.parametrize("n", [3])
async def test_no_record_lost_when_the_answer_goes_first(n: int) -> None:
    """Each write's record is completed with its status even when the next write is asked
    the moment its answer arrives: n writes back to back, n records, in order."""
    async with running_client(_settings()) as (_, c):
        t0 = time.time()
        for k in range(n):
            r = await c.put(f"{DX}/1/registers/led", json={"raw": k % 2}, headers=H(ALICE))
            assert r.status_code == 200

        async def done() -> list[dict[str, Any]] | None:
            r = await c.get(f"{API}/audit", params={"since": t0}, headers=H(TEACH))
            got: list[dict[str, Any]] = r.json()
            return got if len(got) == n and all(x["status"] == 200 for x in got) else None
        got = await wait_for(done, what="the writes' records")
        assert [x["summary"] for x in reversed(got)] == [f'{{"raw":{k % 2}}}' for k in range(n)]


async def test_a_long_request_keeps_its_start_record_and_its_place() -> None:
    """A request that runs on gets its start record while it runs (the kill -9 case,
    tests/test_audit_inflight.py), before the short writes that came after it; those are
    recorded whole once answered; all in the order they passed the gates."""
    async with running_client(_settings(), headers=H(ALICE)) as (_, c):
        t0 = time.time()
        move = asyncio.create_task(c.post(f"{API}/arms/rbe3001/move/joints", json={
            "positions": [0.3, 0.6, 0.2], "speed": 0.3, "wait": True}))

        async def rows() -> list[dict[str, Any]]:
            r = await c.get(f"{API}/audit", params={"since": t0}, headers=H(TEACH))
            out: list[dict[str, Any]] = r.json()
            return out
        await wait_for(lambda: _has(rows, lambda x: x[-1]["status"] is None),
                       what="the move's start record")
        for k in range(3):
            r = await c.put(f"{DX}/1/registers/led", json={"raw": k % 2})
            assert r.status_code == 200
        got = await wait_for(lambda: _has(rows, lambda x: len(x) == 4), what="four records")
        assert not move.done()
        assert [(x["route"].rsplit("/", 1)[-1], x["status"]) for x in reversed(got)] == [
            ("joints", None), ("led", 200), ("led", 200), ("led", 200)]
        assert (await move).status_code == 200
        got = await wait_for(lambda: _has(rows, lambda x: x[-1]["status"] == 200),
                             what="the move's record completed")
        times = [x["time"] for x in reversed(got)]
        assert times == sorted(times)


async def _has(rows: Any, cond: Any) -> list[dict[str, Any]] | None:
    got: list[dict[str, Any]] = await rows()
    if not got:
        return None
    try:
        return got if cond(got) else None
    except (IndexError, KeyError):
        return None
