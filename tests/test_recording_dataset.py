"""The LeRobot v3.0 writer and reader (app/recording/dataset.py) on their own: episodes of
generated frames and videos, read back by tests/_lerobot.py's independent reader."""

from __future__ import annotations

import errno
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest

from app.recording.dataset import ArmLayout, Dataset, EpisodeFrames
from app.recording.video import EpisodeVideo
from tests._lerobot import check_dataset, decode

FPS = 30
W, H = 64, 48
ARMS = [ArmLayout("left", ("base", "elbow"), True), ArmLayout("right", ("z",), False)]


def colour(k: int) -> tuple[int, int]:
    """Frame k's blue and green levels (one in 14 x 14 frames has the same pair)."""
    return (k * 15) % 210 + 20, (k // 14 * 15) % 210 + 20


def image(k: int) -> np.ndarray:
    """Frame k, BGR."""
    b, g = colour(k)
    out = np.zeros((H, W, 3), np.uint8)
    out[..., 0], out[..., 1], out[..., 2] = b, g, 128
    return out


def colour_of(rgb: np.ndarray) -> tuple[int, int]:
    return int(round(rgb[..., 2].mean())), int(round(rgb[..., 1].mean()))


def episode(ds: Dataset, n: int, seed: int, task: str = "pick") -> EpisodeFrames:
    video = EpisodeVideo(ds.partial_dir() / f"{seed}.mp4", W, H, FPS)
    for k in range(n):
        video.add(image(k))
    video.close()
    rng = np.random.default_rng(seed)
    states = rng.uniform(-1, 1, (n, 4))
    return EpisodeFrames(states, states * 0.5, task, {"cam": video.path},
                         {"cam": np.full((2, H, W, 3), 99, np.uint8)})


def make(tmp_path: Path, cameras: bool = True) -> Dataset:
    return Dataset.create(tmp_path / "ds", FPS, ARMS, {"cam": (W, H)} if cameras else {},
                          "test_arm")


def test_three_episodes_read_back(tmp_path: Path) -> None:
    ds = make(tmp_path)
    eps = [episode(ds, n, i, task) for i, (n, task) in
           enumerate([(40, "pick"), (25, "place"), (12, "pick")])]
    for e in eps:
        ds.append(e)
    read = check_dataset(ds.root)
    assert read.info["total_episodes"] == 3 and read.info["total_frames"] == 77
    assert read.tasks == {0: "pick", 1: "place"}
    assert read.info["features"]["observation.state"]["names"] == [
        "left.base.pos", "left.elbow.pos", "left.gripper.pos", "right.z.pos"]
    for i, e in enumerate(eps):
        got = read.episode(i)
        assert np.array_equal(got["observation.state"], e.states.astype(np.float32))
        assert np.array_equal(got["action"], e.actions.astype(np.float32))
        row = read.episodes[i]
        key = "observation.images.cam"
        t0 = row[f"videos/{key}/from_timestamp"]
        frames = decode(ds.root / "videos" / key / "chunk-000/file-000.mp4",
                        [t0 + k / FPS for k in range(len(e.states))], FPS)
        for k, f in enumerate(frames):  # within the YUV round trip's few levels
            assert np.allclose(colour_of(f), colour(k), atol=5), (i, k)
    assert read.info["features"]["observation.images.cam"]["info"]["video.pix_fmt"] == "yuv420p"
    # the read side the replay builds on
    again = Dataset.open(ds.root)
    ep = again.load_episode(1)
    assert ep.fps == FPS and ep.task == "place" and len(ep.timestamps) == 25
    assert np.allclose(ep.states, eps[1].states, atol=1e-6)
    assert ep.arm_columns("right") == [3] and ep.arm_columns("left") == [0, 1, 2]
    assert [e.length for e in again.episodes()] == [40, 25, 12]
    with pytest.raises(IndexError):
        again.load_episode(3)


def test_reopen_appends(tmp_path: Path) -> None:
    ds = make(tmp_path)
    ds.append(episode(ds, 10, 1))
    ds = Dataset.open(ds.root)
    ds.append(episode(ds, 11, 2, "other"))
    read = check_dataset(ds.root)
    assert [e["length"] for e in read.episodes] == [10, 11]
    assert read.episodes[1]["videos/observation.images.cam/from_timestamp"] == pytest.approx(
        10 / FPS)


def test_a_write_cut_short_is_repaired_on_open(tmp_path: Path) -> None:
    """Killed after the frames and the video were written but before the episodes table: the
    episode is not there, and the next one follows the last complete one."""
    ds = make(tmp_path)
    ds.append(episode(ds, 10, 1))
    data = ds.root / "data/chunk-000/file-000.parquet"
    before = pq.read_table(data)
    ds.append(episode(ds, 8, 2))
    # put back the metadata of one episode, as if the process died before writing it
    ds2 = make(tmp_path / "copy")
    ds2.append(episode(ds2, 10, 1))
    for name in ("meta/episodes/chunk-000/file-000.parquet", "meta/info.json",
                 "meta/stats.json"):
        (ds.root / name).write_bytes((ds2.root / name).read_bytes())
    reopened = Dataset.open(ds.root)
    assert pq.read_table(data).num_rows == before.num_rows
    reopened.append(episode(reopened, 5, 3))
    read = check_dataset(ds.root)
    assert [e["length"] for e in read.episodes] == [10, 5]
    # the video file held 18 frames: the new episode started a new file
    assert read.episodes[1]["videos/observation.images.cam/file_index"] == 1


def test_no_cameras(tmp_path: Path) -> None:
    ds = make(tmp_path, cameras=False)
    n = 9
    states = np.linspace(0, 1, n * 4).reshape(n, 4)
    ds.append(EpisodeFrames(states, states, "t"))
    read = check_dataset(ds.root)
    assert read.info["video_path"] is None
    assert np.allclose(read.frames["observation.state"], states)


def test_refuses_a_wrong_shape(tmp_path: Path) -> None:
    ds = make(tmp_path, cameras=False)
    with pytest.raises(ValueError, match="names"):
        ds.append(EpisodeFrames(np.zeros((3, 2)), np.zeros((3, 2)), "t"))
    assert not (ds.root / "data").exists()


def test_disk_full_loses_that_episode_only(tmp_path: Path) -> None:
    """ENOSPC from the kernel (the frames' temporary file is /dev/full): the episode is not
    written, the dataset keeps the earlier ones, and the next episode is written after them."""
    ds = make(tmp_path)
    ds.append(episode(ds, 10, 1))
    tmp = ds.root / "data/chunk-000/.file-000.parquet.tmp"
    tmp.symlink_to("/dev/full")
    with pytest.raises(OSError) as info:
        ds.append(episode(ds, 7, 2, "new task"))
    assert info.value.errno == errno.ENOSPC
    assert not tmp.is_symlink()  # no half file left
    read = check_dataset(ds.root)  # the video file was joined before the failure: repaired
    assert [e["length"] for e in read.episodes] == [10]
    ds.append(episode(ds, 5, 3))
    read = check_dataset(ds.root)
    assert [e["length"] for e in read.episodes] == [10, 5]
    assert [e["videos/observation.images.cam/file_index"] for e in read.episodes] == [0, 1]
    assert Dataset.open(ds.root).episodes()[1].length == 5


def test_two_cameras_each_their_own_video(tmp_path: Path) -> None:
    ds = Dataset.create(tmp_path / "two", FPS, ARMS, {"a": (W, H), "b": (32, 32)}, "t")
    for n, seed in ((6, 1), (9, 2)):
        videos, samples = {}, {}
        for cam, (w, h), shift in (("a", (W, H), 0), ("b", (32, 32), 5)):
            v = EpisodeVideo(ds.partial_dir() / f"{seed}-{cam}.mp4", w, h, FPS)
            for k in range(n):
                v.add(image(k + shift)[:h, :w])
            v.close()
            videos[cam], samples[cam] = v.path, np.zeros((1, h, w, 3), np.uint8)
        states = np.full((n, 4), float(seed))
        ds.append(EpisodeFrames(states, states, "t", videos, samples))
    read = check_dataset(ds.root)
    assert read.info["features"]["observation.images.b"]["shape"] == [32, 32, 3]
    for cam, shift in (("a", 0), ("b", 5)):
        key = f"observation.images.{cam}"
        t0 = read.episodes[1][f"videos/{key}/from_timestamp"]
        assert t0 == pytest.approx(6 / FPS)
        frames = decode(ds.root / "videos" / key / "chunk-000/file-000.mp4",
                        [t0 + k / FPS for k in range(9)], FPS)
        for k, f in enumerate(frames):
            assert np.allclose(colour_of(f), colour(k + shift), atol=5), (cam, k)


def test_velocities_read_back(tmp_path: Path) -> None:
    ds = Dataset.create(tmp_path / "v", FPS, ARMS, {}, "t", velocity=True)
    n = 7
    states = np.arange(n * 4, dtype=float).reshape(n, 4) / 10
    vel = -np.arange(n * 3, dtype=float).reshape(n, 3) / 100
    ds.append(EpisodeFrames(states, states, "t", velocities=vel))
    read = check_dataset(ds.root)
    assert read.info["features"]["observation.velocity"]["names"] == [
        "left.base.vel", "left.elbow.vel", "right.z.vel"]
    assert np.allclose(read.frames["observation.velocity"], vel)
    ep = Dataset.open(ds.root).load_episode(0)
    assert ep.velocities is not None and np.allclose(ep.velocities, vel)
    with pytest.raises(ValueError, match="velocities"):
        ds.append(EpisodeFrames(states, states, "t", velocities=vel[:, :2]))
