"""A small reader of LeRobot v3.0 datasets for the tests, written from the format (huggingface/
lerobot `src/lerobot/datasets/utils.py`, `dataset_metadata.py`, `video_utils.py`) with pyarrow
and PyAV, independent of app/recording: `check_dataset(root)` reads every file and asserts the
format's rules, and answers what it read."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import av
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

DEFAULT_COLUMNS = {"timestamp": "float", "frame_index": "int64", "episode_index": "int64",
                   "index": "int64", "task_index": "int64"}
STAT_KEYS = {"min", "max", "mean", "std", "count", "q01", "q10", "q50", "q90", "q99"}


@dataclass
class Read:
    info: dict[str, Any]
    episodes: list[dict[str, Any]]
    frames: dict[str, np.ndarray]  # every data column over the whole dataset, in index order
    tasks: dict[int, str]
    stats: dict[str, Any]

    def episode(self, i: int) -> dict[str, np.ndarray]:
        sel = self.frames["episode_index"] == i
        return {k: v[sel] for k, v in self.frames.items()}


def _tasks(root: Path) -> dict[int, str]:
    t = pq.read_table(root / "meta/tasks.parquet")
    meta = json.loads(t.schema.metadata[b"pandas"])
    assert meta["index_columns"] == ["task"], meta  # pandas reads it back indexed by task
    d = t.to_pydict()
    return dict(zip(d["task_index"], d["task"], strict=True))


def check_dataset(root: Path, decode_video: bool = True) -> Read:
    info = json.loads((root / "meta/info.json").read_text())
    assert info["codebase_version"] == "v3.0"
    for k in ("fps", "features", "total_episodes", "total_frames", "total_tasks", "chunks_size",
              "data_files_size_in_mb", "video_files_size_in_mb", "data_path", "video_path",
              "robot_type", "splits"):
        assert k in info, k
    fps = info["fps"]
    feats = info["features"]
    for k, dtype in DEFAULT_COLUMNS.items():
        assert feats[k]["shape"] == [1] and dtype.startswith(feats[k]["dtype"][:5]), feats[k]
    video_keys = [k for k, f in feats.items() if f["dtype"] == "video"]
    ep_files = sorted((root / "meta/episodes").glob("chunk-*/file-*.parquet"))
    episodes = [r for p in ep_files for r in pq.read_table(p).to_pylist()]
    assert [e["episode_index"] for e in episodes] == list(range(len(episodes)))
    assert info["total_episodes"] == len(episodes)
    assert info["splits"] == ({"train": f"0:{len(episodes)}"} if episodes else {})
    tasks = _tasks(root) if episodes else {}
    assert info["total_tasks"] == len(tasks)
    data_files = sorted((root / "data").glob("chunk-*/file-*.parquet"))
    tables = [pq.read_table(p) for p in data_files]
    cols: dict[str, list[np.ndarray]] = {}
    for t in tables:
        for name in t.column_names:
            col = t.column(name).combine_chunks()
            if feats[name]["dtype"] == "float32" and feats[name]["shape"] != [1]:
                n = feats[name]["shape"][0]
                assert pa.types.is_fixed_size_list(col.type) and col.type.list_size == n \
                    and col.type.value_type == pa.float32(), col.type
                arr = np.asarray(col.flatten()).reshape(-1, n)
            else:
                arr = np.asarray(col)
            cols.setdefault(name, []).append(arr)
    frames = {k: np.concatenate(v) for k, v in cols.items()}
    non_video = [k for k, f in feats.items() if f["dtype"] != "video"]
    assert sorted(frames) == sorted(non_video) or not episodes, (sorted(frames), non_video)
    total = info["total_frames"]
    if episodes:
        assert frames["timestamp"].dtype == np.float32
        assert np.array_equal(frames["index"], np.arange(total))  # continuity
    for e in episodes:
        i = e["episode_index"]
        assert e["length"] == e["dataset_to_index"] - e["dataset_from_index"]
        sel = slice(e["dataset_from_index"], e["dataset_to_index"])
        assert np.all(frames["episode_index"][sel] == i)
        fi = frames["frame_index"][sel]
        assert np.array_equal(fi, np.arange(e["length"]))
        assert np.array_equal(frames["timestamp"][sel], (fi / fps).astype(np.float32))
        assert all(tasks[t] in e["tasks"] for t in set(frames["task_index"][sel].tolist()))
        path = root / info["data_path"].format(chunk_index=e["data/chunk_index"],
                                               file_index=e["data/file_index"])
        assert path.exists()
        for k in non_video + video_keys:
            assert {c.rsplit("/", 1)[1] for c in e if c.startswith(f"stats/{k}/")} == STAT_KEYS
        for vk in video_keys:
            vpath = root / info["video_path"].format(
                video_key=vk, chunk_index=e[f"videos/{vk}/chunk_index"],
                file_index=e[f"videos/{vk}/file_index"])
            t0 = e[f"videos/{vk}/from_timestamp"]
            assert abs(e[f"videos/{vk}/to_timestamp"] - t0 - e["length"] / fps) < 1e-6
            if decode_video:
                got = decode(vpath, [t0 + k / fps for k in range(e["length"])], fps)
                h, w, _ = feats[vk]["shape"]
                assert got[0].shape == (h, w, 3)
    stats = json.loads((root / "meta/stats.json").read_text()) if episodes else {}
    for k in non_video + video_keys if episodes else []:
        assert set(stats[k]) == STAT_KEYS, (k, stats[k].keys())
    return Read(info, episodes, frames, tasks, stats)


def decode(path: Path, timestamps: list[float], fps: int) -> list[np.ndarray]:
    """The RGB frames of an MP4 at `timestamps`: each the decoded frame within 1e-4 s (lerobot
    asks within its `tolerance_s`, 1e-4 s by default)."""
    out: dict[int, np.ndarray] = {}
    with av.open(str(path)) as f:
        vs = f.streams.video[0]
        assert vs.pix_fmt == "yuv420p" and vs.codec_context.name in ("h264", "libx264", "av1")
        got = {}
        for frame in f.decode(vs):
            got[round(float(frame.pts * vs.time_base) * fps * 1000)] = frame
        for i, t in enumerate(timestamps):
            key = round(t * fps * 1000)
            frame = got.get(key)
            assert frame is not None and abs(float(frame.pts * vs.time_base) - t) < 1e-4, \
                (path, t)
            out[i] = frame.to_ndarray(format="rgb24")
    return [out[i] for i in range(len(timestamps))]
