"""Recordings through the API (app/web/routes/recordings.py) on the simulated arms and their
simulated cameras, in process: datasets created, episodes recorded, discarded, refused, and
what was written read back by tests/_lerobot.py."""

from __future__ import annotations

import io
import tarfile
from pathlib import Path
from typing import Any

import cv2
import httpx
import numpy as np
import pytest

from app.arms.loading import load_arms
from app.cameras.config import CameraConfig
from app.web.factory import create_app
from tests._lerobot import check_dataset
from tests._wait import wait_for
from tests.conftest import make_settings, running_client, wait_ready

API = "/api/v1"
FPS = 10


async def frames_at_least(client: httpx.AsyncClient, rid: str, n: int) -> None:
    """Until recording `rid`'s current episode has `n` frames (bounded)."""
    async def enough() -> bool:
        cur = (await client.get(f"{API}/recordings/{rid}")).json()["current"]
        return cur is not None and cur["frames"] >= n
    await wait_for(enough, timeout=30, what=f"{n} frames recorded")


async def test_record_episodes_discard_and_refusals() -> None:
    async with running_client() as (_, client):
        arms = [a["name"] for a in (await client.get(f"{API}/arms")).json()]
        cams = [c["name"] for c in (await client.get(f"{API}/cameras")).json()]
        body: dict[str, Any] = {"name": "demo", "arms": arms, "cameras": cams[:1], "fps": FPS,
                                "task": "wave"}
        r = await client.post(f"{API}/recordings", json=body)
        assert r.status_code == 201, r.text
        d = r.json()
        assert d["episodes"] == 0 and d["current"] is None and d["recording"] is False
        arm0 = arms[0]
        assert d["names"][0].startswith(f"{arm0}.") and d["names"][-1].startswith(f"{arms[-1]}.")

        # refusals: nothing is made
        for bad, status, code in [
            ({**body, "name": "other", "arms": ["nope"]}, 404, "unknown_arm"),
            ({**body, "name": "other", "cameras": ["nope"]}, 404, "not_found"),
            (body, 409, "conflict"),
            ({**body, "name": "other", "fps": 0}, 422, "invalid_request"),
            ({**body, "name": "../x"}, 422, "invalid_request"),
        ]:
            r = await client.post(f"{API}/recordings", json=bad)
            assert (r.status_code, r.json()["code"]) == (status, code), r.text
        r = await client.post(f"{API}/recordings/demo/episodes/stop")
        assert (r.status_code, r.json()["code"]) == (409, "conflict")
        r = await client.post(f"{API}/recordings/nope/episodes")
        assert (r.status_code, r.json()["code"]) == (404, "not_found")

        # episode 0, with a move of the first arm while it records
        r = await client.post(f"{API}/recordings/demo/episodes", json={"task": "reach"})
        assert r.status_code == 201 and r.json()["recording"] is True
        r = await client.post(f"{API}/recordings/demo/episodes")
        assert (r.status_code, r.json()["code"]) == (409, "busy")
        detail = (await client.get(f"{API}/arms/{arm0}")).json()
        q0 = [(j["min"] + j["max"]) / 2 for j in detail["joints"]]
        target = [q + 0.1 * (j["max"] - j["min"]) for q, j in zip(q0, detail["joints"],
                                                                   strict=True)]
        r = await client.post(f"{API}/arms/{arm0}/gripper", json={"value": 0.7})
        assert r.status_code == 200, r.text
        r = await client.post(f"{API}/arms/{arm0}/move/joints",
                              json={"positions": target, "speed": 0.5, "wait": True})
        assert r.status_code == 200, r.text
        there = (await client.get(f"{API}/recordings/demo")).json()["current"]["frames"]
        await frames_at_least(client, "demo", max(25, there + 3))  # some with the arm there
        r = await client.post(f"{API}/recordings/demo/episodes/stop")
        assert r.status_code == 200, r.text
        assert r.json()["episodes"] == 1 and r.json()["current"] is None

        # episode 1 discarded, episode 2 kept
        assert (await client.post(f"{API}/recordings/demo/episodes")).status_code == 201
        await frames_at_least(client, "demo", 3)
        r = await client.delete(f"{API}/recordings/demo/episodes/current")
        assert r.status_code == 200 and r.json()["episodes"] == 1
        r = await client.delete(f"{API}/recordings/demo/episodes/current")
        assert (r.status_code, r.json()["code"]) == (409, "conflict")
        assert (await client.post(f"{API}/recordings/demo/episodes")).status_code == 201
        await frames_at_least(client, "demo", 5)
        r = await client.post(f"{API}/recordings/demo/episodes/stop")
        d = r.json()
        assert d["episodes"] == 2 and [e["tasks"] for e in d["episode_list"]] == [["reach"],
                                                                                   ["wave"]]

        listed = (await client.get(f"{API}/recordings")).json()
        assert [(x["id"], x["episodes"], x["frames"]) for x in listed] == [
            ("demo", 2, d["frames"])]

        read = check_dataset(Path(d["path"]))
        assert read.tasks == {0: "reach", 1: "wave"}
        ep0 = read.episode(0)
        n0 = len(ep0["index"])
        assert n0 >= 25
        cols = [i for i, n in enumerate(d["names"]) if n.startswith(f"{arm0}.")]
        cols = cols[:len(target)]
        # the action is the commanded setpoint: at the end, the move's target exactly
        assert np.allclose(ep0["action"][-1, cols], target, atol=1e-5)
        # the state is the measured joints: at the end, near the target
        assert np.allclose(ep0["observation.state"][-1, cols], target, atol=0.02)
        # the joints' velocities: moving during the move, still at the end
        vnames = read.info["features"]["observation.velocity"]["names"]
        assert vnames[:len(target)] == [n.replace(".pos", ".vel") for n in
                                        d["names"][:len(target)]]
        vel = ep0["observation.velocity"][:, :len(target)]
        assert np.abs(vel).max() > 0.05 and np.abs(vel[-1]).max() < 0.05
        # the gripper's action is its command
        assert d["names"][len(target)] == f"{arm0}.gripper.pos"
        assert ep0["action"][-1, len(target)] == np.float32(0.7)
        assert ep0["observation.state"][-1, len(target)] == pytest.approx(0.7, abs=0.01)
        # the arms that did not move: state and action steady
        assert np.ptp(ep0["observation.state"][:, len(target) + 1:], axis=0).max() < 0.01

        r = await client.get(f"{API}/recordings/demo/archive")
        assert r.status_code == 200 and r.headers["content-type"] == "application/x-tar"
        with tarfile.open(fileobj=io.BytesIO(r.content)) as tar:
            names = tar.getnames()
            assert "demo/meta/info.json" in names
            assert not any("/." in n for n in names)
            info = tar.extractfile("demo/meta/info.json")
            assert info is not None
            assert info.read() == (Path(d["path"]) / "meta/info.json").read_bytes()


async def test_disk_full_answers_503_and_keeps_the_dataset(tmp_path: Path) -> None:
    async with running_client() as (_, client):
        arms = [a["name"] for a in (await client.get(f"{API}/arms")).json()]
        r = await client.post(f"{API}/recordings", json={"name": "full", "arms": arms[:1],
                                                          "fps": FPS})
        root = Path(r.json()["path"])
        assert (await client.post(f"{API}/recordings/full/episodes")).status_code == 201
        await frames_at_least(client, "full", 3)
        assert (await client.post(f"{API}/recordings/full/episodes/stop")).status_code == 200
        # the kernel's ENOSPC: the frames' temporary file is /dev/full
        (root / "data/chunk-000/.file-000.parquet.tmp").symlink_to("/dev/full")
        assert (await client.post(f"{API}/recordings/full/episodes")).status_code == 201
        await frames_at_least(client, "full", 3)
        r = await client.post(f"{API}/recordings/full/episodes/stop")
        assert (r.status_code, r.json()["code"]) == (503, "recording_failed"), r.text
        d = (await client.get(f"{API}/recordings/full")).json()
        assert d["episodes"] == 1 and d["recording"] is False
        assert "No space left" in d["last_error"]
        assert check_dataset(root).info["total_episodes"] == 1
        # and it records on
        assert (await client.post(f"{API}/recordings/full/episodes")).status_code == 201
        await frames_at_least(client, "full", 3)
        r = await client.post(f"{API}/recordings/full/episodes/stop")
        assert r.json()["episodes"] == 2 and r.json()["last_error"] is None
        check_dataset(root)


async def test_a_camera_lost_mid_episode_ends_it_and_keeps_it(tmp_path: Path) -> None:
    folder = tmp_path / "images"
    folder.mkdir()
    for k in range(3):
        cv2.imwrite(str(folder / f"{k}.png"), np.full((48, 64, 3), 60 * k, np.uint8))
    settings = make_settings()
    profiles = load_arms(None)
    cams = [CameraConfig(name="desk", source=str(folder), arm=profiles[0].name, width=64,
                         height=48, fps=10.0)]
    app = create_app(settings, profiles=profiles, camera_configs=cams)
    async with app.router.lifespan_context(app):
        await wait_ready(app)
        async with httpx.AsyncClient(transport=httpx.ASGITransport(app=app),
                                     base_url="http://armserver.test", timeout=30) as client:
            r = await client.post(f"{API}/recordings", json={
                "name": "cam", "arms": [profiles[0].name], "cameras": ["desk"], "fps": FPS})
            assert r.status_code == 201, r.text
            assert (await client.post(f"{API}/recordings/cam/episodes")).status_code == 201
            await frames_at_least(client, "cam", 5)
            for p in folder.iterdir():
                p.unlink()

            async def ended() -> bool:
                d = (await client.get(f"{API}/recordings/cam")).json()
                return not d["recording"] and d["episodes"] == 1
            await wait_for(ended, timeout=30, what="the episode ended and written")
            d = (await client.get(f"{API}/recordings/cam")).json()
            assert "camera desk lost" in d["last_error"], d
            read = check_dataset(Path(d["path"]))
            assert read.episodes[0]["length"] >= 5
    assert app.state.internal_errors == 0


async def test_shutdown_writes_the_episode_that_records() -> None:
    async with running_client() as (app, client):
        arms = [a["name"] for a in (await client.get(f"{API}/arms")).json()]
        r = await client.post(f"{API}/recordings", json={"name": "bye", "arms": arms[:1],
                                                          "fps": FPS})
        root = Path(r.json()["path"])
        assert (await client.post(f"{API}/recordings/bye/episodes")).status_code == 201
        await frames_at_least(client, "bye", 4)
    read = check_dataset(root)  # the lifespan's end wrote it
    assert read.info["total_episodes"] == 1 and read.episodes[0]["length"] >= 4


async def test_a_broken_dataset_folder_is_left_out_at_start(tmp_path: Path) -> None:
    bad = tmp_path / "recordings" / "bad"
    (bad / "meta").mkdir(parents=True)
    (bad / "armserver.json").write_text('{"name": "bad"}')
    (bad / "meta" / "info.json").write_text("{not json")
    async with running_client(make_settings(data_dir=str(tmp_path))) as (_, client):
        assert (await client.get(f"{API}/recordings")).json() == []
        arms = [a["name"] for a in (await client.get(f"{API}/arms")).json()]
        r = await client.post(f"{API}/recordings", json={"name": "bad", "arms": arms[:1]})
        assert (r.status_code, r.json()["code"]) == (409, "conflict")  # its folder is there
        r = await client.post(f"{API}/recordings", json={"name": "good", "arms": arms[:1]})
        assert r.status_code == 201, r.text
