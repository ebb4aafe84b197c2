"""Schemathesis over /openapi.json: every operation, on both arms, with valid and invalid
inputs, on an open server and on a token-protected one (with the operator's token, and with
none). Hostile input must never crash anything:

- no 500, and no other 5xx than the device codes (502/503/504 with `device_error`,
  `corrupt_reply`, `link_down`, `busy`, `device_timeout`; never `internal_error`);
- every error body is exactly `{"detail", "code"}`;
- responses conform to the schema (status code documented, body valid, JSON content type);
- without a token everything but health is 401 `unauthorized`, malformed body or not;
- afterwards both arms' link tasks and motion executors are alive, the links up and the
  telemetry still advancing, and the last-resort error handler was never hit.

The number of generated cases per operation, arm and mode is ARMSERVER_FUZZ_CASES (default 3:
about 9 per operation on the open server, about 35 s for the module; `make fuzz` runs 300). Valid
cases are per arm (the `arm` path parameter fixed), invalid ones break the arm name as well. The
default's short run draws them once, on the open server, and sends the same requests to the
token-protected one (`_DRAWN`: Hypothesis, derandomized, would draw them again the same, and the
drawing was two thirds of the module's time); `make fuzz` draws anew for each.
Positive runs also draw bodies that pass every check (see `_valid_bodies`), so moves, line
paths and set-points really run. Between cases the fuzzer's side
effects that would starve later cases are undone: a latched estop is released, a lease taken is
dropped and a long queue of (valid, slow) motions is stopped. A move with `wait: true` is
capped at a short duration (a line move, which has none, does not wait) so one case cannot hold
the run for ten minutes.
"""

from __future__ import annotations

import copy
import json
import os
import time
from collections import Counter
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import schemathesis
from conftest import make_settings
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st
from hypothesis.errors import Unsatisfiable
from schemathesis import GenerationMode
from schemathesis.checks import (
    content_type_conformance,
    response_schema_conformance,
    status_code_conformance,
)
from schemathesis.core import NOT_SET
from schemathesis.python import asgi as st_asgi

from app.arms import model_for
from app.arms.loading import load_profile
from app.web.factory import create_app

pytestmark = pytest.mark.slow

CASES = int(os.environ.get("ARMSERVER_FUZZ_CASES", "3"))
#: The suite's short run is the same every time; a long run (`make fuzz`) explores anew.
DETERMINISTIC = CASES <= 50
ARMS = ("rbe3001", "angler")
OPERATOR = "op"
VIEWER = "view"
#: 5xx the contract allows: the device's codes. Anything else (500, `internal_error`) is a bug.
DEVICE_CODES = {502: {"device_error", "corrupt_reply"}, 503: {"link_down", "busy"},
                504: {"device_timeout"}}
OPEN_PATHS = {"/api/v1/health"}
#: A single case may not take longer than this, s (a capped `wait: true` move ends well within).
CALL_TIMEOUT_S = 20.0
#: Longest move a `wait: true` case may ask for, s.
WAIT_CAP_S = 1.0


# ---------------------------------------------------------------- the apps under test


class Target:
    """An app whose lifespan schemathesis runs in its own event-loop thread (the portal)."""

    def __init__(self, **settings: Any) -> None:
        self.app = create_app(make_settings(**settings))
        self.schema = schemathesis.openapi.from_asgi("/openapi.json", self.app)  # starts it
        self.portal = st_asgi._get_portal()
        self.statuses: Counter[tuple[str, int, str]] = Counter()
        self.wait_ready()

    def run(self, fn: Any) -> Any:
        """Run `async fn()` in the app's event loop (its services belong to that loop)."""
        return self.portal.call(fn)

    @property
    def services(self) -> dict[str, Any]:
        return self.app.state.services  # type: ignore[no-any-return]

    def wait_ready(self, timeout: float = 10.0) -> None:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            svcs = self.services
            if svcs and all(s.hub.latest is not None and not s.driver.stale
                            for s in svcs.values()):
                return
            time.sleep(0.02)
        raise TimeoutError("the simulated arms did not answer in time")

    def reset(self) -> None:
        """Undo what would starve later cases: estop, leases, a long queue."""
        async def _reset() -> None:
            leases = self.app.state.leases
            for name, svc in self.services.items():
                held = leases.held(name)
                if held is not None:
                    await leases.release(name, held.id)
                await svc.release_estop()
                ex = svc.motion
                cur = ex.current
                if len(ex._queue) > 2 or (cur is not None and cur.planned_duration > 3.0):
                    await svc.stop()
        self.run(_reset)

    def check_alive(self) -> None:
        """Both arms' link tasks and executors running, links up, telemetry advancing."""
        for name, svc in self.services.items():
            assert svc.driver._task is not None and not svc.driver._task.done(), name
            assert svc.motion._task is not None and not svc.motion._task.done(), name
        seqs = {n: s.hub.latest["seq"] for n, s in self.services.items()}
        deadline = time.monotonic() + 5.0
        while time.monotonic() < deadline:
            if all(s.hub.latest["seq"] > seqs[n] + 5 and s.driver.link.state.value == "up"
                   and not s.driver.stale for n, s in self.services.items()):
                break
            time.sleep(0.05)
        for name, svc in self.services.items():
            assert svc.driver.link.state.value == "up", (name, svc.driver.link.last_error)
            assert svc.hub.latest["seq"] > seqs[name] + 5, f"{name}: telemetry stopped"
        assert self.app.state.internal_errors == 0, "the last-resort error handler was hit"


@pytest.fixture(scope="module")
def targets() -> Iterator[dict[str, Target]]:
    out = {"open": Target(), "tokens": Target(operator_tokens=OPERATOR, viewer_tokens=VIEWER)}
    started = time.monotonic()
    try:
        yield out
    finally:
        _write_report(out, time.monotonic() - started)
        st_asgi.shutdown_lifespans()  # stop the simulated arms: nothing runs on after us


REPORT = Path(__file__).resolve().parents[1] / "test-output" / "fuzz-report.txt"


def _write_report(targets: dict[str, Target], seconds: float) -> None:
    """The figures `make fuzz` prints: calls, answers by status, 5xx, internal errors."""
    lines = [f"schemathesis over /openapi.json: {CASES} cases per operation, arm and mode; "
             f"{seconds:.0f} s"]
    for name, t in targets.items():
        by_status: Counter[int] = Counter()
        for (_, status, _), n in t.statuses.items():
            by_status[status] += n
        total = sum(by_status.values())
        five = sum(n for st, n in by_status.items() if st >= 500)
        ops = len({label for (label, _, _) in t.statuses})
        internal = getattr(t.app.state, "internal_errors", 0)
        lines.append(f"  {name:7} server: {total} calls over {ops} operations; "
                     f"5xx {five} (device codes only), 500 {by_status.get(500, 0)}, "
                     f"internal errors {internal}")
        lines.append("          by status: " + ", ".join(f"{st}: {n}" for st, n
                                                       in sorted(by_status.items())))
    REPORT.parent.mkdir(exist_ok=True)
    REPORT.write_text("\n".join(lines) + "\n")


# ---------------------------------------------------------------- valid inputs, mixed in

#: Random floats almost never land inside the joint limits, so positive runs also draw bodies
#: that pass every check (moves and set-points within the limits, tips the arm reaches): the
#: motion paths, the executor and the devices get exercised, not only the refusals.
MODELS = {a: model_for(load_profile(a)) for a in ARMS}


def _joints(arm: str) -> st.SearchStrategy[list[float]]:
    m = MODELS[arm]
    return st.tuples(*(st.floats(float(lo), float(hi)) for lo, hi in zip(m.lower, m.upper,
                                                                        strict=True))).map(list)


def _move_extras() -> st.SearchStrategy[dict[str, Any]]:
    return st.fixed_dictionaries({}, optional={
        "duration": st.floats(0.05, 3.0), "speed": st.floats(0.05, 1.0),
        "mode": st.sampled_from(["queue", "replace"]), "wait": st.booleans()})


def _valid_bodies(op: Any, arm: str) -> st.SearchStrategy[Any] | None:
    path = op.path.removeprefix("/api/v1/arms/{arm}")
    m = MODELS[arm]
    if path in ("/move/joints", "/plan/joints"):
        return st.builds(lambda q, x: {"positions": q, **x}, _joints(arm), _move_extras())
    if path == "/kinematics/forward":
        return _joints(arm).map(lambda q: {"positions": q})
    if path in ("/move/pose", "/plan/pose", "/kinematics/inverse"):
        def pose(q: list[float], x: dict[str, Any], line: bool) -> dict[str, Any]:
            tip = m.fk(q)
            body = {"x": float(tip[0]), "y": float(tip[1]), "z": float(tip[2])}
            if path != "/kinematics/inverse":
                body.update(x, path="line" if line else "joint")
            return body
        return st.builds(pose, _joints(arm), _move_extras(), st.booleans())
    if path == "/rbe3001/set-pid":
        return _joints(arm).map(lambda q: {"joints": [
            {"position_ticks": float(t)} for t in m.transmission.to_ticks(q)]})
    return None


def _strategy(op: Any, arm: str | None, mode: GenerationMode) -> st.SearchStrategy[Any]:
    pp = {"arm": arm} if arm is not None and mode is GenerationMode.POSITIVE else None
    strategy = op.as_strategy(generation_mode=mode, path_parameters=pp)
    if arm is None or mode is not GenerationMode.POSITIVE:
        return strategy
    bodies = _valid_bodies(op, arm)
    if bodies is None:
        return strategy
    valid = bodies.map(lambda b: op.Case(path_parameters={"arm": arm}, body=b,
                                         media_type="application/json"))
    return st.one_of(strategy, valid)


# ---------------------------------------------------------------- checks of one answer


def _cap_waits(case: Any) -> None:
    body = case.body
    if isinstance(body, dict) and body.get("wait") is True:
        if body.get("path") == "line":  # a line runs at the tip's speed limit: no duration
            body["wait"] = False
            return
        d = body.get("duration")
        if not isinstance(d, (int, float)) or isinstance(d, bool) or d > WAIT_CAP_S:
            body["duration"] = WAIT_CAP_S


def _check_answer(case: Any, response: Any, *, authorized: bool) -> None:
    status = response.status_code
    where = f"{case.method} {case.formatted_path} body={case.body!r:.300} -> {status} " \
            f"{response.text[:300]}"
    assert status != 500, where
    if status >= 500:
        code = response.json().get("code")
        assert code in DEVICE_CODES.get(status, set()), where
    if status >= 400:
        body = response.json()
        assert isinstance(body, dict) and set(body) == {"detail", "code"}, where
        assert isinstance(body["code"], str) and body["code"], where
    if not authorized and case.path not in OPEN_PATHS:
        assert status == 401, where
        assert response.json()["code"] == "unauthorized", where
        assert response.headers.get("www-authenticate") == ["Bearer"], where


#: The cases each (operation, arm, mode) was given, as drawn in the module's first run of it:
#: the later runs (the token-protected server's, with a token and without) send the same
#: requests again. With `derandomize` Hypothesis would draw them again the same, and drawing
#: them is most of the module's time (a case 44 ms, a call a few; session 34). `make fuzz`
#: (not DETERMINISTIC) draws anew in each run.
_DRAWN: dict[tuple[str, str | None, GenerationMode], list[dict[str, Any]]] = {}


def _copied(fields: dict[str, Any]) -> dict[str, Any]:
    """A deep copy of a case's fields (schemathesis' "no body" is one object, kept)."""
    return {k: v if v is NOT_SET else copy.deepcopy(v) for k, v in fields.items()}


def _snapshot(case: Any) -> dict[str, Any]:
    """What rebuilds `case` on another server's operation (`op.Case(**_copied(snapshot))`:
    a call changes its case), taken before the call."""
    return _copied({"method": case.method, "path_parameters": case.path_parameters,
                    "headers": dict(case.headers or {}), "cookies": case.cookies,
                    "query": case.query, "body": case.body, "media_type": case.media_type,
                    "multipart_content_types": case.multipart_content_types,
                    "_meta": case._meta})


def _fuzz(target: Target, headers: dict[str, str], authorized: bool,
          modes: tuple[GenerationMode, ...] = (GenerationMode.POSITIVE, GenerationMode.NEGATIVE),
          arms: tuple[str | None, ...] = ARMS) -> None:
    checks = [status_code_conformance, content_type_conformance, response_schema_conformance]
    for result in target.schema.get_all_operations():
        op = result.ok()
        has_arm = "{arm}" in op.path
        runs = [(arm, GenerationMode.POSITIVE) for arm in (arms if has_arm else (None,))
                if GenerationMode.POSITIVE in modes]
        if GenerationMode.NEGATIVE in modes:  # the arm is part of what gets broken
            runs.append((None, GenerationMode.NEGATIVE))
        for arm, mode in runs:
            def attempt(case: Any) -> None:
                _cap_waits(case)
                response = case.call(headers=headers, timeout=CALL_TIMEOUT_S)
                target.statuses[(op.label, response.status_code, _code(response))] += 1
                _check_answer(case, response, authorized=authorized)
                if mode is GenerationMode.POSITIVE or response.status_code < 400:
                    case.validate_response(response, checks=checks, headers=headers)
                target.reset()

            key = (op.label, arm, mode)
            if DETERMINISTIC and key in _DRAWN:
                for snapshot in _DRAWN[key]:
                    attempt(op.Case(**_copied(snapshot)))
                continue
            drawn = _DRAWN.setdefault(key, []) if DETERMINISTIC else []

            @settings(max_examples=CASES, deadline=None, database=None,
                      derandomize=DETERMINISTIC,
                      phases=[Phase.explicit, Phase.generate],
                      suppress_health_check=list(HealthCheck))
            @given(case=_strategy(op, arm, mode))
            def one(case: Any) -> None:
                drawn.append(_snapshot(case))
                attempt(case)

            try:
                one()
            except Unsatisfiable:
                if mode is GenerationMode.POSITIVE:
                    raise  # nothing to break in an operation without inputs: fine


def _code(response: Any) -> str:
    try:
        body = response.json()
    except (ValueError, json.JSONDecodeError):
        return "-"
    return str(body.get("code", "-")) if isinstance(body, dict) else "-"


# ---------------------------------------------------------------- the runs


def test_fuzz_open_server(targets: dict[str, Target]) -> None:
    t = targets["open"]
    _fuzz(t, {}, authorized=True)
    t.check_alive()
    assert any(st == 202 for (_, st, _) in t.statuses), "no move was ever accepted"


def test_fuzz_with_operator_token(targets: dict[str, Target]) -> None:
    t = targets["tokens"]
    _fuzz(t, {"Authorization": f"Bearer {OPERATOR}"}, authorized=True,
          modes=(GenerationMode.POSITIVE,))
    t.check_alive()


def test_fuzz_without_token_is_401_everywhere(targets: dict[str, Target]) -> None:
    t = targets["tokens"]
    _fuzz(t, {}, authorized=False)
    t.check_alive()
