"""The simulated camera (app/sim/camera.py): a pinhole view of the world, deterministic for a
seed. The objects' table positions come back from the rendered image through the view's own
table homography within a pixel; the bins are not taken for objects by the camera's colour
detection (app/cameras/detect.py), under changed light and with noise."""

from __future__ import annotations

import math

import numpy as np
import pytest

from app.arms.loading import load_profile
from app.cameras.config import DEFAULT_COLORS
from app.cameras.detect import detect
from app.sim.camera import SimView, render
from app.sim.world import COLORS, World, WorldObject, height, random_objects

W, H = 640, 480


def _apply(h: np.ndarray, xy: tuple[float, float]) -> np.ndarray:
    p = h @ np.array([xy[0], xy[1], 1.0])
    return np.asarray(p[:2] / p[2])


@pytest.mark.parametrize("arm", ["rbe3001", "angler"])
def test_homography_is_the_projection_of_the_table(arm: str) -> None:
    view = SimView.default_for(load_profile(arm))
    rng = np.random.default_rng(1)
    xy = rng.uniform(-0.1, 0.3, (20, 2))
    pts = np.column_stack([xy, np.full(20, view.table_z)])
    hom = view.table_homography()
    for p, uv in zip(pts, view.project(pts), strict=True):
        np.testing.assert_allclose(_apply(hom, (p[0], p[1])), uv, atol=1e-9)
    # looking straight down from above the workspace: +x up the image, +y to the left
    u0, v0 = _apply(hom, (0.1, 0.0))
    u1, v1 = _apply(hom, (0.2, 0.0))
    u2, _ = _apply(hom, (0.1, 0.1))
    assert v1 < v0 and u2 < u0


@pytest.mark.parametrize(("arm", "noise", "light"), [
    ("rbe3001", 0.0, 1.0), ("rbe3001", 0.02, 0.6), ("angler", 0.02, 1.3), ("angler", 0.0, 0.8)])
def test_objects_come_back_through_the_homography_within_a_pixel(
        arm: str, noise: float, light: float) -> None:
    """Each object's blob centroid (the camera's own detection: HSV bands, clean-up,
    components), taken back to the plane of its visible face through that plane's homography,
    is the object's (x, y); its pixel is within one of where the homography puts it. Only the
    objects are found: the bins, tinted in the same colours, are not."""
    profile = load_profile(arm)
    world = World(profile)
    objects = random_objects(world, seed=7, n=6, colors=("red", "green", "blue", "yellow"))
    world.set_scene(objects, world.scene().bins)
    view = SimView.default_for(profile)
    image = render(world, view, W, H, noise=noise, light=light, seed=3)
    blobs = detect(image, DEFAULT_COLORS, list(DEFAULT_COLORS), min_area=40)
    scene = world.scene()
    assert len(blobs) == len(scene.objects), [(b.color, b.area) for b in blobs]
    for o in scene.objects:
        mine = [b for b in blobs if b.color == o.color]
        # the plane of what the camera sees of it: a disc's or block's top, a ball's centre
        z = o.position[2] + (0.0 if o.kind == "ball" else height(o.kind) / 2)
        hom = view.table_homography(z)
        want = _apply(hom, (o.position[0], o.position[1]))
        b = min(mine, key=lambda b: math.dist((b.u, b.v), want))
        assert math.dist((b.u, b.v), want) < 1.0, (o, b, want)
        back = np.linalg.solve(hom, np.array([b.u, b.v, 1.0]))
        metres_per_px = (view.position[2] - z) / view.fx
        assert math.dist(back[:2] / back[2], o.position[:2]) < metres_per_px


def test_render_is_deterministic_for_a_seed_and_light_scales_it() -> None:
    profile = load_profile("rbe3001")
    world = World(profile)
    view = SimView.default_for(profile)
    a = render(world, view, W, H, noise=0.03, seed=5)
    b = render(world, view, W, H, noise=0.03, seed=5)
    c = render(world, view, W, H, noise=0.03, seed=6)
    assert a.shape == (H, W, 3) and a.dtype == np.uint8
    assert a.tobytes() == b.tobytes() and a.tobytes() != c.tobytes()
    clean = render(world, view, W, H)
    assert clean.tobytes() == render(world, view, W, H, seed=99).tobytes()
    dim = render(world, view, W, H, light=0.5)
    assert float(dim.mean()) == pytest.approx(float(clean.mean()) * 0.5, rel=0.01)
    # another size is the same camera: the same table point lands on the scaled pixel
    small = view.scaled(320, 240)
    np.testing.assert_allclose(_apply(small.table_homography(), (0.15, 0.05)),
                               (_apply(view.table_homography(), (0.15, 0.05)) + 0.5) / 2 - 0.5,
                               atol=1e-9)
    assert render(world, view, 320, 240).shape == (240, 320, 3)


def test_a_plain_picture_skips_the_light_pass_with_the_same_bytes() -> None:
    """Without light or noise render() returns the picture as drawn (app/sim/camera.py): the
    same bytes the light pass gives at a light of 1 (forced here by a light a hair above it),
    and a picture of its own, not the cached empty table."""
    profile = load_profile("angler")
    world = World(profile)
    random_objects(world, 3, 6)
    view = SimView.default_for(profile)
    plain = render(world, view, W, H)
    passed = render(world, view, W, H, light=1.0 + 1e-12)
    assert plain.dtype == np.uint8 and plain.tobytes() == passed.tobytes()
    plain[:] = 0  # the caller's to keep or change
    assert render(world, view, W, H).tobytes() == passed.tobytes()


def test_a_held_object_is_drawn_where_the_tip_carries_it() -> None:
    profile = load_profile("rbe3001")
    world = World(profile)
    model = world.model
    world.set_scene([WorldObject("r", "ball", "red", (0.18, 0.0, 0.0))], [])
    q = model.ik_best(np.array([0.18, 0.0, 0.0125]), None).positions
    ticks = tuple(float(t) for t in model.transmission.to_ticks(q))
    world.observe(ticks, 0.0)
    world.observe(ticks, 1.0)  # the claw closes around it
    q2 = model.ik_best(np.array([0.12, 0.1, 0.08]), None).positions
    world.observe(tuple(float(t) for t in model.transmission.to_ticks(q2)), 1.0)
    o = world.scene().objects[0]
    assert o.held
    view = SimView.default_for(profile)
    blobs = detect(render(world, view, W, H), DEFAULT_COLORS, ["red"], min_area=40)
    assert len(blobs) == 1
    np.testing.assert_allclose((blobs[0].u, blobs[0].v), view.project(np.array(o.position)),
                               atol=1.0)
    assert set(COLORS) == set(DEFAULT_COLORS)
