"""The simulated world (app/sim/world.py) through its route and real moves: the scene read and
laid out over GET/PUT /arms/{arm}/world, refusals that change nothing, a real arm's 404, and
grasp, carry and release done by the simulated hardware itself (the rbe3001's claw through
moves and the gripper route, the angler's magnet and a bin's rim)."""

from __future__ import annotations

import contextlib
import math
from collections.abc import AsyncIterator
from typing import Any

import httpx
import numpy as np
import pytest

from app.arms.loading import load_profile
from app.client import ArmServerError, AsyncArmClient
from app.device.factory import make_sim_device
from app.sim.serve import serve_tcp
from app.sim.world import BALL_D, TARGET_T, World, WorldObject
from tests._wait import wait_for
from tests.conftest import make_settings, running_client

OP = "op-w"
TEACH = "teach-w"
RED_BIN = {"name": "red", "color": "red", "min": {"x": 0.04, "y": 0.17, "z": 0.0},
           "max": {"x": 0.11, "y": 0.25, "z": 0.03}}


def ball(i: str, color: str, x: float, y: float, kind: str = "ball") -> dict[str, Any]:
    return {"id": i, "kind": kind, "color": color, "position": {"x": x, "y": y, "z": 0.0}}


@contextlib.asynccontextmanager
async def clients(profiles: list[Any] | None = None
                  ) -> AsyncIterator[tuple[AsyncArmClient, AsyncArmClient, httpx.AsyncClient]]:
    """The app in process with tokens: an operator's and an instructor's Python client, and a
    raw httpx client (no token)."""
    settings = make_settings(operator_tokens=OP, instructor_tokens=TEACH)
    async with running_client(settings, profiles=profiles) as (app, raw):
        transport = httpx.ASGITransport(app=app)
        async with AsyncArmClient("http://armserver.test", token=OP, transport=transport,
                                  timeout=30.0) as op, \
                AsyncArmClient("http://armserver.test", token=TEACH, transport=transport,
                               timeout=30.0) as teach:
            yield op, teach, raw


async def test_scene_round_trip_and_refusals_change_nothing() -> None:
    async with clients() as (op, teach, raw):
        first = await op.world("rbe3001")
        assert len(first.objects) == 6 and {o.color for o in first.objects} == {
            "red", "green", "blue"}
        assert {b.name for b in first.bins} == {"red", "green", "blue"}
        assert first.tip is not None and first.gripper is not None

        scene = {"objects": [ball("a", "red", 0.15, 0.02), ball("b", "yellow", 0.2, -0.05,
                                                               "block")],
                 "bins": [RED_BIN]}
        # a viewer may read, not write; an operator needs the lease; an instructor may
        r = await raw.put("/api/v1/arms/rbe3001/world", json=scene)
        assert r.status_code == 401
        async with teach.hold_lease("rbe3001"):  # another holds the lease: the operator waits
            with pytest.raises(ArmServerError) as no_lease:
                await op.set_world("rbe3001", scene)
        assert no_lease.value.code == "leased"
        got = await teach.set_world("rbe3001", scene)
        assert [(o.id, o.color, o.kind, o.held) for o in got.objects] == [
            ("a", "red", "ball", False), ("b", "yellow", "block", False)]
        a = got.objects[0].position
        assert (a.x, a.y, a.z) == (0.15, 0.02, BALL_D / 2)  # settled on the table
        headers = {"Authorization": f"Bearer {TEACH}"}
        read = await raw.get("/api/v1/arms/rbe3001/world", headers=headers)
        assert read.json()["objects"] == [o.model_dump(mode="json") for o in got.objects]

        bad = [
            ({"objects": [ball("a", "red", 0.9, 0.0)], "bins": []}, "off the table"),
            ({"objects": [ball("a", "purple", 0.1, 0.0)], "bins": []}, "unknown colour"),
            ({"objects": [ball("a", "red", 0.1, 0.0, "target")], "bins": []}, "claw"),
            ({"objects": [ball("a", "red", 0.1, 0.0), ball("a", "red", 0.2, 0.0)],
              "bins": []}, "unique"),
            ({"objects": [], "bins": [{**RED_BIN, "max": {"x": 0.0, "y": 0.3, "z": 0.03}}]},
             "min must be below max"),
        ]
        for body, why in bad:
            r = await raw.put("/api/v1/arms/rbe3001/world", json=body, headers=headers)
            assert r.status_code == 422, body
            assert r.json()["code"] == "invalid_request" and why in r.json()["detail"], r.json()
        nan = ('{"objects": [{"id": "a", "kind": "ball", "color": "red", "position": '
               '{"x": NaN, "y": 0, "z": 0}}], "bins": []}')
        r = await raw.put("/api/v1/arms/rbe3001/world", content=nan,
                          headers={**headers, "Content-Type": "application/json"})
        assert r.status_code == 422 and r.json()["code"] == "invalid_request"
        after = await op.world("rbe3001")
        assert after.objects == got.objects and after.bins == got.bins


async def test_a_real_link_has_no_world() -> None:
    """The angler over a socket (a simulator in another process, to the server a serial
    device): 404 not_found; the in-process rbe3001 beside it has its world."""
    device = make_sim_device(load_profile("angler"))
    server = await serve_tcp(device)
    try:
        angler = load_profile("angler")
        angler = angler.model_copy(update={"link": angler.link.model_copy(update={
            "kind": "serial", "address": f"socket://127.0.0.1:{server.port}",
            "homed_at_start": True})})
        async with clients([load_profile("rbe3001"), angler]) as (op, teach, raw):
            r = await raw.get("/api/v1/arms/angler/world",
                              headers={"Authorization": f"Bearer {OP}"})
            assert r.status_code == 404 and r.json()["code"] == "not_found"
            r = await raw.put("/api/v1/arms/angler/world", json={"objects": [], "bins": []},
                              headers={"Authorization": f"Bearer {TEACH}"})
            assert r.status_code == 404 and r.json()["code"] == "not_found"
            r = await raw.get("/api/v1/arms/rbe3001/world",
                              headers={"Authorization": f"Bearer {OP}"})
            assert r.status_code == 200
    finally:
        await server.close()


async def _held(c: AsyncArmClient, arm: str, oid: str) -> Any:
    w = await c.world(arm)
    return next(o for o in w.objects if o.id == oid)


async def test_claw_grasps_carries_and_drops_into_a_bin() -> None:
    async with clients() as (op, _, _raw):
        arm = "rbe3001"
        async with op.hold_lease(arm):
            await op.set_world(arm, {"objects": [ball("r", "red", 0.18, 0.0),
                                                 ball("g", "green", 0.14, -0.08)],
                                     "bins": [RED_BIN]})
            await op.gripper(arm, 0.0)
            await wait_for(lambda: _gripper_below(op, arm, 0.05), what="the claw open")
            z = BALL_D / 2
            await op.move_pose(arm, 0.18, 0.0, z + 0.05, wait=True)
            await op.move_pose(arm, 0.18, 0.0, z, wait=True)
            await op.gripper(arm, 1.0)
            await wait_for(lambda: _gripper_above(op, arm, 0.95), what="the claw closed")
            await op.move_pose(arm, 0.18, 0.0, z + 0.06, wait=True)
            # the held ball and the tip from one scene (two reads of it a moment apart saw the
            # servos settle 0.17 mm between them on a slow host)
            w = await op.world(arm)
            r = next(o for o in w.objects if o.id == "r")
            assert r.held and w.tip is not None
            assert math.dist((r.position.x, r.position.y, r.position.z),
                             (w.tip.x, w.tip.y, w.tip.z)) < 1e-9
            assert r.position.z > z + 0.04  # carried up with the tip
            g = await _held(op, arm, "g")
            assert not g.held and (g.position.x, g.position.y) == (0.14, -0.08)
            # over the red bin, open: it falls onto the bin's floor below the tip
            await op.move_pose(arm, 0.075, 0.21, 0.08, wait=True)
            await op.gripper(arm, 0.0)
            await wait_for(lambda: _gripper_below(op, arm, 0.3), what="the claw opening")
            r = await _held(op, arm, "r")
            assert not r.held
            assert abs(r.position.x - 0.075) < 0.01 and abs(r.position.y - 0.21) < 0.01
            assert r.position.z == pytest.approx(0.0 + BALL_D / 2)
            # closing on nothing holds nothing
            await op.gripper(arm, 1.0)
            await wait_for(lambda: _gripper_above(op, arm, 0.95), what="the claw closed")
            assert not any(o.held for o in (await op.world(arm)).objects)


async def _gripper_above(c: AsyncArmClient, arm: str, v: float) -> bool:
    g = (await c.world(arm)).gripper
    return g is not None and g >= v


async def _gripper_below(c: AsyncArmClient, arm: str, v: float) -> bool:
    g = (await c.world(arm)).gripper
    return g is not None and g <= v


def test_magnet_picks_what_it_touches_and_a_bin_rim_strips_it() -> None:
    """The angler's world fed the readings its simulated bus would hold (joint ticks through
    the profile's transmission): a target touched by the magnet follows it; lowered into a bin
    it stays there and is not picked again."""
    profile = load_profile("angler")
    world = World(profile)
    model = world.model
    bin_ = world.scene().bins[0]
    z_table = world.table.z
    world.set_scene([WorldObject("t", "target", "red", (0.0, 0.08, 0.0))], [bin_])

    def go(x: float, y: float, z: float) -> None:
        q = model.ik_best(np.array([x, y, z]), None).positions
        world.observe(tuple(float(t) for t in model.transmission.to_ticks(q)), None)

    top = z_table + TARGET_T
    go(0.0, 0.08, top + 0.03)
    assert not world.scene().objects[0].held
    go(0.0, 0.08, top + 0.002)  # touching
    t = world.scene().objects[0]
    assert t.held and t.position[2] == pytest.approx(top + 0.002 - TARGET_T / 2, abs=1e-6)
    cx, cy = bin_.centre
    go(cx, cy, bin_.hi[2] + 0.02)  # over the bin, above the rim: still held
    assert world.scene().objects[0].held
    go(cx, cy, bin_.hi[2] - 0.005)  # into the bin: the rim strips it
    t = world.scene().objects[0]
    assert not t.held and t.position == pytest.approx((cx, cy, bin_.lo[2] + TARGET_T / 2),
                                                      abs=1e-6)
    go(cx, cy, bin_.lo[2] + TARGET_T + 0.001)  # touching it inside the bin: stays
    assert not world.scene().objects[0].held


async def test_the_openmanipulator_grippers_servo_grasps_too() -> None:
    """The OpenManipulator-X's gripper is its own XM430: the world reads that servo's Present
    Position as the driver converts it (0 open .. 1 closed)."""
    async with clients([load_profile("openmanipulator_x")]) as (op, _, _raw):
        arm = "omx"
        w = await op.world(arm)
        assert w.gripper == pytest.approx(0.5, abs=0.02)  # fingers half open at power-up
        async with op.hold_lease(arm):
            await op.set_world(arm, {"objects": [ball("r", "red", 0.2, 0.0)],
                                     "bins": [b.model_dump(mode="json") for b in w.bins]})
            await op.gripper(arm, 0.0)
            await op.move_pose(arm, 0.2, 0.0, BALL_D / 2 + 0.05, wait=True)
            await wait_for(lambda: _gripper_below(op, arm, 0.05), what="the gripper open")
            await op.move_pose(arm, 0.2, 0.0, BALL_D / 2, wait=True)
            await op.gripper(arm, 1.0)
            await wait_for(lambda: _gripper_above(op, arm, 0.95), what="the gripper closed")
            await op.move_pose(arm, 0.2, 0.0, 0.08, wait=True)
            r = await _held(op, arm, "r")
            assert r.held and r.position.z == pytest.approx(0.08, abs=0.005)
