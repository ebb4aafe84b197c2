"""A stateful property test of issue 22's safety core: a hypothesis state machine over the real
app (a uvicorn server on loopback, tokens on, the simulated arms, with or without the
profile's `raw_access`) that interleaves, on one arm:

- planned moves (`move/joints`, with and without `wait`, queued or replacing, some aimed
  through a keep-out zone), `stop`;
- pass-through position commands: rbe3001 SET_PID (small steps, steps far too big, a walk of
  small steps each waited for, and a chase: steps back to back, each as far ahead of the
  reported position as the route takes);
  angler `goal_position` by a single PUT and by a multi-id `sync-write`;
- keep-out zones (an instructor adds a box around a body point near the arm's path, or
  removes them) and a floor (just below the arm's lowest point, or none), homing (operator,
  instructor, un-home then home), estop press (its hold watched for 0.3 s) and release.

After every step, from every telemetry sample (a hub listener on the control thread, with
the simulated device's own setpoint read in the same call; tests/_safety_support.py):

(a) while the estop is latched the device's setpoint stays within max(8 ticks, 30 ms at the
    joint's limit) of where the arm was at the latch;
(b) no sample puts a body point inside a zone, or below a floor, accepted before it (the
    envelope's own point model and margins, less a tracking slack);
(c) no joint's measured speed exceeds 1.1 x its limit (GET /api/v1/arms/{arm} `max_velocity`).

Every answer is a success or one of the refusals the contract names for that route (never a
500), and these hold on each: a SET_PID step of 0.2 rad or more from where the arm is answers
422 `velocity_limit`; an operator's POST /home on an arm whose joints are all homed answers
409 `already_homed` (where some joints need homing: a declaration moves nothing on an arm with
none); a PUT /safety that adds a zone or raises the floor, accepted while one motion ran
throughout or while the arm moved, is a failure (409 `busy` is the contract).

ARMSERVER_SAFETY_SKIP=home,set_pid_chase leaves those rules out, and =busy,already_homed,
velocity_limit those contract checks (to look past one failure at the rest, a diagnosis).
Bounded: ARMSERVER_SAFETY_EXAMPLES examples (default 12) of at most ARMSERVER_SAFETY_STEPS steps
(default 15) per arm, within ARMSERVER_SAFETY_BUDGET_S (default 75 s; an example that would
start later is skipped); no shrinking (a failure prints its steps as they ran); the same
sequences each run unless ARMSERVER_SAFETY_RANDOM=1.
Serial: it measures joint speeds.
"""

from __future__ import annotations

import contextlib
import functools
import os
import time
from collections import Counter
from typing import Any

import httpx
import numpy as np
import pytest
from _safety_support import (
    ARMS,
    INSTRUCTOR,
    OPERATOR,
    LatchTracker,
    Recorder,
    auth,
    box,
    documented,
    estop_tolerance,
    goal_raw,
    motor_of,
    peak_speed,
    profiles,
    serve_live,
    set_pid_body,
    speed_violations,
    token_settings,
    wait_samples_sync,
    zone_hits,
)
from hypothesis import HealthCheck, Phase, settings
from hypothesis import strategies as st
from hypothesis.stateful import (
    RuleBasedStateMachine,
    initialize,
    invariant,
    precondition,
    rule,
    run_state_machine_as_test,
)

pytestmark = pytest.mark.serial

EXAMPLES = int(os.environ.get("ARMSERVER_SAFETY_EXAMPLES", "12"))
STEPS = int(os.environ.get("ARMSERVER_SAFETY_STEPS", "15"))
BUDGET_S = float(os.environ.get("ARMSERVER_SAFETY_BUDGET_S", "75"))
#: ARMSERVER_SAFETY_RANDOM=1: other sequences each run (default: the same, derandomized).
RANDOM = os.environ.get("ARMSERVER_SAFETY_RANDOM", "") not in ("", "0")
#: Rules left out (comma-separated names, e.g. `home`), or the contract checks `busy`,
#: `already_homed`, `velocity_limit`: to look past one failure at the rest (a diagnosis only).
SKIP = set(filter(None, os.environ.get("ARMSERVER_SAFETY_SKIP", "").split(",")))

#: How far a random move or goal goes from where the arm is, per joint (rad, m): the angler's
#: screws run at 6 mm/s, so their moves stay short.
SPAN = {"rbe3001": np.array([1.0, 0.6, 0.8]), "angler": np.array([0.008, 0.008, 1.2, 0.03])}
#: Keep-out box half sizes, m.
HALF = {"rbe3001": (0.01, 0.04), "angler": (0.003, 0.01)}
#: A SET_PID step this far from where the arm is (rad) is far beyond 30 ms at 1.5 rad/s,
#: whatever the arm did between the reading and the check: it must be `velocity_limit`.
BIG_STEP = 0.2
#: Moving, for the envelope's "while the arm is still moving": above this fraction of a
#: joint's limit in the samples on both sides of the request.
MOVING = 0.1

MOVE_CODES = {"keep_out", "joint_limit", "estop_latched", "busy", "not_homed", "unreachable",
              "fault", "velocity_limit"}
PASS_CODES = {"keep_out", "joint_limit", "velocity_limit", "estop_latched", "busy",
              "not_homed", "fault", "out_of_range"}
SAFETY_CODES = {"keep_out", "busy"}
HOME_CODES = {"busy", "already_homed", "estop_latched"}

unit = st.floats(-1.0, 1.0, allow_nan=False)
#: Figures over every example, printed at the end of each test (pytest -s).
STATS: dict[str, Counter[str]] = {}
PEAKS: dict[str, list[float]] = {}
HOLDS: dict[str, list[float]] = {}


def allowed(name: str, arm: str | None = None, when: Any = None) -> Any:
    """The one precondition of a rule: not skipped, on its arm, and `when(self)`."""
    return precondition(lambda self: name not in SKIP and (arm is None or self.ARM == arm)
                        and (when is None or when(self)))


def live(f: Any) -> Any:
    """A rule that does nothing in an example started past the time budget (no server)."""
    @functools.wraps(f)
    def run(self: Any, *args: Any, **kwargs: Any) -> Any:
        if self.live is None:
            return None
        return f(self, *args, **kwargs)
    return run


class SafetyMachine(RuleBasedStateMachine):
    ARM = "rbe3001"
    started_at = 0.0

    def __init__(self) -> None:
        super().__init__()
        self.stack = contextlib.ExitStack()
        self.live: Any = None
        self.latched = False

    # ------------------------------------------------------------ set-up

    @initialize(raw=st.booleans())
    def start(self, raw: bool) -> None:
        self.raw = raw
        if time.monotonic() - type(self).started_at > BUDGET_S:
            STATS.setdefault(self.ARM, Counter())["past the time budget"] += 1
            return  # past the time budget: every rule of this example does nothing
        self.live = self.stack.enter_context(serve_live(profiles(raw), token_settings()))
        self.http = self.stack.enter_context(httpx.Client(
            base_url=self.live.url, headers=auth(OPERATOR), timeout=30.0))
        self.url = f"/api/v1/arms/{self.ARM}"
        self.svc = self.live.app.state.services[self.ARM]
        self.model = self.svc.model
        joints = self.http.get(self.url).json()["joints"]
        self.vmax = np.array([j["max_velocity"] for j in joints], dtype=float)
        np.testing.assert_allclose(self.vmax, self.model.vmax)
        self.rec = Recorder(self.svc)
        self.stack.callback(self.rec.close)
        self.latch = LatchTracker(self.svc)
        self.checked = 0
        self.zones: list[dict[str, Any]] = []
        self.floor: float | None = None
        self.latched = False
        self.last_target: np.ndarray | None = None
        self.anchor: np.ndarray | None = None
        self.n_zone = 0
        self.stats = STATS.setdefault(self.ARM, Counter())
        self.stats[f"raw={raw}"] += 1
        wait_samples_sync(self.rec, lambda g: len(g) >= 5, 5.0)

    def teardown(self) -> None:
        try:
            if self.live is not None:
                # the last command's effects: until the arm is at rest (bounded), then judge
                with contextlib.suppress(AssertionError):
                    self._wait_rest(8.0)
                self.check()
                got = self.rec.samples
                if got:
                    PEAKS.setdefault(self.ARM, []).append(
                        float(np.max(peak_speed(got) / self.vmax)))
                if self.latch.worst is not None:
                    HOLDS.setdefault(self.ARM, []).append(
                        float(np.max(self.latch.worst / estop_tolerance(self.svc))))
                assert self.rec.errors == [], self.rec.errors[:3]
        finally:
            self.stack.close()

    # ------------------------------------------------------------ helpers

    def q(self) -> np.ndarray:
        return np.asarray(self.svc.driver.positions, dtype=float).copy()

    def clip(self, q: np.ndarray) -> np.ndarray:
        lo, hi = self.model.lower, self.model.upper
        pad = 0.03 * (hi - lo)
        return np.clip(q, lo + pad, hi - pad)

    def expect(self, r: httpx.Response, ok: tuple[int, ...], codes: set[str]) -> bool:
        """Counts the answer; fails on anything undocumented. True on success."""
        what = r.request.url.path.rsplit("/", 1)[-1]
        code = "" if r.status_code in ok else (r.json().get("code") if r.content else "")
        self.stats[f"{r.request.method} {what} {r.status_code} {code}".strip()] += 1
        problem = documented(r, ok, codes)
        assert problem is None, problem
        return r.status_code in ok

    def _wait_rest(self, timeout: float) -> None:
        slow = 0.01 * self.vmax

        def still(got: list[Any]) -> bool:
            last = got[-20:]
            return (len(last) == 20 and self.svc.motion.current is None
                    and not self.svc.motion.queued()
                    and all(r.qd is not None and np.all(np.abs(r.qd) <= slow) for r in last))
        wait_samples_sync(self.rec, still, timeout, start=max(0, len(self.rec) - 1))

    def _moving(self, recs: list[Any]) -> bool:
        return any(r.qd is not None and np.any(np.abs(r.qd) > MOVING * self.vmax)
                   for r in recs)

    # ------------------------------------------------------------ the invariants

    @invariant()
    def check(self) -> None:
        if self.live is None:
            return
        new = self.rec.since(self.checked)
        self.checked += len(new)
        self._judge(new, self.zones, self.floor)

    def _judge(self, recs: list[Any], zones: list[dict[str, Any]],
               floor: float | None) -> None:
        bad = speed_violations(self.svc, recs)
        assert bad == [], f"(c) a joint over its speed limit: {bad}"
        bad = self.latch.feed(recs)
        assert bad == [], f"(a) the setpoint moved away after the latch: {bad}"
        hit = zone_hits(self.svc, recs, zones, floor)
        assert hit is None, f"(b) a body point inside a zone: {hit}"

    # ------------------------------------------------------------ planned moves

    @allowed("move")
    @rule(frac=st.lists(unit, min_size=4, max_size=4), wait=st.booleans(),
          mode=st.sampled_from(["queue", "queue", "replace"]), through=st.booleans())
    @live
    def move(self, frac: list[float], wait: bool, mode: str, through: bool) -> None:
        here = self.q()
        if through and self.anchor is not None:
            target = self.anchor + 0.3 * (self.anchor - here)
        else:
            target = here + np.array(frac[:self.model.n]) * SPAN[self.ARM]
        target = self.clip(target)
        self.last_target = target
        r = self.http.post(f"{self.url}/move/joints", json={
            "positions": target.tolist(), "wait": wait, "mode": mode})
        if self.expect(r, (200,) if wait else (202,), MOVE_CODES) and wait:
            assert r.json()["status"] in ("done", "stopped", "failed"), r.text

    @allowed("stop")
    @rule()
    @live
    def stop(self) -> None:
        self.expect(self.http.post(f"{self.url}/stop"), (200,), set())

    @allowed("settle")
    @rule()
    @live
    def settle(self) -> None:
        with contextlib.suppress(AssertionError):  # still moving after 6 s: go on
            self._wait_rest(6.0)

    # ------------------------------------------------------------ rbe3001 SET_PID

    @allowed("set_pid", "rbe3001")
    @rule(frac=st.lists(st.floats(-1.0, 1.0), min_size=3, max_size=3), big=st.booleans(),
          joint=st.integers(0, 2))
    @live
    def set_pid(self, frac: list[float], big: bool, joint: int) -> None:
        here = self.q()
        target = here + np.array(frac) * 0.035
        if big:
            sign = 1.0 if frac[joint] >= 0 else -1.0
            target[joint] = here[joint] + sign * (BIG_STEP + abs(frac[joint]) * 1.3)
        target = self.clip(target)
        step = np.abs(target - here)
        r = self.http.post(f"{self.url}/rbe3001/set-pid", json=set_pid_body(self.svc, target))
        ok = self.expect(r, (200,), PASS_CODES)
        if ok and step.max() >= BIG_STEP and "velocity_limit" not in SKIP:
            raise AssertionError(
                f"a SET_PID step of {np.round(step, 3).tolist()} rad from where the arm is "
                f"({np.round(here, 3).tolist()}) was accepted: 422 velocity_limit expected")

    @allowed("set_pid_chase", "rbe3001")
    @rule(joint=st.integers(0, 2), sign=st.sampled_from([-1.0, 1.0]),
          travel=st.floats(0.4, 1.2))
    @live
    def set_pid_chase(self, joint: int, sign: float, travel: float) -> None:
        """SET_PID steps back to back, each as far ahead of the reported position as the
        route takes (0.08 rad, then 5 mrad less after each refusal), until the joint has gone
        `travel` (or the limit, or 3 s)."""
        tr = self.model.transmission
        step, reported, hold = 0.08, self.q(), self.q()
        goal = hold[joint] + sign * travel
        deadline = time.monotonic() + 3.0
        while sign * (goal - reported[joint]) > 0 and time.monotonic() < deadline:
            target = hold.copy()
            target[joint] = reported[joint] + sign * step
            if not np.all(self.clip(target) == target):
                break
            r = self.http.post(f"{self.url}/rbe3001/set-pid",
                               json=set_pid_body(self.svc, target))
            if not self.expect(r, (200,), PASS_CODES):
                if r.json()["code"] != "velocity_limit":
                    break
                step = max(0.01, step - 0.005)
                reported = self.q()
                continue
            reported = np.asarray(tr.from_ticks(np.asarray(r.json()["position_ticks"],
                                                           dtype=float)), dtype=float)
        self.stats[f"chase step {step:.3f}"] += 1

    @allowed("set_pid_walk", "rbe3001")
    @rule(joint=st.integers(0, 2), travel=st.floats(-1.0, 1.0), through=st.booleans())
    @live
    def set_pid_walk(self, joint: int, travel: float, through: bool) -> None:
        """A joint walked `travel` rad (or through the last zone's anchor) by SET_PID steps of
        35 mrad from where it is, each waited for (bounded): the arm ends far from where any
        plan left it."""
        hold = self.q()
        goal = float(self.clip(hold + travel)[joint])
        if through and self.anchor is not None:
            goal = float(self.clip(self.anchor + 0.3 * (self.anchor - hold))[joint])
        deadline = time.monotonic() + 4.0
        while time.monotonic() < deadline:
            here = self.q()
            if abs(here[joint] - goal) < 0.01:
                break
            target = hold.copy()
            target[joint] = here[joint] + float(np.clip(goal - here[joint], -0.035, 0.035))
            r = self.http.post(f"{self.url}/rbe3001/set-pid",
                               json=set_pid_body(self.svc, target))
            if not self.expect(r, (200,), PASS_CODES):
                break
            step_end = time.monotonic() + 1.0
            while abs(self.q()[joint] - target[joint]) > 0.01 and time.monotonic() < step_end:
                time.sleep(0.005)

    # ------------------------------------------------------------ angler goal_position

    def _goals(self, joints: list[int], frac: list[float], through: bool
               ) -> tuple[np.ndarray, dict[str, int]]:
        here = self.q()
        target = here.copy()
        aim = (self.anchor + 0.3 * (self.anchor - here) if through and self.anchor is not None
               else here + np.array(frac) * SPAN[self.ARM])
        target[joints] = aim[joints]
        target = self.clip(target)
        return target, {str(motor_of(self.svc, k)): goal_raw(self.svc, k, target)
                        for k in joints}

    @allowed("goal_position", "angler")
    @rule(joint=st.integers(0, 3), frac=st.lists(unit, min_size=4, max_size=4),
          through=st.booleans())
    @live
    def goal_position(self, joint: int, frac: list[float], through: bool) -> None:
        _, goals = self._goals([joint], frac, through)
        (dxl, raw), = goals.items()
        r = self.http.put(f"{self.url}/dynamixel/{dxl}/registers/goal_position",
                          json={"raw": raw})
        self.expect(r, (200,), PASS_CODES)

    @allowed("sync_write", "angler")
    @rule(joints=st.sets(st.integers(0, 3), min_size=2, max_size=4),
          frac=st.lists(unit, min_size=4, max_size=4), through=st.booleans())
    @live
    def sync_write(self, joints: set[int], frac: list[float], through: bool) -> None:
        target, goals = self._goals(sorted(joints), frac, through)
        self.last_target = target
        r = self.http.post(f"{self.url}/dynamixel/sync-write",
                           json={"name": "goal_position", "values": goals})
        self.expect(r, (200,), PASS_CODES)

    @allowed("plan_then_pass")
    @rule(frac=st.lists(unit, min_size=4, max_size=4), joint=st.integers(0, 3),
          travel=st.floats(-1.0, 1.0), then_estop=st.booleans())
    @live
    def plan_then_pass(self, frac: list[float], joint: int, travel: float,
                       then_estop: bool) -> None:
        """A planned move (waited for), then a pass-through that takes one joint well away
        from where the plan left it (a SET_PID walk; a goal_position, waited for), then maybe
        the estop: the state in which the hold, or the next plan, must start from where the
        arm is."""
        self.move(frac, True, "queue", False)
        k = joint % self.model.n
        if self.ARM == "rbe3001":
            self.set_pid_walk(k, travel, False)
        else:
            self.goal_position(k, [travel] * 4, False)
            self.settle()
        if then_estop:
            self.estop(True)

    # ------------------------------------------------------------ the envelope

    @allowed("add_zone")
    @rule(u=st.floats(0.0, 1.0), frac=st.lists(unit, min_size=4, max_size=4),
          body=st.integers(0, 9), half=st.floats(0.0, 1.0))
    @live
    def add_zone(self, u: float, frac: list[float], body: int, half: float) -> None:
        here = self.q()
        if self.last_target is not None:
            anchor = here + u * (self.last_target - here)
        else:
            anchor = self.clip(here + 0.5 * np.array(frac[:self.model.n]) * SPAN[self.ARM])
        pts = self.svc.safety.points(anchor)
        b = min(body, len(pts) - 1)  # the tip (last) most often
        lo, hi = HALF[self.ARM]
        self.n_zone += 1
        zone = box(f"z{self.n_zone}", pts[b], lo + half * (hi - lo))
        zones = [*self.zones[-2:], zone]
        self._put_safety({"zones": zones}, zones, self.floor, anchor, "busy" not in SKIP)

    @allowed("clear_zones")
    @rule()
    @live
    def clear_zones(self) -> None:  # fewer zones: harmless while moving, may go
        self._put_safety({"zones": []}, [], self.floor, None, False)

    @allowed("set_floor")
    @rule(u=st.floats(0.0, 1.0))
    @live
    def set_floor(self, u: float) -> None:
        """A floor 5 mm + u x 8 cm below the lowest body point (less its margin) now."""
        env = self.svc.safety
        z = env.points(self.q())[:, 2] - env.margins
        floor = float(z.min()) - 0.005 - u * 0.08
        raised = self.floor is None or floor > self.floor
        self._put_safety({"floor_z": floor}, self.zones, floor, self.anchor,
                         raised and "busy" not in SKIP)

    @allowed("clear_floor")
    @rule()
    @live
    def clear_floor(self) -> None:
        self._put_safety({"floor_z": None}, self.zones, None, self.anchor, False)

    def _put_safety(self, body: dict[str, Any], zones: list[dict[str, Any]],
                    floor: float | None, anchor: np.ndarray | None, busy: bool) -> None:
        """PUT /safety (instructor); what is in force is judged on each side of it, and
        across it the weaker of the two (an accepted change applies while it is answered)."""
        self.check()  # every sample so far judged against the envelope before
        before = self.rec.samples[-3:]
        r = self.http.put(f"{self.url}/safety", json=body, headers=auth(INSTRUCTOR))
        after_start = len(self.rec)
        ok = self.expect(r, (200,), SAFETY_CODES)
        during = self.rec.since(self.checked)
        self.checked += len(during)
        if ok:
            kept = [z for z in self.zones if z in zones]
            low = None if floor is None or self.floor is None else min(floor, self.floor)
            self._judge(during, kept, low)
            self.zones, self.floor = zones, floor
            self.anchor = anchor if zones else None
            if busy:
                self._not_busy(before, after_start)
        else:
            self._judge(during, self.zones, self.floor)

    def _not_busy(self, before: list[Any], after_start: int) -> None:
        """An accepted PUT /safety: no motion ran throughout it, the arm did not move."""
        after = wait_samples_sync(self.rec, lambda g: len(g) >= 2, 2.0, after_start)[:2]
        ran = {(r_.motion or {}).get("id") for r_ in before + after
               if (r_.motion or {}).get("status") in ("running", "queued")}
        same = [m for m in ran if m is not None and all(
            (x.motion or {}).get("id") == m and (x.motion or {}).get("status") == "running"
            for x in before + after)]
        assert not same, (f"PUT /safety answered 200 while motion {same[0]} ran throughout: "
                          "409 busy expected")
        assert not (self._moving(before) and self._moving(after)), (
            "PUT /safety answered 200 while the arm moved (speeds "
            f"{[np.round(x.qd, 3).tolist() for x in before + after if x.qd is not None]}): "
            "409 busy expected")

    # ------------------------------------------------------------ homing

    @allowed("home", when=lambda self: not self.latched)
    @rule(who=st.sampled_from(["operator", "instructor", "unhome"]))
    @live
    def home(self, who: str) -> None:
        here = [float(v) for v in self.q()]
        needs = [j.needs_homing for j in self.svc.profile.joints]
        if who == "unhome":
            r = self.http.delete(f"{self.url}/home")
            if not self.expect(r, (200, 204), HOME_CODES):
                return
        homed = self.http.get(self.url).json()["homed"]
        # a declaration moves the limits and zones of the joints that need homing: refused
        # where there are some and they are all homed (an arm with none: nothing to move)
        refuse = any(needs) and all(h for h, n in zip(homed, needs, strict=True) if n)
        headers = auth(INSTRUCTOR) if who == "instructor" else None
        r = self.http.post(f"{self.url}/home", json={"positions": here}, headers=headers)
        ok = self.expect(r, (200,), HOME_CODES)
        if ok:
            assert r.json()["homed"] == [True] * self.model.n, r.text
            assert who == "instructor" or not refuse or "already_homed" in SKIP, (
                f"an operator's POST /home on an arm homed {homed} answered 200: 409 "
                "already_homed expected")
        elif r.json()["code"] == "already_homed":
            assert who != "instructor" and refuse, r.text

    # ------------------------------------------------------------ the estop

    @allowed("estop")
    @rule(then_release=st.sampled_from([True, True, False]))
    def estop(self, then_release: bool) -> None:
        """Press; judge the hold over 0.3 s of latched samples (bounded); mostly release."""
        if self.live is None:
            # the model's state moves as in a live example, so that the preconditions (which
            # read only the model, never the server) draw the same steps when Hypothesis runs
            # a failing example again to report it
            self.latched = not then_release
            return
        n0 = len(self.rec)
        r = self.http.post(f"{self.url}/estop")
        self.expect(r, (200,), set())
        assert r.json() == {"estop": True}
        self.latched = True
        poll = float(self.svc.profile.link.poll_hz)
        with contextlib.suppress(AssertionError):
            wait_samples_sync(self.rec, lambda g: sum(x.estop for x in g) >= 0.3 * poll, 3.0,
                              max(0, n0 - 1))
        if then_release:
            self.release()

    @allowed("release", when=lambda self: self.latched)
    @rule()
    def release_rule(self) -> None:
        if self.live is None:
            self.latched = False
            return
        self.release()

    def release(self) -> None:
        self.check()  # judge the latch's samples before it ends
        r = self.http.delete(f"{self.url}/estop")
        self.expect(r, (200,), set())
        self.latched = False


def machine_for(arm: str) -> type[SafetyMachine]:
    return type(f"SafetyMachine_{arm}", (SafetyMachine,), {"ARM": arm})


@pytest.mark.parametrize("arm", ARMS)
def test_safety_machine(arm: str) -> None:
    machine = machine_for(arm)
    machine.started_at = time.monotonic()
    STATS.pop(arm, None)
    try:
        run_state_machine_as_test(machine, settings=settings(
            max_examples=EXAMPLES, stateful_step_count=STEPS, deadline=None, database=None,
            derandomize=not RANDOM, phases=[Phase.explicit, Phase.generate],
            suppress_health_check=list(HealthCheck)))
    finally:
        took = time.monotonic() - machine.started_at
        print(f"\n{arm}: {took:.1f} s; answers {dict(sorted(STATS.get(arm, Counter()).items()))}"
              f"\n{arm}: peak measured speed / limit per example "
              f"{np.round(PEAKS.get(arm, []), 3).tolist()}; worst hold offset / tolerance per "
              f"example with a latch {np.round(HOLDS.get(arm, []), 3).tolist()}")
        PEAKS.pop(arm, None)
        HOLDS.pop(arm, None)
