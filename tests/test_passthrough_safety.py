"""Issue 22's holes between the planner and the pass-through routes, one regression test each,
through the real app over the simulated arms (the device's own setpoint and registers read
back from the simulators, the arm's motion from every telemetry sample):

1. the estop holds where the arm is, not where the last planned move left it;
2. the first planned move after a pass-through starts from where the arm is (no leap);
3. Dynamixel goals written together (a sync-write, or two single PUTs in a row) are checked
   together against the keep-out zones;
4. re-homing a homed arm is refused unless an instructor does it or it is un-homed first;
5. a SET_PID step the firmware would take faster than the speed limit is refused;
6. raw access does not lift the envelope from Dynamixel goals;
7. the envelope applies at once: a PUT /safety while the arm moves is refused (409 busy) and
   the motion goes on;
and the bound of 5 itself (a step over 0.03 s at the limit, 50 mrad on the rbe3001, is refused),
and a storm of SET_PID steps, each one allowed, keeps under the speed limit.

Serial (tests/conftest.py SERIAL_FILES's reason): these measure joint speeds and positions in
telemetry, which two busy workers disturb.
"""

from __future__ import annotations

import asyncio
import time
from typing import Any

import httpx
import numpy as np
import pytest
from _safety_support import (
    API,
    INSTRUCTOR,
    OPERATOR,
    SPEED_TOLERANCE,
    Rec,
    Recorder,
    auth,
    box,
    device_setpoint,
    estop_tolerance,
    goal_raw,
    motor_of,
    peak_speed,
    positions,
    profiles,
    served,
    set_pid_body,
    speed_violations,
    token_settings,
    wait_samples,
    zone_hits,
)
from fastapi import FastAPI

from app.safety.guard import PASSTHROUGH_STEP_S

pytestmark = pytest.mark.serial

RB = f"{API}/arms/rbe3001"
AN = f"{API}/arms/angler"
#: A SET_PID step every test here may send: under 30 ms at the rbe3001's 1.5 rad/s limit.
SMALL_STEP = 0.04
#: The storm's first step, rad: more than the route allows (it finds the largest it takes).
STORM_FIRST_STEP = 0.08


def url(arm: str) -> str:
    return f"{API}/arms/{arm}"


def svc_of(app: FastAPI, arm: str) -> Any:
    return app.state.services[arm]


def measured(app: FastAPI, arm: str) -> np.ndarray:
    return np.asarray(svc_of(app, arm).driver.positions, dtype=float).copy()


async def at_rest(rec: Recorder, n: int = 25, timeout: float = 15.0) -> None:
    """Until the last n samples show every joint still, under 1 % of its limit (bounded)."""
    slow = 0.01 * np.asarray(rec.svc.model.vmax, dtype=float)

    def still(got: list[Rec]) -> bool:
        last = got[-n:]
        return len(last) == n and all(r.qd is not None and np.all(np.abs(r.qd) <= slow)
                                      for r in last)
    await wait_samples(rec, still, timeout, start=max(0, len(rec) - 1))


async def move(client: httpx.AsyncClient, arm: str, q: Any, **kw: Any) -> dict[str, Any]:
    r = await client.post(f"{url(arm)}/move/joints",
                          json={"positions": [float(v) for v in q], "wait": True, **kw})
    assert r.status_code == 200 and r.json()["status"] == "done", r.text
    return r.json()


async def set_pid_steps(client: httpx.AsyncClient, app: FastAPI, joint: int, goal: float,
                        hold: np.ndarray, timeout: float = 20.0) -> int:
    """Bring the rbe3001's `joint` to `goal` with SET_PID steps of at most SMALL_STEP from
    where it is measured and from its last command (the step rule judges both: from the
    one less far on toward the goal), the other joints told `hold`; each step waited for
    (bounded), and sent no sooner than PASSTHROUGH_STEP_S after the arm's last command, as the
    step rule paces a client (a step of SMALL_STEP from the last command needs that long at
    the limit; sooner, it is refused `velocity_limit`, rightly: a planned move's last setpoint
    counts). A step from the measured position alone was refused on a loaded machine, where
    the joint lagged its last command by more than the rule's margin."""
    svc = svc_of(app, "rbe3001")
    deadline = time.monotonic() + timeout
    sent = 0
    while True:
        q = measured(app, "rbe3001")
        if abs(q[joint] - goal) < 0.01:
            return sent
        assert time.monotonic() < deadline, f"SET_PID steps did not reach {goal} ({q})"
        pace = PASSTHROUGH_STEP_S - (time.monotonic() - svc.driver.commanded_at)
        if pace > 0:
            await asyncio.sleep(pace)  # the rule's own pace, not a wait for something
        q = measured(app, "rbe3001")
        told = svc.driver.commanded
        behind = q[joint]
        if told is not None and np.isfinite(told[joint]):
            behind = (min(behind, told[joint]) if goal > behind
                      else max(behind, told[joint]))
        target = hold.copy()
        target[joint] = behind + float(np.clip(goal - behind, -SMALL_STEP, SMALL_STEP))
        r = await client.post(f"{RB}/rbe3001/set-pid", json=set_pid_body(svc, target))
        assert r.status_code == 200, (f"a {SMALL_STEP} rad SET_PID step from where the arm is "
                                      f"and from its last command was refused: {r.text}")
        sent += 1
        step_deadline = time.monotonic() + 2.0
        while (abs(measured(app, "rbe3001")[joint] - target[joint]) > 0.01
               and time.monotonic() < step_deadline):
            await asyncio.sleep(0.005)


async def press_and_watch(client: httpx.AsyncClient, rec: Recorder, arm: str,
                          n_after: int) -> list[Rec]:
    """Press the estop; the samples from just before it to n_after samples after it."""
    n0 = len(rec)
    r = await client.post(f"{url(arm)}/estop")
    assert r.status_code == 200 and r.json() == {"estop": True}, r.text
    got = await wait_samples(rec, lambda g: sum(1 for x in g if x.estop) >= n_after,
                             timeout=10.0, start=max(0, n0 - 1))
    return got


def after_latch(got: list[Any]) -> list[Any]:
    k = next(i for i, r in enumerate(got) if r.estop)
    return got[k:]


# ---------------------------------------------------------------- 1. the estop's hold


async def test_estop_after_set_pid_steps_holds_where_the_rbe3001_is() -> None:
    """move/joints, then SET_PID the base to 1 rad in small allowed steps, wait until there,
    press the estop: the base must not swing back to where the planned move left it."""
    async with served(profiles()) as (app, client):
        svc = svc_of(app, "rbe3001")
        rec = Recorder(svc)
        try:
            hold = np.array([0.0, 0.6, 0.3])
            await move(client, "rbe3001", hold)
            steps = await set_pid_steps(client, app, 0, 1.0, hold)
            assert steps >= 20  # 1 rad in steps of 0.04
            await at_rest(rec)
            here = measured(app, "rbe3001")
            assert abs(here[0] - 1.0) < 0.02, here
            got = after_latch(await press_and_watch(client, rec, "rbe3001", 250))
            q = positions(got)
            tol = estop_tolerance(svc)
            drift = np.abs(q - q[0]).max(axis=0)
            setpoint = device_setpoint(svc)
            print(f"\nrbe3001 estop after SET_PID: latched at {np.round(q[0], 4).tolist()}, "
                  f"moved up to {np.round(drift, 4).tolist()} rad over {len(q)} samples; "
                  f"device setpoint {np.round(setpoint, 4).tolist()}; peak speed "
                  f"{np.round(peak_speed(got), 3).tolist()}")
            assert drift[0] <= tol[0], (
                f"the base swung {drift[0]:.3f} rad after the latch (from {q[0][0]:.3f}; "
                f"lowest {q[:, 0].min():.3f}), tolerance {tol[0]:.3f}")
            assert np.all(drift <= tol), (drift, tol)
            assert np.all(np.abs(setpoint - q[0]) <= tol), (
                f"the device setpoint {setpoint.tolist()} is not where the arm was "
                f"{q[0].tolist()} (tolerance {tol.tolist()})")
            assert speed_violations(svc, got) == []
        finally:
            rec.close()
            await client.delete(f"{RB}/estop")


async def test_estop_after_a_goal_position_holds_where_the_angler_is() -> None:
    """The same with a Dynamixel goal_position: theta3 sent to 1 rad after a planned move to
    0, then the estop: theta3 stays at 1 rad, and so do the servos' goals."""
    async with served(profiles()) as (app, client):
        svc = svc_of(app, "angler")
        rec = Recorder(svc)
        try:
            q0 = measured(app, "angler")
            q0[2] = 0.0
            await move(client, "angler", q0)
            qb = q0.copy()
            qb[2] = 1.0
            r = await client.put(f"{AN}/dynamixel/{motor_of(svc, 2)}/registers/goal_position",
                                 json={"raw": goal_raw(svc, 2, qb)})
            assert r.status_code == 200, r.text
            await wait_samples(rec, lambda g: bool(g) and g[-1].q is not None
                               and abs(g[-1].q[2] - 1.0) < 0.01, timeout=10.0,
                               start=len(rec) - 1)
            await at_rest(rec)
            got = after_latch(await press_and_watch(client, rec, "angler", 100))
            q = positions(got)
            tol = estop_tolerance(svc)
            drift = np.abs(q - q[0]).max(axis=0)
            setpoint = device_setpoint(svc)
            print(f"\nangler estop after goal_position: latched at {np.round(q[0], 4).tolist()}"
                  f", moved up to {np.round(drift, 5).tolist()}; servo goals "
                  f"{np.round(setpoint, 5).tolist()}")
            assert drift[2] <= tol[2], (
                f"theta3 swung {drift[2]:.3f} rad after the latch (from {q[0][2]:.3f}; lowest "
                f"{q[:, 2].min():.3f}), tolerance {tol[2]:.3f}")
            assert np.all(drift <= tol), (drift, tol)
            assert np.all(np.abs(setpoint - q[0]) <= tol), (setpoint.tolist(), q[0].tolist())
            assert speed_violations(svc, got) == []
        finally:
            rec.close()
            await client.delete(f"{AN}/estop")


async def test_estop_while_a_servo_runs_into_its_goal_holds_where_the_arm_is() -> None:
    """The hold is the last command only for a joint at rest within one step of it: theta3
    running at its limit (2 rad/s), pressed 65..93 mrad before its goal (twelve times), holds
    where it is (the servo's goal within 30 ms of motion at the limit of where theta3 was at
    the latch), not at the goal still ahead of it. A hold at the pending goal lands beyond
    that whenever the goal was over 60 mrad ahead at the latch and within it at the hold
    (a few presses in twelve); held where it is, the offset is one poll of motion."""
    async with served(profiles()) as (app, client):
        svc = svc_of(app, "angler")
        rec = Recorder(svc)
        tol = estop_tolerance(svc)
        offsets: list[float] = []
        try:
            for k in range(12):
                await client.delete(f"{AN}/estop")
                await at_rest(rec)
                goal = measured(app, "angler")
                goal[2] = 0.6 if k % 2 == 0 else -0.6
                ahead = 0.065 + 0.0025 * k  # a sweep: wherever the hold's latency puts the edge
                r = await client.put(f"{AN}/dynamixel/{motor_of(svc, 2)}/registers/"
                                     "goal_position", json={"raw": goal_raw(svc, 2, goal)})
                assert r.status_code == 200, r.text
                await wait_samples(rec, lambda g: bool(g) and g[-1].q is not None
                                   and abs(g[-1].q[2] - goal[2]) <= ahead, 5.0, len(rec) - 1)
                got = after_latch(await press_and_watch(client, rec, "angler", 60))
                offsets.append(float(abs(got[-1].setpoint[2] - got[0].q[2])))
            print(f"\nangler theta3 at its limit, estop 65..93 mrad before its goal: servo goal "
                  f"from where theta3 was at the latch {np.round(offsets, 4).tolist()} "
                  f"(tolerance {tol[2]:.3f})")
            assert max(offsets) <= tol[2], (
                f"the servo's goal ended {max(offsets):.4f} rad from where theta3 was at the "
                f"latch (tolerance {tol[2]:.3f}): offsets {np.round(offsets, 4).tolist()}")
        finally:
            rec.close()
            await client.delete(f"{AN}/estop")


# ---------------------------------------------------------------- 2. a plan starts from the arm


@pytest.mark.parametrize("arm", ["rbe3001", "angler"])
async def test_the_first_planned_move_after_a_pass_through_starts_where_the_arm_is(
        arm: str) -> None:
    async with served(profiles()) as (app, client):
        svc = svc_of(app, arm)
        rec = Recorder(svc)
        try:
            if arm == "rbe3001":
                k, start, there, goal = 0, np.array([0.0, 0.6, 0.3]), 0.5, 0.6
                await move(client, arm, start)
                await set_pid_steps(client, app, k, there, start)
            else:
                k, there, goal = 2, 1.0, 1.1
                start = measured(app, arm)
                start[k] = 0.0
                await move(client, arm, start)
                qb = start.copy()
                qb[k] = there
                r = await client.put(f"{AN}/dynamixel/{motor_of(svc, k)}/registers/"
                                     "goal_position", json={"raw": goal_raw(svc, k, qb)})
                assert r.status_code == 200, r.text
                await wait_samples(rec, lambda g: bool(g) and g[-1].q is not None
                                   and abs(g[-1].q[k] - there) < 0.01, 10.0, len(rec) - 1)
            await at_rest(rec)
            here = measured(app, arm)
            target = here.copy()
            target[k] = goal
            n0 = len(rec)
            body = await move(client, arm, target)
            got = rec.since(n0)
            q = positions(got)
            tol = estop_tolerance(svc)
            low = float(q[:, k].min())
            print(f"\n{arm}: from {here[k]:.3f} to {goal}: joint {svc.model.names[k]} went as "
                  f"low as {low:.3f}; peak speed {np.round(peak_speed(got), 3).tolist()}")
            assert low >= here[k] - tol[k], (
                f"the move leapt back: {svc.model.names[k]} went to {low:.3f} on its way from "
                f"{here[k]:.3f} to {goal} (the plan started from a stale setpoint)")
            assert speed_violations(svc, got) == []
            assert abs(body["final_positions"][k] - goal) < 0.03, body
        finally:
            rec.close()


# ---------------------------------------------------------------- 3. goals checked together


async def _pair_zone(app: FastAPI, client: httpx.AsyncClient
                     ) -> tuple[Any, dict[str, Any], np.ndarray, dict[int, int]]:
    """A zone 'pair' around the angler's tip at x + 2 cm, y + 2 cm, which neither goal alone
    comes near (checked here) and a planned move to the same place is refused for."""
    svc = svc_of(app, "angler")
    q0 = measured(app, "angler")
    qt = q0 + np.array([0.02, 0.02, 0.0, 0.0])
    zone = box("pair", svc.safety.points(qt)[-1], 0.004)
    r = await client.put(f"{AN}/safety", json={"zones": [zone]})
    assert r.status_code == 200, r.text
    for k in (0, 1):  # x alone, y alone, along their whole way
        alone = q0.copy()
        alone[k] = qt[k]
        way = [_rec(q0 + s * (alone - q0)) for s in np.linspace(0.0, 1.0, 50)]
        assert zone_hits(svc, way, [zone], slack=0.0) is None
    r = await client.post(f"{AN}/plan/joints", json={"positions": qt.tolist()})
    assert r.status_code == 422 and r.json()["code"] == "keep_out", r.text
    dev = svc.driver.link.device
    return svc, zone, qt, {i: dev.servo(i).get("goal_position") for i in (1, 2, 3, 4)}


async def test_a_sync_write_of_two_goals_into_a_zone_is_keep_out() -> None:
    async with served(profiles()) as (app, client):
        svc, _zone, qt, before = await _pair_zone(app, client)
        dev = svc.driver.link.device
        gx, gy = goal_raw(svc, 0, qt), goal_raw(svc, 1, qt)
        mx, my = motor_of(svc, 0), motor_of(svc, 1)
        r = await client.post(f"{AN}/dynamixel/sync-write",
                              json={"name": "goal_position", "values": {str(mx): gx,
                                                                        str(my): gy}})
        assert r.status_code == 422 and r.json()["code"] == "keep_out", (
            f"a sync-write of x and y into zone 'pair' answered {r.status_code} {r.text}")
        assert "'pair'" in r.json()["detail"]
        assert {i: dev.servo(i).get("goal_position") for i in (1, 2, 3, 4)} == before


async def test_two_single_goal_puts_in_a_row_into_a_zone_are_keep_out() -> None:
    """The second PUT counts the first one's pending goal."""
    async with served(profiles()) as (app, client):
        svc, _zone, qt, before = await _pair_zone(app, client)
        dev = svc.driver.link.device
        gx, gy = goal_raw(svc, 0, qt), goal_raw(svc, 1, qt)
        mx, my = motor_of(svc, 0), motor_of(svc, 1)
        r = await client.put(f"{AN}/dynamixel/{mx}/registers/goal_position", json={"raw": gx})
        assert r.status_code == 200, r.text
        assert dev.servo(mx).get("goal_position") == gx
        r = await client.put(f"{AN}/dynamixel/{my}/registers/goal_position", json={"raw": gy})
        assert r.status_code == 422 and r.json()["code"] == "keep_out", (
            f"the second single PUT (y) while x was on its way answered {r.status_code} "
            f"{r.text}")
        assert "'pair'" in r.json()["detail"]
        assert dev.servo(my).get("goal_position") == before[my]


def _rec(q: np.ndarray) -> Rec:
    return Rec(0.0, 0, np.asarray(q, dtype=float), None, False, np.asarray(q), None)


# ---------------------------------------------------------------- 4. homing


async def test_rehoming_a_homed_angler_is_refused_unless_an_instructor_or_unhomed_first(
) -> None:
    async with served(profiles(), token_settings()) as (app, client):
        svc = svc_of(app, "angler")
        op, ins = auth(OPERATOR), auth(INSTRUCTOR)
        detail = (await client.get(AN, headers=op)).json()
        assert detail["homed"] == [True] * 4
        offsets = np.array(svc.model.transmission.offset_ticks, dtype=float).copy()
        q0 = measured(app, "angler")
        wrong = (q0 + np.array([0.066, 0.0, 0.0, 0.0])).tolist()  # 6.6 cm off the truth
        r = await client.post(f"{AN}/home", json={"positions": wrong}, headers=op)
        assert r.status_code == 409 and r.json()["code"] == "already_homed", (
            f"an operator re-homed a homed arm 6.6 cm off: {r.status_code} {r.text}")
        r = await client.post(f"{AN}/home", headers=op)
        assert r.status_code == 409 and r.json()["code"] == "already_homed", r.text
        np.testing.assert_array_equal(svc.model.transmission.offset_ticks, offsets)
        np.testing.assert_allclose(measured(app, "angler"), q0, atol=1e-4)
        # an instructor may (here: the truth)
        r = await client.post(f"{AN}/home", json={"positions": q0.tolist()}, headers=ins)
        assert r.status_code == 200 and r.json()["homed"] == [True] * 4, r.text
        np.testing.assert_allclose(measured(app, "angler"), q0, atol=1e-4)
        # un-home on purpose (operator), then home again
        r = await client.delete(f"{AN}/home", headers=op)
        assert r.status_code in (200, 204), r.text
        homed = (await client.get(AN, headers=op)).json()["homed"]
        needs = [j.needs_homing for j in svc.profile.joints]
        assert homed == [not n for n in needs], homed
        nudge = (q0 + np.array([0.01, 0.0, 0.0, 0.0])).tolist()
        r = await client.post(f"{AN}/move/joints", json={"positions": nudge}, headers=op)
        assert r.status_code == 409 and r.json()["code"] == "not_homed", r.text
        home = [0.01, -0.01, float(q0[2]), 0.06]
        r = await client.post(f"{AN}/home", json={"positions": home}, headers=op)
        assert r.status_code == 200 and r.json()["homed"] == [True] * 4, r.text
        q = measured(app, "angler")
        np.testing.assert_allclose(q[[0, 1, 3]], np.array(home)[[0, 1, 3]], atol=2e-4)


# ---------------------------------------------------------------- 5. SET_PID's speed


async def test_a_set_pid_step_from_minus_to_plus_1_5_rad_is_velocity_limit() -> None:
    async with served(profiles()) as (app, client):
        svc = svc_of(app, "rbe3001")
        rec = Recorder(svc)
        try:
            await move(client, "rbe3001", [-1.5, 0.6, 0.3])
            await at_rest(rec)
            here = measured(app, "rbe3001")
            before = list(svc.driver.link.device.setpoint)
            far = here.copy()
            far[0] = 1.5
            n0 = len(rec)
            r = await client.post(f"{RB}/rbe3001/set-pid", json=set_pid_body(svc, far))
            assert r.status_code == 422 and r.json()["code"] == "velocity_limit", (
                f"a 3 rad SET_PID step answered {r.status_code} {r.text}")
            assert "base" in r.json()["detail"]
            assert list(svc.driver.link.device.setpoint) == before
            got = await wait_samples(rec, lambda g: len(g) >= 100, 5.0, n0)
            assert np.abs(positions(got)[:, 0] - here[0]).max() < 0.01
            # a small step from where it is goes through, to the firmware
            near = here.copy()
            near[0] += SMALL_STEP
            r = await client.post(f"{RB}/rbe3001/set-pid", json=set_pid_body(svc, near))
            assert r.status_code == 200, r.text
            np.testing.assert_allclose(device_setpoint(svc)[0], near[0], atol=1e-3)
        finally:
            rec.close()


async def test_a_set_pid_step_over_30_ms_at_the_limit_is_velocity_limit() -> None:
    """The bound itself: a joint at rest may be sent at most its velocity limit x 0.03 s
    (45 mrad on the rbe3001) from where it is measured; 50 mrad is refused, 40 goes."""
    async with served(profiles()) as (app, client):
        svc = svc_of(app, "rbe3001")
        rec = Recorder(svc)
        try:
            await move(client, "rbe3001", [0.0, 0.6, 0.3])
            await at_rest(rec)
            here = measured(app, "rbe3001")
            before = list(svc.driver.link.device.setpoint)
            over = here.copy()
            over[0] += 0.05
            r = await client.post(f"{RB}/rbe3001/set-pid", json=set_pid_body(svc, over))
            assert r.status_code == 422 and r.json()["code"] == "velocity_limit", (
                f"a SET_PID step of 0.050 rad (limit x 0.03 s = "
                f"{svc.model.vmax[0] * 0.03:.3f}) answered {r.status_code} {r.text}")
            assert list(svc.driver.link.device.setpoint) == before
            near = here.copy()
            near[0] += SMALL_STEP
            r = await client.post(f"{RB}/rbe3001/set-pid", json=set_pid_body(svc, near))
            assert r.status_code == 200, r.text
        finally:
            rec.close()


async def test_a_storm_of_allowed_set_pid_steps_keeps_under_the_speed_limit() -> None:
    """SET_PID steps back to back, each ahead of the position the last reply reported by as
    much as the route allows (a refused step is tried again 5 mrad shorter): every step sent
    is one the route accepted, and the base must still not outrun its limit."""
    async with served(profiles()) as (app, client):
        svc = svc_of(app, "rbe3001")
        tr = svc.model.transmission
        rec = Recorder(svc)
        try:
            hold = np.array([-0.6, 0.6, 0.3])
            await move(client, "rbe3001", hold)
            await at_rest(rec)
            n0 = len(rec)
            reported = measured(app, "rbe3001")
            step, sent, refused, largest = STORM_FIRST_STEP, 0, 0, 0.0
            deadline = time.monotonic() + 15.0
            while reported[0] < 0.6 and time.monotonic() < deadline:
                target = hold.copy()
                target[0] = reported[0] + step
                r = await client.post(f"{RB}/rbe3001/set-pid", json=set_pid_body(svc, target))
                if r.status_code != 200:
                    assert r.json()["code"] == "velocity_limit", r.text
                    refused += 1
                    step = max(0.01, step - 0.005)
                    reported = measured(app, "rbe3001")
                    continue
                sent += 1
                largest = max(largest, step)
                reported = np.asarray(tr.from_ticks(np.asarray(r.json()["position_ticks"],
                                                               dtype=float)), dtype=float)
            await at_rest(rec)
            got = rec.since(n0)
            peak = peak_speed(got)
            print(f"\nSET_PID storm: {sent} steps sent (largest {largest:.3f} rad), {refused} "
                  f"refused; peak speed {np.round(peak, 3).tolist()} rad/s (limit "
                  f"{svc.model.vmax.tolist()})")
            assert sent >= 10
            assert speed_violations(svc, got) == [], (
                f"steps of up to {largest:.3f} rad, each accepted, drove the base at "
                f"{peak[0]:.3f} rad/s: over {SPEED_TOLERANCE} x {svc.model.vmax[0]:g}")
        finally:
            rec.close()


# ---------------------------------------------------------------- 6. raw access


async def test_raw_access_goals_into_a_zone_are_keep_out() -> None:
    async with served(profiles(raw=True)) as (app, client):
        svc = svc_of(app, "angler")
        assert svc.profile.raw_access
        q0 = measured(app, "angler")
        qb = q0.copy()
        qb[2] = q0[2] + 0.6
        arm_end = svc.safety.points(q0 + np.array([0.0, 0.0, 0.3, 0.0]))[3]
        r = await client.put(f"{AN}/safety", json={"zones": [box("lamp", arm_end, 0.01)]})
        assert r.status_code == 200, r.text
        dev = svc.driver.link.device
        m3 = motor_of(svc, 2)
        before = dev.servo(m3).get("goal_position")
        raw = goal_raw(svc, 2, qb)
        r = await client.put(f"{AN}/dynamixel/{m3}/registers/goal_position", json={"raw": raw})
        assert r.status_code == 422 and r.json()["code"] == "keep_out", (
            f"a raw-access goal through zone 'lamp' answered {r.status_code} {r.text}")
        assert "'lamp'" in r.json()["detail"]
        assert dev.servo(m3).get("goal_position") == before
        r = await client.post(f"{AN}/dynamixel/sync-write",
                              json={"name": "goal_position", "values": {str(m3): raw}})
        assert r.status_code == 422 and r.json()["code"] == "keep_out", r.text
        assert dev.servo(m3).get("goal_position") == before
        # raw access still lifts the joint limits: a goal beyond theta3's limit, away from
        # the zone, goes through
        qc = q0.copy()
        qc[2] = float(svc.model.lower[2]) - 0.05
        r = await client.put(f"{AN}/dynamixel/{m3}/registers/goal_position",
                             json={"raw": goal_raw(svc, 2, qc)})
        assert r.status_code == 200, r.text


# ---------------------------------------------------------------- 7. the envelope at once


async def test_a_zone_put_while_a_motion_runs_is_busy_and_the_motion_goes_on() -> None:
    async with served(profiles()) as (app, client):
        svc = svc_of(app, "rbe3001")
        rec = Recorder(svc)
        try:
            await move(client, "rbe3001", [0.0, 0.6, 0.3])
            r = await client.post(f"{RB}/move/joints", json={"positions": [1.2, 0.6, 0.3]})
            assert r.status_code == 202, r.text
            mid = r.json()["id"]
            await wait_samples(rec, lambda g: bool(g) and g[-1].q is not None
                               and g[-1].q[0] > 0.15, 10.0, len(rec) - 1)
            ahead = svc.safety.points(np.array([0.9, 0.6, 0.3]))[3]  # the tip, on the way
            r = await client.put(f"{RB}/safety", json={"zones": [box("late", ahead, 0.02)]})
            status = (await client.get(f"{RB}/motions/{mid}")).json()["status"]
            assert r.status_code == 409 and r.json()["code"] == "busy", (
                f"a zone PUT while motion {mid} was {status} answered {r.status_code} {r.text}")
            assert (await client.get(f"{RB}/safety")).json()["zones"] == []
            deadline = time.monotonic() + 10.0
            while True:
                m = (await client.get(f"{RB}/motions/{mid}")).json()
                if m["status"] not in ("queued", "running") or time.monotonic() > deadline:
                    break
                await asyncio.sleep(0.02)
            assert m["status"] == "done", m
            assert abs(m["final_positions"][0] - 1.2) < 0.03, m
        finally:
            rec.close()


async def test_a_zone_put_while_the_arm_moves_after_a_goal_is_busy() -> None:
    """'While the arm is still moving' too: a pass-through goal, no motion record. Measured
    moving: any new zone is 409 busy. Just sent (maybe not moving yet): a zone on the goal's
    way is refused (409 busy, or 422 keep_out for the pending path) and never entered."""
    async with served(profiles()) as (app, client):
        svc = svc_of(app, "angler")
        rec = Recorder(svc)
        try:
            # theta3 from near one end to near the other: 2.8 rad, 1.4 s at 2 rad/s, the window
            # the PUT below must land in (with 1.2 rad, 0.6 s, a slow host's PUT once came
            # after the arm had stopped, and a zone at rest is rightly accepted)
            start = measured(app, "angler")
            start[2] = -1.4
            await move(client, "angler", start)
            await at_rest(rec)
            q0 = measured(app, "angler")
            m3 = motor_of(svc, 2)
            qb = q0.copy()
            qb[2] = 1.4
            r = await client.put(f"{AN}/dynamixel/{m3}/registers/goal_position",
                                 json={"raw": goal_raw(svc, 2, qb)})
            assert r.status_code == 200, r.text
            got = await wait_samples(rec, lambda g: bool(g) and g[-1].qd is not None
                                     and abs(g[-1].qd[2]) > 0.5, 5.0, len(rec) - 1)
            far = box("far", [0.5, 0.5, 0.5], 0.05)
            r = await client.put(f"{AN}/safety", json={"zones": [far]})
            assert r.status_code == 409 and r.json()["code"] == "busy", (
                f"a zone PUT while theta3 moved at {got[-1].qd[2]:.2f} rad/s answered "
                f"{r.status_code} {r.text}")
            assert (await client.get(f"{AN}/safety")).json()["zones"] == []
            await at_rest(rec)
            # a goal back, and at once a zone on its way (the arm end half way back)
            here = measured(app, "angler")
            back = here.copy()
            back[2] = q0[2]
            mid = here.copy()
            mid[2] = (here[2] + q0[2]) / 2
            zone = box("on_the_way", svc.safety.points(mid)[3], 0.01)
            n0 = len(rec)
            r = await client.put(f"{AN}/dynamixel/{m3}/registers/goal_position",
                                 json={"raw": goal_raw(svc, 2, back)})
            assert r.status_code == 200, r.text
            r = await client.put(f"{AN}/safety", json={"zones": [zone]})
            assert r.status_code in (409, 422) and r.json()["code"] in ("busy", "keep_out"), (
                f"a zone on the way of a goal just sent answered {r.status_code} {r.text}")
            assert (await client.get(f"{AN}/safety")).json()["zones"] == []
            await at_rest(rec)  # and the goal goes on, to where it was sent
            assert abs(measured(app, "angler")[2] - q0[2]) < 0.01
            assert len(rec.since(n0)) > 0
        finally:
            rec.close()
