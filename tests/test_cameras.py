"""Cameras through the API (issue 25): image-folder sources, detections matching the objects'
true table positions after a four-point calibration (changed lighting, noise), calibration
refusals and persistence, frames encoded once, the MJPEG stream and its slow client, 404 and
503 answers, the config's refusals, and the simulated arm's camera."""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import cv2
import httpx
import numpy as np
import pytest
from _camera_scene import (
    camera_homography,
    clicked,
    project,
    render,
    scene,
    write_folder,
)
from _wait import wait_for
from conftest import OPERATOR, VIEWER, make_settings, wait_ready
from fastapi import FastAPI

from app.arms.loading import load_arms
from app.cameras.config import CameraConfig, load_cameras
from app.cameras.hub import CameraHub
from app.config import ConfigError
from app.sim.camera import SimView
from app.web.factory import create_app

API = "/api/v1"


@contextlib.asynccontextmanager
async def serve(cameras: list[CameraConfig], data_dir: str | None = None, **over: Any
                ) -> AsyncIterator[tuple[FastAPI, httpx.AsyncClient]]:
    settings = make_settings(**({"data_dir": data_dir} if data_dir else {}), **over)
    app = create_app(settings, camera_configs=cameras)
    async with app.router.lifespan_context(app):
        await wait_ready(app)
        transport = httpx.ASGITransport(app=app)
        async with httpx.AsyncClient(transport=transport, base_url="http://armserver.test",
                                     timeout=30.0) as client:
            yield app, client
    assert app.state.internal_errors == 0


def hub(app: FastAPI) -> CameraHub:
    h: CameraHub = app.state.cameras
    return h


async def up(client: httpx.AsyncClient, cam: str) -> None:
    async def check() -> bool:
        return bool((await client.get(f"{API}/cameras/{cam}")).json()["up"])
    await wait_for(check, what=f"camera {cam} up")


def folder_camera(name: str, folder: Path, fps: float = 20.0) -> CameraConfig:
    return CameraConfig(name=name, source=str(folder), arm="rbe3001", fps=fps)


def calibration_body(points: list[Any]) -> dict[str, Any]:
    return {"points": [{"pixel": {"u": u, "v": v}, "position": {"x": x, "y": y, "z": z}}
                       for (u, v), (x, y, z) in points]}


# ---------------------------------------------------------------- detection accuracy


async def test_folder_detections_match_true_positions_within_5mm(tmp_path: Path) -> None:
    h = camera_homography()
    conditions = {"plain": (1.0, 0.0), "dim": (0.6, 6.0), "bright": (1.3, 8.0)}
    discs = {name: scene(seed) for seed, name in enumerate(conditions)}
    cams = []
    for name, (light, noise) in conditions.items():
        folder = write_folder(tmp_path / name, [render(discs[name], h, light=light,
                                                       noise=noise, seed=7)])
        cams.append(folder_camera(name, folder))
    async with serve(cams) as (_, client):
        for name in conditions:
            await up(client, name)
            # before calibration: pixels, no positions
            r = await client.get(f"{API}/cameras/{name}/detections")
            assert r.status_code == 200
            assert all(d["position"] is None for d in r.json()["detections"])
            r = await client.post(f"{API}/cameras/{name}/calibration",
                                  json=calibration_body(clicked(h)))
            assert r.status_code == 200, r.text
            assert r.json()["calibrated"] and r.json()["points"] == 4
            r = await client.get(f"{API}/cameras/{name}/detections")
            body = r.json()
            assert body["camera"] == name and body["took_ms"] > 0
            found = body["detections"]
            assert len(found) == len(discs[name]) == 6
            areas = [d["area"] for d in found]
            assert areas == sorted(areas, reverse=True)
            for d in found:
                pos = d["position"]
                true = min(discs[name], key=lambda q: np.hypot(q.x - pos["x"], q.y - pos["y"]))
                err = np.hypot(true.x - pos["x"], true.y - pos["y"])
                assert err < 0.005, f"{name}: {d} is {err * 1000:.1f} mm from {true}"
                assert d["color"] == true.color
                assert pos["z"] == 0.0
                u0, v0, u1, v1 = d["bbox"]
                assert u0 <= d["pixel"]["u"] <= u1 and v0 <= d["pixel"]["v"] <= v1
            # one colour, largest first, and min_area
            r = await client.get(f"{API}/cameras/{name}/detections",
                                 params={"color": "red"})
            assert [d["color"] for d in r.json()["detections"]] == ["red", "red"]
            r = await client.get(f"{API}/cameras/{name}/detections",
                                 params={"color": "red", "min_area": 100000})
            assert r.json()["detections"] == []


async def test_configured_colour_is_detected(tmp_path: Path) -> None:
    img = np.full((240, 320, 3), 150, np.uint8)
    cv2.circle(img, (100, 120), 20, (0, 128, 255), -1)  # orange, BGR
    folder = write_folder(tmp_path / "o", [img])
    cam = CameraConfig(name="o", source=str(folder), arm="rbe3001", width=320, height=240,
                       colors={"orange": [((5, 120, 100), (20, 255, 255))]})
    async with serve([cam]) as (_, client):
        await up(client, "o")
        r = await client.get(f"{API}/cameras/o/detections", params={"color": "orange"})
        (d,) = r.json()["detections"]
        assert abs(d["pixel"]["u"] - 100) < 0.5 and abs(d["pixel"]["v"] - 120) < 0.5
        r = await client.get(f"{API}/cameras/o/detections", params={"color": "purple"})
        assert r.status_code == 422 and r.json()["code"] == "invalid_request"
        assert "purple" in r.json()["detail"] and "orange" in r.json()["detail"]
        r = await client.get(f"{API}/cameras/o")
        assert {"red", "green", "blue", "yellow", "orange"} <= set(r.json()["colors"])


# ---------------------------------------------------------------- calibration


DEGENERATE = [
    ("three", [((10, 10), (0.1, 0.0, 0)), ((200, 10), (0.1, 0.1, 0)),
               ((10, 200), (0.2, 0.0, 0))], "4 or more points, got 3"),
    ("repeated", [((10, 10), (0.1, 0.0, 0)), ((200, 10), (0.1, 0.1, 0)),
                  ((10, 200), (0.2, 0.0, 0)), ((20, 20), (0.1, 0.0, 0))],
     "points 1 and 4 repeat the same table position"),
    ("collinear", [((10, 10), (0.1, 0.0, 0)), ((20, 20), (0.12, 0.02, 0)),
                   ((30, 30), (0.14, 0.04, 0)), ((40, 40), (0.16, 0.06, 0)),
                   ((50, 50), (0.18, 0.08, 0))], "lie on one line"),
    ("three of four", [((10, 10), (0.1, 0.0, 0)), ((200, 10), (0.1, 0.1, 0)),
                       ((390, 10), (0.1, 0.2, 0)), ((10, 200), (0.2, 0.0, 0))],
     "points 1, 2, 3 lie on one line"),
    ("not level", [((10, 10), (0.1, 0.0, 0)), ((200, 10), (0.1, 0.1, 0)),
                   ((10, 200), (0.2, 0.0, 0.05)), ((200, 200), (0.2, 0.1, 0))],
     "heights differ by 50 mm"),
]


async def test_calibration_refusals_say_why_and_change_nothing(tmp_path: Path) -> None:
    h = camera_homography()
    folder = write_folder(tmp_path / "t", [render(scene(0), h)])
    data_dir = str(tmp_path / "data")
    async with serve([folder_camera("t", folder)], data_dir) as (_, client):
        ok = await client.post(f"{API}/cameras/t/calibration",
                               json=calibration_body(clicked(h)))
        before = ok.json()
        for what, points, reason in DEGENERATE:
            r = await client.post(f"{API}/cameras/t/calibration",
                                  json=calibration_body(points))
            assert r.status_code == 422, what
            assert r.json()["code"] == "invalid_request"
            assert reason in r.json()["detail"], (what, r.json()["detail"])
        assert (await client.get(f"{API}/cameras/t/calibration")).json() == before
        r = await client.post(f"{API}/cameras/t/calibration",
                              json={"points": [{"pixel": {"u": "a", "v": 1}}]})
        assert r.status_code == 422
        r = await client.post(f"{API}/cameras/nope/calibration",
                              json=calibration_body(clicked(h)))
        assert r.status_code == 404 and r.json()["code"] == "not_found"
    # found again after a restart (the store, scope camera:<name>)
    async with serve([folder_camera("t", folder)], data_dir) as (_, client):
        again = (await client.get(f"{API}/cameras/t/calibration")).json()
        assert again == before and again["calibrated"]
        assert (await client.get(f"{API}/cameras")).json()[0]["calibrated"] is True


async def test_sim_camera_true_homography_recovered_from_noisy_points() -> None:
    async with serve([CameraConfig(name="rbe3001", source="sim:rbe3001", arm="rbe3001")]) \
            as (app, client):
        svc = app.state.services["rbe3001"]
        truth = SimView.default_for(svc.profile, 640, 480).table_homography()
        rng = np.random.default_rng(4)
        xy = np.c_[rng.uniform(0.06, 0.30, 12), rng.uniform(-0.2, 0.2, 12)]
        uv = project(truth, xy) + rng.normal(0, 0.5, (12, 2))
        points = [((float(u), float(v)), (float(x), float(y), 0.0))
                  for (u, v), (x, y) in zip(uv, xy, strict=True)]
        r = await client.post(f"{API}/cameras/rbe3001/calibration",
                              json=calibration_body(points))
        cal = r.json()
        assert cal["rms_px"] < 1.0
        fitted = np.array(cal["homography"])
        grid = np.stack(np.meshgrid(np.linspace(0.06, 0.30, 5),
                                    np.linspace(-0.2, 0.2, 5)), -1).reshape(-1, 2)
        err = np.linalg.norm(project(fitted, grid) - project(truth, grid), axis=1)
        assert err.max() < 1.5, err.max()  # 3 sigma of the pixel noise
        # the simulated table as seen: one detection per object, colours as in the world
        r = await client.get(f"{API}/cameras/rbe3001/detections")
        assert r.status_code == 200
        found = sorted(d["color"] for d in r.json()["detections"])
        assert found == sorted(o.color for o in svc.world.scene().objects)
        for d in r.json()["detections"]:
            pos = d["position"]
            near = min(np.hypot(o.position[0] - pos["x"], o.position[1] - pos["y"])
                       for o in svc.world.scene().objects)
            assert near < 0.015  # the objects' tops, seen from above the table plane


async def test_calibration_needs_an_operator_and_the_arms_lease(tmp_path: Path) -> None:
    h = camera_homography()
    folder = write_folder(tmp_path / "t", [render(scene(0), h)])
    body = calibration_body(clicked(h))
    path = f"{API}/cameras/t/calibration"
    op, viewer = {"Authorization": f"Bearer {OPERATOR}"}, {"Authorization": f"Bearer {VIEWER}"}
    async with serve([folder_camera("t", folder)], operator_tokens=OPERATOR,
                     viewer_tokens=VIEWER) as (_, client):
        assert (await client.post(path, json=body)).status_code == 401
        r = await client.post(path, json=body, headers=viewer)
        assert r.status_code == 403 and r.json()["code"] == "forbidden"
        assert (await client.get(path, headers=viewer)).json()["calibrated"] is False
        lease = (await client.post(f"{API}/arms/rbe3001/lease", headers=op)).json()["id"]
        for extra in ({}, {"X-Arm-Lease": "not-the-lease"}):
            r = await client.post(path, json=body, headers={**op, **extra})
            assert r.status_code == 409 and r.json()["code"] == "leased"
        assert (await client.get(path, headers=viewer)).json()["calibrated"] is False
        r = await client.post(path, json=body, headers={**op, "X-Arm-Lease": lease})
        assert r.status_code == 200 and r.json()["calibrated"] is True
        # viewers read frames and detections
        await wait_for(lambda: hub_of_client_ready(client, viewer))
        r = await client.get(f"{API}/cameras/t/detections", headers=viewer)
        assert r.status_code == 200 and all(d["position"] for d in r.json()["detections"])


async def hub_of_client_ready(client: httpx.AsyncClient, headers: dict[str, str]) -> bool:
    return bool((await client.get(f"{API}/cameras/t", headers=headers)).json()["up"])


# ---------------------------------------------------------------- frames and stream


async def test_frame_is_encoded_once_for_many_clients(tmp_path: Path) -> None:
    folder = write_folder(tmp_path / "f", [render(scene(1), camera_homography())])
    async with serve([folder_camera("f", folder, fps=0.5)]) as (app, client):
        await up(client, "f")
        cam = hub(app).get("f")
        answers = await asyncio.gather(*(client.get(f"{API}/cameras/f/frame.jpg")
                                         for _ in range(20)))
        assert all(a.status_code == 200 for a in answers)
        assert all(a.headers["content-type"] == "image/jpeg" for a in answers)
        seqs = {a.headers["x-frame-seq"] for a in answers}
        assert cam.encodes == len(seqs) <= 2
        img = cv2.imdecode(np.frombuffer(answers[0].content, np.uint8), cv2.IMREAD_COLOR)
        assert img.shape == (480, 640, 3)


async def test_unknown_camera_404_and_down_camera_503(tmp_path: Path) -> None:
    gone = tmp_path / "nothing-here"
    async with serve([folder_camera("gone", gone)]) as (app, client):
        for path in ("", "/frame.jpg", "/detections", "/calibration"):
            r = await client.get(f"{API}/cameras/nope{path}")
            assert r.status_code == 404 and r.json()["code"] == "not_found", path
        await wait_for(lambda: "gone" in (hub(app).get("gone").last_error or "")
                       or "nothing-here" in (hub(app).get("gone").last_error or ""))
        for path in ("/frame.jpg", "/detections", "/stream"):
            r = await client.get(f"{API}/cameras/gone{path}")
            assert r.status_code == 503 and r.json()["code"] == "camera_down", path
            assert "nothing-here" in r.json()["detail"]
        health = (await client.get(f"{API}/health")).json()
        assert health["cameras"]["gone"]["up"] is False
        assert "nothing-here" in health["cameras"]["gone"]["last_error"]
        assert health["status"] == "ok"  # the arms serve without a camera


async def test_stream_slow_client_drops_frames_bounded(tmp_path: Path) -> None:
    h = camera_homography()
    folder = write_folder(tmp_path / "s", [render(scene(k), h) for k in range(3)])
    async with serve([folder_camera("s", folder, fps=30)]) as (app, client):
        await up(client, "s")
        feed = hub(app).feed("s")
        slow = feed.frames()
        first = await slow.__anext__()  # then it takes nothing for a while
        assert first.startswith(b"--frame\r\nContent-Type: image/jpeg\r\n")
        await wait_for(lambda: feed.produced >= 6, what="frames produced meanwhile")
        assert feed.dropped >= 4  # one part waits for it, the rest were dropped
        assert feed.clients == 1
        await slow.aclose()
        assert feed.clients == 0


async def test_stream_over_http_and_the_client(tmp_path: Path) -> None:
    from app.client import AsyncArmClient
    folder = write_folder(tmp_path / "m", [render(scene(k), camera_homography())
                                           for k in range(2)])
    async with serve([folder_camera("m", folder, fps=30)]) as (app, client):
        await up(client, "m")
        transport = httpx.ASGITransport(app=app)
        async with AsyncArmClient("http://armserver.test", transport=transport) as c:
            cams = await c.cameras()
            assert [x.name for x in cams] == ["m"] and cams[0].kind == "folder"
            jpeg = await c.camera_frame("m")
            assert jpeg[:2] == b"\xff\xd8"
            detail = await c.camera("m")
            assert detail.up and detail.frame_seq >= 1 and detail.last_error is None
            # ASGITransport buffers a whole body: the stream is read over real HTTP in
            # test_camera_sources.py; here the client's part parser on a real body
            calib = await c.calibrate_camera("m", clicked(camera_homography()))
            assert calib.calibrated and calib.points == 4
            assert (await c.camera_calibration("m")).homography == calib.homography
            det = await c.detections("m", color="blue")
            assert det.detections and all(d.color == "blue" for d in det.detections)


# ---------------------------------------------------------------- config


def test_unknown_camera_key_and_table_refused_with_their_names(tmp_path: Path) -> None:
    cfg = tmp_path / "lab.toml"
    cfg.write_text('[[arms]]\nprofile = "rbe3001"\n\n[[cameras]]\nname = "t"\n'
                   'arm = "rbe3001"\nsource = "/dev/video0"\nframerate = 15\n')
    with pytest.raises(ConfigError, match=r"framerate: unknown key"):
        load_cameras(cfg, load_arms(cfg))
    cfg.write_text('[[arms]]\nprofile = "rbe3001"\n\n[[camera]]\nname = "t"\n')
    with pytest.raises(ConfigError, match=r"unknown table or key camera"):
        load_arms(cfg)
    cfg.write_text('[[arms]]\nprofile = "rbe3001"\n\n[[cameras]]\nname = "t"\n'
                   'arm = "left"\nsource = "0"\n')
    with pytest.raises(ConfigError, match=r"arm = 'left' is not a hosted arm"):
        load_cameras(cfg, load_arms(cfg))
    cfg.write_text('[[arms]]\nprofile = "rbe3001"\n\n[[cameras]]\nname = "t"\n'
                   'arm = "rbe3001"\nsource = "0"\n[cameras.colors]\n'
                   'orange = [[5, 120, 100], [200, 255, 255]]\n')
    with pytest.raises(ConfigError, match=r"H band 5..200"):
        load_cameras(cfg, load_arms(cfg))
    cfg.write_text('[[arms]]\nprofile = "rbe3001"\n\n[[cameras]]\nname = "table"\n'
                   'arm = "rbe3001"\nsource = "/dev/video0"\nwidth = 320\nheight = 240\n'
                   'fps = 30\n[cameras.colors]\norange = [[5, 120, 100], [20, 255, 255]]\n')
    (cam,) = load_cameras(cfg, load_arms(cfg))
    assert (cam.kind, cam.width, cam.fps) == ("device", 320, 30.0)
    assert cam.palette()["orange"] == [((5, 120, 100), (20, 255, 255))]


def test_default_server_has_a_sim_camera_per_simulated_arm() -> None:
    arms = load_arms(None)
    cams = load_cameras(None, arms)
    assert [(c.name, c.source, c.arm) for c in cams] == [
        (a.name, f"sim:{a.name}", a.name) for a in arms if a.link.kind == "sim"]


async def test_default_server_serves_the_sim_camera() -> None:
    app = create_app(make_settings())
    async with app.router.lifespan_context(app):
        await wait_ready(app)
        transport = httpx.ASGITransport(app=app)
        async with httpx.AsyncClient(transport=transport, base_url="http://armserver.test") as c:
            names = [x["name"] for x in (await c.get(f"{API}/cameras")).json()]
            assert names == list(app.state.services)
            r = await c.get(f"{API}/cameras/{names[0]}/frame.jpg")
            assert r.status_code == 200 and r.content[:2] == b"\xff\xd8"


def test_a_shutdown_ends_open_streams_instead_of_waiting_for_them(tmp_path: Path) -> None:
    """uvicorn waits for open responses before it stops, and an MJPEG stream never ends by
    itself: a dashboard left open held every restart for the whole graceful timeout. The
    real server (ArmServer) ends the streams when its shutdown starts."""
    import socket
    import threading
    import time

    import uvicorn

    from app.web.serving import ArmServer

    folder = write_folder(tmp_path / "m", [render(scene(k), camera_homography())
                                           for k in range(2)])
    app = create_app(make_settings(), camera_configs=[folder_camera("m", folder, fps=30)])
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    # a graceful timeout far beyond the wait below: only ending the stream stops it in time
    server = ArmServer(uvicorn.Config(app, host="127.0.0.1", port=port, log_level="warning",
                                      timeout_graceful_shutdown=120), app)
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    url = f"http://127.0.0.1:{port}/api/v1/cameras/m/stream"
    wait_for_sync = time.monotonic() + 30
    while not server.started and time.monotonic() < wait_for_sync:
        time.sleep(0.02)
    assert server.started
    got = b""
    try:
        with httpx.stream("GET", url, timeout=30) as resp:
            assert resp.status_code == 200
            parts = resp.iter_bytes()
            while b"\xff\xd8" not in got:  # a first JPEG: the stream is open
                got += next(parts)
            server.should_exit = True
            for chunk in parts:  # ends when the server ends the response
                got += chunk
        thread.join(30)
        assert not thread.is_alive(), "the server waited for the open stream"
    finally:
        server.force_exit = server.should_exit = True
        thread.join(5)
    assert got.startswith(b"--")
