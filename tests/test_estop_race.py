"""The estop against pass-through commands fired together, at varying offsets: nothing that
moves the arm reaches the device after the latch but the one hold, and the hold is where the
arm was (issue 22: the estop and every route that moves an arm share one record; issue 23:
every command is checked against the latch on the control thread at the moment it is sent).

The simulated devices are wrapped where they receive bytes (on the control thread, in the
order the owner task writes them), so each command is seen with the latch as it stood when
the device got it."""

from __future__ import annotations

import asyncio
import random
import time
from typing import Any

import httpx
import numpy as np
from _bus_watch import watch_writes
from conftest import running_client

from app.safety.guard import PASSTHROUGH_STEP_S
from app.service import ArmService
from protocol import rbe3001 as rb

API = "/api/v1/arms"
ROUNDS = 40


def watch_rbe3001(svc: ArmService) -> list[tuple[bool, tuple[float, ...]]]:
    """(latched, position ticks) of every SET_PID the simulated firmware receives."""
    dev = svc.driver.link.device
    seen: list[tuple[bool, tuple[float, ...]]] = []
    receive = dev.receive

    def receiving(data: bytes, now: float) -> Any:
        try:
            cmd = rb.decode_command(bytes(data))
        except rb.DecodeError:
            cmd = None
        if isinstance(cmd, rb.SetPid):
            seen.append((svc.guard.estop, tuple(j.position_ticks for j in cmd.setpoints)))
        return receive(data, now)

    dev.receive = receiving
    return seen


def watch_goals(svc: ArmService) -> list[tuple[bool, dict[int, int]]]:
    """(latched, {id: goal ticks}) of every Goal Position write the simulated bus receives."""
    seen: list[tuple[bool, dict[int, int]]] = []

    def note(name: str, values: dict[int, int]) -> None:
        if name == "goal_position":
            seen.append((svc.guard.estop, values))

    watch_writes(svc.driver.link.device, note)
    return seen


async def settle(svc: ArmService, within: float = 1.0, timeout: float = 10.0) -> None:
    """Until the arm is `within` of a full step (PASSTHROUGH_STEP_S at the limit) of where it
    was last told to go, PASSTHROUGH_STEP_S after that command (a full step may then be sent
    again: app/safety/guard.py), bounded."""
    deadline = time.monotonic() + timeout
    while True:
        told, here = svc.driver.told(), svc.driver.positions
        if told is not None and here is not None and np.all(
                np.abs(told - here) <= within * svc.model.vmax * PASSTHROUGH_STEP_S) and (
                time.monotonic() - svc.driver.commanded_at > PASSTHROUGH_STEP_S):
            return
        assert time.monotonic() < deadline, (told, here)
        await asyncio.sleep(0.005)


async def race(client: httpx.AsyncClient, arm: str, command: Any, offset: float) -> int:
    """Fire `command()` and an estop press `offset` s apart (either first); the command's
    status."""
    async def press() -> None:
        if offset > 0:
            await asyncio.sleep(offset)
        assert (await client.post(f"{API}/{arm}/estop")).status_code == 200

    async def send() -> int:
        if offset < 0:
            await asyncio.sleep(-offset)
        r: httpx.Response = await command()
        assert r.status_code in (200, 409), r.text  # through, or refused by the latch
        if r.status_code == 409:
            assert r.json()["code"] == "estop_latched", r.text
        return r.status_code

    _, status = await asyncio.gather(press(), send())
    return status


def check_after_latch(seen: list[tuple[bool, Any]], start: int, here: np.ndarray,
                      to_q: Any, cap: np.ndarray) -> None:
    """After the latch: one command at most (the hold), within one step of where the arm
    was when it was latched."""
    latched = [cmd for flag, cmd in seen[start:] if flag]
    assert len(latched) <= 1, latched
    for cmd in latched:
        q = to_q(cmd)
        assert np.all(np.abs(q - here) <= cap), (q, here)


async def test_estop_against_set_pid_at_varying_offsets() -> None:
    rng = random.Random(22)
    async with running_client() as (app, client):
        svc: ArmService = app.state.services["rbe3001"]
        tr = svc.model.transmission
        seen = watch_rbe3001(svc)
        cap = svc.model.vmax * PASSTHROUGH_STEP_S * 2 + svc.guard.tolerance()
        through = refused = 0
        for _ in range(ROUNDS):
            # the step below is 0.6 of a full one from the last command, and the guard also
            # bounds it from where the arm is: the arm within 0.3 of a step of that command
            # first (within a full step, a step from a hold the arm had not reached yet was
            # 0.048 rad from where it was, over the 0.047 allowed: 422; a clean clone)
            await settle(svc, within=0.3)
            here = np.asarray(svc.driver.positions, dtype=float)
            told = np.asarray(svc.driver.told(), dtype=float)
            # each joint a small step towards the middle of its range: the rounds' outcomes
            # (through, refused, held part way) must not walk the arm to a limit (alternating
            # steps did, when the ones up were refused and the ones down went through)
            sign = np.where(told < (svc.model.lower + svc.model.upper) / 2, 1.0, -1.0)
            goal = told + sign * svc.model.vmax * PASSTHROUGH_STEP_S * 0.6
            ticks = tr.to_ticks(goal)
            body = {"joints": [{"position_ticks": float(t)} for t in ticks]}
            start = len(seen)
            status = await race(client, "rbe3001",
                                lambda b=body: client.post(f"{API}/rbe3001/rbe3001/set-pid",
                                                           json=b),
                                rng.uniform(-0.003, 0.003))
            through += status == 200
            refused += status == 409
            check_after_latch(seen, start, here,
                              lambda c: np.asarray(tr.from_ticks(np.array(c, float))), cap)
            assert (await client.delete(f"{API}/rbe3001/estop")).status_code == 200
        assert through + refused == ROUNDS


async def test_estop_against_a_goal_sync_write_at_varying_offsets() -> None:
    rng = random.Random(23)
    async with running_client() as (app, client):
        svc: ArmService = app.state.services["angler"]
        tr = svc.model.transmission
        ids = [j.motor_id for j in svc.profile.joints]
        seen = watch_goals(svc)
        cap = svc.model.vmax * PASSTHROUGH_STEP_S * 2 + svc.guard.tolerance()

        def to_q(cmd: dict[int, int]) -> np.ndarray:
            ticks = np.array(tr.to_ticks(np.asarray(svc.driver.told(), dtype=float)))
            for i, v in cmd.items():
                ticks[ids.index(i)] = v
            return np.asarray(tr.from_ticks(ticks), dtype=float)

        for k in range(ROUNDS):
            await settle(svc)
            here = np.asarray(svc.driver.positions, dtype=float)
            goal = here.copy()
            goal[2] += 0.05 if k % 2 == 0 else -0.05  # theta3: small, within the limits
            raw = int(round(float(tr.to_ticks(goal)[2])))
            body = {"name": "goal_position", "values": {str(ids[2]): raw}}
            start = len(seen)
            await race(client, "angler",
                       lambda b=body: client.post(f"{API}/angler/dynamixel/sync-write", json=b),
                       rng.uniform(-0.003, 0.003))
            # the hold is where theta3 was at the latch; the goal may have started it moving
            check_after_latch(seen, start, here, to_q, cap + np.abs(goal - here))
            latched = [c for flag, c in seen[start:] if flag]
            for cmd in latched:  # the hold never heads for the refused or dropped goal
                assert not (cmd.get(ids[2]) == raw and abs(goal[2] - here[2]) > cap[2]), cmd
            assert (await client.delete(f"{API}/angler/estop")).status_code == 200


async def test_a_command_queued_before_the_latch_is_not_written_after_it() -> None:
    """On the control loop itself: a pass-through SET_PID is checked and queued, then the
    estop latches before the owner task writes it. The owner task asks the latch as it
    writes: the command fails with estop_latched and the device gets only the hold."""
    from app.errors import EstopLatched
    from app.runtime.control_thread import call_in

    async with running_client() as (app, client):
        svc: ArmService = app.state.services["rbe3001"]
        tr = svc.model.transmission
        seen = watch_rbe3001(svc)
        for k in range(10):
            await settle(svc)
            here = np.asarray(svc.driver.positions, dtype=float)
            told = np.asarray(svc.driver.told(), dtype=float)
            goal = told + (1 if k % 2 == 0 else -1) * svc.model.vmax * PASSTHROUGH_STEP_S * 0.6
            sps = [(float(t), 0.0, 0.0) for t in tr.to_ticks(goal)]
            start = len(seen)

            async def queue_then_latch(sps: list[tuple[float, float, float]] = sps) -> Any:
                sent = asyncio.ensure_future(svc.command_passthrough(
                    dict(enumerate(t for t, _v, _f in sps)),
                    lambda: svc.driver.set_pid(sps)))  # type: ignore[attr-defined]
                await asyncio.sleep(0)  # checked and queued; the owner task not yet run
                await svc.latch_estop()
                return (await asyncio.gather(sent, return_exceptions=True))[0]

            outcome = await call_in(svc.home_loop, queue_then_latch)
            assert isinstance(outcome, EstopLatched), outcome
            after = [np.asarray(tr.from_ticks(np.array(c, float))) for flag, c in seen[start:]]
            assert len(after) == 1, after  # the hold alone
            assert np.all(np.abs(after[0] - here) <= svc.guard.tolerance()
                          + svc.model.vmax * PASSTHROUGH_STEP_S), (after, here)
            assert not np.allclose(after[0], goal, atol=1e-6)
            assert (await client.delete(f"{API}/rbe3001/estop")).status_code == 200
