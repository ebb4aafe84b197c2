"""Replaying joint targets at a frame rate as one motion (app/motion/replay.py), on a simulated
OpenManipulator-X behind its real link: the soft start, the frames' tip path, the checks
before anything moves (joint limits, speed, the envelope, the frame rate), and stop and
estop like any motion."""

from __future__ import annotations

from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import orjson
import pytest
from _wait import wait_for
from fastapi import FastAPI

from app.errors import ArmError
from app.service import ArmService
from tests.conftest import make_settings, running_client

API = "/api/v1"
CONFIG = Path(__file__).resolve().parents[1] / "config" / "teleop_omx.toml"
FPS = 30.0


@pytest.fixture()
async def omx() -> AsyncIterator[tuple[FastAPI, httpx.AsyncClient]]:
    async with running_client(make_settings(config=str(CONFIG))) as pair:
        yield pair


def arm_of(app: FastAPI, name: str = "leader") -> ArmService:
    arm: ArmService = app.state.services[name]
    return arm


def wave(seconds: float = 2.0, fps: float = FPS) -> np.ndarray:
    """A smooth path well inside the OMX's limits and speed (under 1 rad/s)."""
    t = np.arange(int(seconds * fps)) / fps
    w = 2 * np.pi / seconds
    return np.stack([0.5 * np.sin(w * t), -0.3 + 0.2 * np.sin(w * t), 0.2 + 0.2 * np.cos(w * t),
                     0.5 + 0.1 * np.sin(2 * w * t)], axis=1)


def path_distance(points: np.ndarray, path: np.ndarray) -> np.ndarray:
    """Each point's distance (m) to the polyline `path` (k, 3)."""
    a, b = path[:-1], path[1:]
    ab = b - a
    out = []
    for p in points:
        t = np.clip(np.einsum("ij,ij->i", p - a, ab) / np.maximum(
            np.einsum("ij,ij->i", ab, ab), 1e-18), 0.0, 1.0)
        out.append(float(np.min(np.linalg.norm(a + t[:, None] * ab - p, axis=1))))
    return np.asarray(out)


def farthest(off: np.ndarray, samples: list[dict[str, Any]]) -> str:
    """Where a played path is farthest from its path (`off`, one distance per sample of
    `samples`), for a failure's message: when, and how far apart the samples around it came
    (a process that lost its pace, as beside the browser tests, shows gaps of several sample
    periods there: tests/conftest.py)."""
    t = np.array([float(smp["time"]) for smp in samples])
    k = int(np.argmax(off))
    gaps = np.diff(t[np.abs(t - t[k]) <= 0.05])
    return (f"{off[k] * 1e3:.2f} mm at {t[k] - t[0]:.2f} s of {t[-1] - t[0]:.2f}, the samples "
            f"within 50 ms of it up to {np.max(gaps, initial=0.0) * 1e3:.1f} ms apart (all of "
            f"them: median {np.median(np.diff(t)) * 1e3:.1f} ms)")


#: After a sample that comes more than PAUSE_PERIODS sample periods after the one before it
#: (the control loop lost its pace: the host, a busy 2-core machine), the streamed setpoints
#: have jumped ahead and the servos cut the chord to them: the samples up to AFTER_PAUSE_S
#: after such a gap are held to LOOSE times the bound, the rest to the bound. (CI's stop 45
#: and a clean clone in session 29: 3.31 and 2.71 mm, each just after a 20 ms gap.)
PAUSE_PERIODS = 3.0
AFTER_PAUSE_S = 0.1
LOOSE = 2.5


def assert_on_path(off: np.ndarray, samples: list[dict[str, Any]], bound: float,
                   what: str) -> None:
    """Each sample's distance from its path (`off`, m) under `bound`; under LOOSE x `bound`
    just after a pause of the control loop (above). At least 30 samples judged strictly."""
    t = np.array([float(smp["time"]) for smp in samples])
    dt = np.diff(t)
    ends = t[1:][dt > PAUSE_PERIODS * float(np.median(dt))]
    after = np.zeros(len(t), dtype=bool)
    for end in ends:
        after |= (t >= end) & (t <= end + AFTER_PAUSE_S)
    assert int(np.count_nonzero(~after)) > 30, f"{what}: too few samples away from pauses"
    assert float(np.max(off[~after])) < bound, f"{what}: {farthest(off * ~after, samples)}"
    assert float(np.max(off)) < LOOSE * bound, \
        f"{what}, just after a pause: {farthest(off * after, samples)}"


#: The path is judged against wall-clock servos: in the serial part's browser lane
#: (tests/conftest.py), never beside a browser test nor the parallel part (it missed 2 mm at
#: load average 9-13 beside the parallel part, and beside browser tests: 2.1-3.8 mm).
@pytest.mark.serial
async def test_replay_follows_the_frames_tip_path(
        omx: tuple[FastAPI, httpx.AsyncClient]) -> None:
    app, c = omx
    arm = arm_of(app)
    targets = wave()
    sub = arm.subscribe(4000)
    try:
        rec = await arm.replay(targets, FPS)
        assert rec.kind == "joints" and rec.path == "joint"
        np.testing.assert_allclose(rec.target, targets[-1])
        await rec.wait()
        assert rec.status == "done", (rec.reason, rec.code)
        # the frames' part lasts exactly (T - 1) / fps after the soft start
        assert rec.planned_duration >= (len(targets) - 1) / FPS
        samples = [orjson.loads(x) for x in sub.take()[0]]
    finally:
        sub.close()
    moving = [smp for smp in samples
              if (smp.get("motion") or {}).get("id") == rec.id
              and (smp["motion"]["status"] == "running")]
    q = np.array([smp["positions"] for smp in moving], dtype=float)
    # the part of the motion after the soft start: from where the tip first reaches frame 0
    path = np.asarray(arm.model.fk(dense(targets)), dtype=float)
    tips = np.asarray(arm.model.fk(q), dtype=float)
    start = np.asarray(arm.model.fk(targets[0]), dtype=float)
    # the soft start ends at rest on the first frame: from the first sample there (its
    # approach, from elsewhere, is not the recording's path)
    reached = int(np.argmax(np.linalg.norm(tips - start, axis=1) < 0.0005))
    d = path_distance(tips[reached:], path)
    assert len(d) > 30
    assert_on_path(d, moving[reached:], 0.002, "tip off the frames' path")
    final = (await c.get(f"{API}/arms/leader/state")).json()["positions"]
    np.testing.assert_allclose(final, targets[-1], atol=8 * 2 * np.pi / 4096)


def dense(targets: np.ndarray, k: int = 20) -> np.ndarray:
    """The frames linearly interpolated k times per interval (the executor's own path)."""
    s = np.linspace(0.0, 1.0, k, endpoint=False)
    parts = [a + s[:, None] * (b - a) for a, b in zip(targets[:-1], targets[1:], strict=True)]
    return np.concatenate([*parts, targets[-1:]])


@pytest.mark.parametrize(("change", "code"), [
    ("beyond_limit", "joint_limit"),
    ("nan", "invalid_request"),
    ("wrong_width", "invalid_request"),
    ("fps", "invalid_request"),
])
async def test_replay_refuses_bad_frames_before_moving(
        omx: tuple[FastAPI, httpx.AsyncClient], change: str, code: str) -> None:
    app, _ = omx
    arm = arm_of(app)
    targets, fps = wave(), FPS
    if change == "too_fast":
        targets[10:, 0] += 1.0  # a 1 rad jump in one frame: 30 rad/s
    elif change == "beyond_limit":
        targets[5, 1] = 3.0
    elif change == "nan":
        targets[3, 2] = np.nan
    elif change == "wrong_width":
        targets = targets[:, :3]
    else:
        fps = 0.0
    with pytest.raises(ArmError) as err:
        await arm.replay(targets, fps)
    assert err.value.code == code, err.value.detail
    assert not arm.moving


async def test_replay_refused_by_the_envelope(omx: tuple[FastAPI, httpx.AsyncClient]) -> None:
    app, c = omx
    arm = arm_of(app)
    targets = wave()
    p = np.asarray(arm.model.fk(targets[len(targets) // 4]), dtype=float)  # a frame's tip
    box = {"name": "cup", "min": dict(zip("xyz", (p - 0.01).tolist(), strict=True)),
           "max": dict(zip("xyz", (p + 0.01).tolist(), strict=True))}
    r = await c.put(f"{API}/arms/leader/safety", json={"zones": [box]})
    assert r.status_code == 200, r.text
    with pytest.raises(ArmError) as err:
        await arm.replay(targets, FPS)
    assert err.value.code == "keep_out", err.value.detail
    assert not arm.moving


@pytest.mark.parametrize("how", ["stop", "cancel", "estop"])
async def test_replay_stops_like_any_motion(omx: tuple[FastAPI, httpx.AsyncClient],
                                            how: str) -> None:
    app, c = omx
    arm = arm_of(app)
    rec = await arm.replay(wave(seconds=4.0), FPS)
    await wait_for(lambda: rec.status == "running" and rec.progress > 0.3,
                   what="the replay past its soft start")
    if how == "stop":
        r = await c.post(f"{API}/arms/leader/stop")
    elif how == "cancel":
        r = await c.delete(f"{API}/arms/leader/motions/{rec.id}")
    else:
        r = await c.post(f"{API}/arms/leader/estop")
    assert r.status_code == 200, r.text
    await rec.wait()
    assert rec.status == "stopped"
    assert rec.reason is not None
    if how == "estop":
        assert rec.reason == "emergency stop"
        assert (await c.delete(f"{API}/arms/leader/estop")).status_code == 200


async def test_a_step_over_the_speed_limit_is_played_at_the_limit(
        omx: tuple[FastAPI, httpx.AsyncClient]) -> None:
    """A frame that jumps (a recording's grid jitter, a faster arm) keeps its path and takes
    as long as the velocity limit times the tracking margin needs; the rest keeps its fps."""
    app, _ = omx
    arm = arm_of(app)
    targets = np.repeat(wave(seconds=1.0)[:1], 30, axis=0)
    targets[15:, 0] += 1.0  # 1 rad in one frame: 30 rad/s as recorded
    cap = float(arm.model.vmax[0]) * arm.profile.tracking_margin
    rec = await arm.replay(targets, FPS)
    frames = rec.planned_duration
    assert frames >= 28 / FPS + 1.0 / cap - 1e-6
    await rec.wait()
    assert rec.status == "done", (rec.reason, rec.code)
    np.testing.assert_allclose(rec.final_positions, targets[-1], atol=8 * 2 * np.pi / 4096)


def test_the_path_judgement_is_loose_only_just_after_a_pause() -> None:
    """`assert_on_path` on made-up samples 5 ms apart with one 20 ms gap at 0.5 s: 3 mm off
    just after the gap passes a 2 mm bound, the same 3 mm away from it fails, and 6 mm just
    after it fails."""
    t = np.concatenate([np.arange(0.0, 0.5, 0.005), np.arange(0.52, 1.0, 0.005)])
    samples = [{"time": x} for x in t]
    after_gap = int(np.argmax(t >= 0.52)) + 2
    off = np.full(len(t), 0.0005)
    off[after_gap] = 0.003
    assert_on_path(off, samples, 0.002, "just after the gap")
    away = off.copy()
    away[after_gap], away[10] = 0.0005, 0.003
    with pytest.raises(AssertionError, match="3.00 mm at 0.05 s"):
        assert_on_path(away, samples, 0.002, "away from it")
    off[after_gap] = 0.006
    with pytest.raises(AssertionError, match="just after a pause: 6.00 mm"):
        assert_on_path(off, samples, 0.002, "too far")
