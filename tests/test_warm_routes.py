"""Every route is built while the server starts (app/web/warm.py), not by its first request:
the first emergency stop pressed on a fresh server does the work the tenth does, not the
framework's route building as well (which made `bench/lab.py`'s estop p99 the first press on
each arm). Work is counted as Python calls on the HTTP thread (`sys.setprofile`), which a busy
machine does not change, not as time."""

from __future__ import annotations

import sys
from collections.abc import Awaitable, Callable
from typing import Any

import httpx

from app.web.middleware import API_PREFIX
from app.web.warm import warm_routes
from tests.conftest import make_settings, running_client


async def _calls(request: Callable[[], Awaitable[httpx.Response]]) -> tuple[int, int]:
    """(Python calls made on this thread while `request` ran, its status)."""
    n = 0

    def count(frame: Any, event: str, arg: Any) -> None:
        nonlocal n
        if event == "call":
            n += 1

    sys.setprofile(count)
    try:
        r = await request()
    finally:
        sys.setprofile(None)
    return n, r.status_code


async def _first_and_again(warm_start: bool) -> tuple[int, int]:
    """The Python calls of the first estop press on a fresh server and of the second."""
    async with running_client(make_settings(warm_start=warm_start)) as (_, client):
        press = f"{API_PREFIX}/arms/rbe3001/estop"
        first, status = await _calls(lambda: client.post(press))
        assert status == 200
        assert (await client.delete(press)).status_code == 200
        again, status = await _calls(lambda: client.post(press))
        assert status == 200
        assert (await client.delete(press)).status_code == 200
        return first, again


async def test_the_first_estop_press_costs_what_a_later_one_does() -> None:
    first, again = await _first_and_again(warm_start=True)  # the default (Settings)
    # unwarmed, the first press made about 25 times the calls of the second (FastAPI
    # building the arms' routers); the first warning line and such are small beside it
    assert first < 2 * again, (first, again)


async def test_without_a_warm_start_the_first_press_builds_the_routes() -> None:
    """`warm_start=False` (the suite's servers, conftest.make_settings) skips the warm-up: the
    first press is the one that builds the routers, so the test above is the warm-up's."""
    first, again = await _first_and_again(warm_start=False)
    assert first > 5 * again, (first, again)


async def test_the_warm_up_is_a_request_no_route_answers() -> None:
    async with running_client(make_settings(warm_start=True)) as (app, client):
        assert await warm_routes(app.router, API_PREFIX) == 404
        # nothing of it shows: the audit log has no entry for it
        r = await client.get(f"{API_PREFIX}/audit")
        assert r.status_code == 200
        assert "__warm_routes__" not in r.text
