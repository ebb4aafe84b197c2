"""The motion executor on the simulated arms: line moves stay on their segment (checked against
every telemetry sample), queueing and replacing, cancel decelerates, stop and estop."""

from __future__ import annotations

import asyncio
import json

import numpy as np
import pytest
from _wait import held_still, wait_for

from app import schemas as s
from app.arms.loading import load_profile
from app.config import homed_at_start
from app.errors import EstopLatched, JointLimit, Unreachable
from app.service import ArmService


async def _service(name: str) -> ArmService:
    svc = ArmService(homed_at_start(load_profile(name)))  # simulated: starts at a known pose
    await svc.start()
    assert await svc.driver.wait_connected(5.0)
    return svc


@pytest.fixture
async def rbe():
    svc = await _service("rbe3001")
    yield svc
    await svc.close()


@pytest.fixture
async def angler():
    svc = await _service("angler")
    yield svc
    await svc.close()


def _distance_to_segment(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    ab = b - a
    t = np.clip(((p - a) @ ab) / (ab @ ab), 0.0, 1.0)
    return np.linalg.norm(p - (a + t[:, None] * ab), axis=1)


async def _line_run(svc: ArmService, start_q, target):
    rec = await svc.motion.move_joints(s.MoveJoints(positions=start_q, wait=True))
    await rec.wait()
    assert rec.status == "done", rec.reason
    await held_still(lambda: svc.driver.positions, 2e-4, window=0.1)  # settled at the start
    a = np.array([svc.hub.latest["tip"][k] for k in "xyz"])
    sub = svc.hub.subscribe()
    rec = await svc.motion.move_pose(s.MovePose(x=target[0], y=target[1], z=target[2],
                                                path="line"))
    await rec.wait()
    samples, _, dropped = sub.take()
    sub.close()
    tips = np.array([[json.loads(x)["tip"][k] for k in "xyz"] for x in samples])
    return rec, a, tips, dropped


# Serial (tests/conftest.py): the measured tip against the line, like the measured speeds of
# test_tracking.py: a PID catching up after a control tick that two busy workers held up strays.
@pytest.mark.serial
@pytest.mark.parametrize("name, start_q, target", [
    ("rbe3001", [0.2, 0.7, 0.4], (0.22, -0.06, 0.16)),
    ("angler", [0.0, 0.0, 0.0, 0.05], (0.01, 0.12, 0.02)),
])
async def test_a_line_move_keeps_the_measured_tip_on_the_segment(name, start_q, target):
    svc = await _service(name)
    try:
        rec, a, tips, dropped = await _line_run(svc, start_q, target)
    finally:
        await svc.close()
    assert rec.status == "done", rec.reason
    assert dropped == 0 and len(tips) > 50
    b = np.array(target)
    tol = svc.profile.cartesian.line_tolerance
    dev = _distance_to_segment(tips, a, b)
    print(f"{name}: max deviation from the line {dev.max() * 1000:.2f} mm over {len(tips)} samples")
    assert dev.max() <= tol, (f"tip strayed {dev.max() * 1000:.2f} mm from the line "
                              f"(tol {tol * 1000} mm)")
    # it really went along the line: the samples span it, ending at the target
    assert np.linalg.norm(tips[-1] - b) <= tol
    assert np.linalg.norm(tips[len(tips) // 2] - a) > 0.2 * np.linalg.norm(b - a)


async def test_a_line_through_the_inner_hole_is_refused_before_anything_moves(rbe):
    # both ends reachable, but the segment passes 3 cm from the shoulder, inside |L2 - L3|
    a, b = (0.03, 0.1, 0.2032), (0.03, -0.1, 0.2032)
    rec = await rbe.motion.move_pose(s.MovePose(x=a[0], y=a[1], z=a[2]))
    await rec.wait()
    assert rec.status == "done", rec.reason
    q_before = rbe.driver.positions.copy()
    with pytest.raises((JointLimit, Unreachable)) as info:
        await rbe.motion.move_pose(s.MovePose(x=b[0], y=b[1], z=b[2], path="line"))
    assert "line refused at" in info.value.detail
    assert rbe.motion.current is None and not rbe.motion._queue
    await asyncio.sleep(0.2)  # under test: nothing moves for 0.2 s after the refusal
    np.testing.assert_allclose(rbe.driver.positions, q_before, atol=0.01)
    # the same target by a joint path is fine
    rec = await rbe.motion.move_pose(s.MovePose(x=b[0], y=b[1], z=b[2], path="joint"))
    await rec.wait()
    assert rec.status == "done", rec.reason


async def test_queued_moves_run_in_order_and_replace_takes_over(rbe):
    m1 = await rbe.motion.move_joints(s.MoveJoints(positions=[0.5, 0.7, 0.4]))
    m2 = await rbe.motion.move_joints(s.MoveJoints(positions=[-0.5, 0.7, 0.4]))
    assert (m1.status, m2.status) in {("queued", "queued"), ("running", "queued")}
    await m2.wait()
    assert (m1.status, m2.status) == ("done", "done") and m1.ended <= m2.started
    m3 = await rbe.motion.move_joints(s.MoveJoints(positions=[0.6, 0.9, 0.6]))
    await wait_for(lambda: m3.status == "running" and m3.progress > 0.05, what="m3 under way")
    m4 = await rbe.motion.move_joints(s.MoveJoints(positions=[0.0, 0.8, 0.5], mode="replace"))
    await m4.wait()
    assert m3.status == "stopped" and "replaced" in m3.reason
    assert m4.status == "done"
    np.testing.assert_allclose(rbe.driver.positions, [0.0, 0.8, 0.5], atol=0.03)


async def test_cancel_decelerates_and_holds_short_of_the_target(rbe):
    m = await rbe.motion.move_joints(s.MoveJoints(positions=[1.2, 0.7, 0.4], speed=0.5))
    await wait_for(lambda: rbe.driver.positions[0] > 0.1, what="the base under way")
    await rbe.motion.cancel(m.id)
    assert m.status == "stopped"
    held = rbe.driver.positions.copy()
    assert 0.05 < held[0] < 1.15  # stopped on the way
    await asyncio.sleep(0.5)  # under test: it holds there for 0.5 s
    np.testing.assert_allclose(rbe.driver.positions, held, atol=0.03)  # holds


async def test_estop_latches_refuses_moves_and_release_reenables(rbe):
    m = await rbe.motion.move_joints(s.MoveJoints(positions=[1.0, 0.7, 0.4], speed=0.5))
    queued = await rbe.motion.move_joints(s.MoveJoints(positions=[0.0, 0.7, 0.4]))
    await wait_for(lambda: m.status == "running" and m.progress > 0.05, what="m under way")
    await rbe.latch_estop()
    assert m.status == "stopped" and m.reason == "emergency stop"
    assert queued.status == "stopped"
    held = rbe.driver.positions.copy()
    with pytest.raises(EstopLatched):
        await rbe.motion.move_joints(s.MoveJoints(positions=[0.0, 0.7, 0.4]))
    await asyncio.sleep(0.4)  # under test: the latched arm holds for 0.4 s
    np.testing.assert_allclose(rbe.driver.positions, held, atol=0.05)
    assert rbe.hub.latest["estop"] is True
    await rbe.release_estop()
    # at once, as the latch: a client that reads the state after the release sees it released
    assert rbe.hub.latest["estop"] is False
    m2 = await rbe.motion.move_joints(s.MoveJoints(positions=[0.0, 0.7, 0.4]))
    await m2.wait()
    assert m2.status == "done"


async def test_stop_clears_the_queue(angler):
    m1 = await angler.motion.move_joints(s.MoveJoints(positions=[0.02, 0.0, 0.0, 0.05]))
    m2 = await angler.motion.move_joints(s.MoveJoints(positions=[0.0, 0.02, 0.0, 0.05]))
    await wait_for(lambda: m1.status == "running" and m1.progress > 0.05, what="m1 under way")
    result = await angler.stop()
    assert set(result.stopped) == {m1.id, m2.id}
    assert (m1.status, m2.status) == ("stopped", "stopped")
    assert m1.final_positions is not None and m1.final_positions[0] < 0.02


async def test_a_done_motion_reports_its_real_final_state(angler):
    m = await angler.motion.move_pose(s.MovePose(x=-0.03, y=0.1, z=0.04))
    await m.wait()
    assert m.status == "done"
    tip = angler.model.fk(angler.driver.positions)
    np.testing.assert_allclose([m.final_tip["x"], m.final_tip["y"], m.final_tip["z"]], tip,
                               atol=0.002)
    np.testing.assert_allclose(tip, [-0.03, 0.1, 0.04], atol=0.003)
