"""Wait for the thing, not for a time (issue 22). A fixed sleep before an assert guesses how long
the thing takes: right on an idle laptop, wrong on a machine whose cores are busy. These wait
for the condition itself, as long as it takes up to a generous bound, and no longer.

    await wait_for(lambda: rec.status == "running", what="the move started")
    wait_until(lambda: keeper.renewals >= 3)                  # the same, from a plain thread
    await new_samples(svc.hub, 2)                             # samples taken after this point
    q = await held_still(lambda: svc.driver.positions, 1e-3)  # the arm settled

A sleep that is itself under test ("nothing happens for N ms", a rate over a window) stays a
sleep, with a comment saying so.
"""

from __future__ import annotations

import asyncio
import inspect
import time
from collections.abc import Callable
from typing import Any

import numpy as np

#: Long enough for a loaded two-core machine (CI's is slower than ours: a browser's page took
#: over 10 s there once); a test that passes waits far less.
TIMEOUT_S = 30.0

#: What is waited for: words, or a function giving them at the deadline (the state then).
What = str | Callable[[], str] | None


def _describe(cond: Callable[..., Any], what: What) -> str:
    if callable(what):
        try:
            return what()
        except Exception as exc:  # noqa: BLE001 - the description must not hide the timeout
            return f"{_describe(cond, None)} (describing it failed: {exc!r})"
    if what:
        return what
    try:
        return inspect.getsource(cond).strip()
    except (OSError, TypeError):
        return repr(cond)


async def wait_for(cond: Callable[[], Any], timeout: float = TIMEOUT_S, what: What = None,
                   every: float = 0.01) -> Any:
    """Until `cond()` (sync, or returning an awaitable) is truthy: its value. After `timeout`
    seconds an AssertionError naming `what`; an exception raised by `cond` counts as "not yet"
    (the last one is reported)."""
    deadline = time.monotonic() + timeout
    last_exc: BaseException | None = None
    while True:
        try:
            value = cond()
            if inspect.isawaitable(value):
                value = await value
        except Exception as exc:  # noqa: BLE001 - retried until the deadline, then reported
            last_exc, value = exc, None
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout} s waiting for {_describe(cond, what)}"
                                 + (f" (last error: {last_exc!r})" if last_exc else ""))
        await asyncio.sleep(every)


def wait_until(cond: Callable[[], Any], timeout: float = TIMEOUT_S, what: What = None,
               every: float = 0.02) -> Any:
    """`wait_for` for plain threads (blocking)."""
    deadline = time.monotonic() + timeout
    last_exc: BaseException | None = None
    while True:
        try:
            value = cond()
        except Exception as exc:  # noqa: BLE001 - retried until the deadline, then reported
            last_exc, value = exc, None
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout} s waiting for {_describe(cond, what)}"
                                 + (f" (last error: {last_exc!r})" if last_exc else ""))
        time.sleep(every)


async def new_samples(hub: Any, n: int = 1, timeout: float = TIMEOUT_S) -> None:
    """Until `n` samples have been published on `hub` (a TelemetryHub) since the call: the
    latest sample is then one taken after whatever the caller did before."""
    start = hub.published
    await wait_for(lambda: hub.published >= start + n, timeout,
                   f"{n} new sample(s) of {getattr(hub, 'arm', 'the arm')}")


async def held_still(positions: Callable[[], Any], tol: float, window: float = 0.2,
                     timeout: float = TIMEOUT_S) -> np.ndarray:
    """Until the positions (`positions()`, an array or None) move less than `tol` (each joint)
    over `window` seconds: the settled positions."""
    deadline = time.monotonic() + timeout
    last: Any = None
    while time.monotonic() < deadline:
        q0 = positions()
        if q0 is None:
            await asyncio.sleep(0.02)
            continue
        q0 = np.array(q0, dtype=float)
        await asyncio.sleep(window)  # the window over which "still" is judged
        q1 = positions()
        if q1 is not None:
            last = np.array(q1, dtype=float)
            if np.all(np.abs(last - q0) <= tol):
                return last
    raise AssertionError(f"never held still within {tol} over {window} s: {last}")


async def fresh_state(client: Any, arm: str, n: int = 3, api: str = "/api/v1") -> dict[str, Any]:
    """GET .../arms/{arm}/state (over an httpx AsyncClient) until its sample is `n` polls newer
    than the latest at the call: a sample taken after whatever the caller did before."""
    async def get() -> dict[str, Any]:
        r = await client.get(f"{api}/arms/{arm}/state")
        assert r.status_code == 200, r.text
        return dict(r.json())

    seq0 = (await get())["seq"]

    async def newer() -> dict[str, Any] | None:
        sample = await get()
        return sample if sample["seq"] >= seq0 + n else None

    return dict(await wait_for(newer, what=f"a new sample of {arm}"))
