"""The LeRobot v3.0 dataset layout: paths, `meta/info.json`'s fields and atomic file writes.

Every name here is the format's own, from huggingface/lerobot `src/lerobot/datasets/utils.py`
(`DEFAULT_DATA_PATH`, `DEFAULT_VIDEO_PATH`, `DEFAULT_EPISODES_PATH`, `DEFAULT_TASKS_PATH`,
`INFO_PATH`, `STATS_PATH`, `CHUNK_FILE_PATTERN`, the `DatasetInfo` fields and their defaults)
and `src/lerobot/utils/constants.py` (`DEFAULT_FEATURES`). A dataset is a folder:

    meta/info.json  meta/stats.json  meta/tasks.parquet
    meta/episodes/chunk-000/file-000.parquet
    data/chunk-000/file-000.parquet
    videos/<key>/chunk-000/file-000.mp4

Nothing is written in place: a new version of a file goes to a temporary file in the same
folder, is flushed to disk (fsync) and renamed over the old one, so a server killed at any
moment leaves each file either as it was or as it is meant to be.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

CODEBASE_VERSION = "v3.0"
DEFAULT_CHUNK_SIZE = 1000
DEFAULT_DATA_FILE_SIZE_IN_MB = 100
DEFAULT_VIDEO_FILE_SIZE_IN_MB = 200

INFO_PATH = "meta/info.json"
STATS_PATH = "meta/stats.json"
TASKS_PATH = "meta/tasks.parquet"
CHUNK_FILE_PATTERN = "chunk-{chunk_index:03d}/file-{file_index:03d}"
EPISODES_PATH = "meta/episodes/" + CHUNK_FILE_PATTERN + ".parquet"
DATA_PATH = "data/" + CHUNK_FILE_PATTERN + ".parquet"
VIDEO_PATH = "videos/{video_key}/" + CHUNK_FILE_PATTERN + ".mp4"

#: The columns every frame carries besides the dataset's own features (`DEFAULT_FEATURES`).
DEFAULT_FEATURES: dict[str, dict[str, Any]] = {
    "timestamp": {"dtype": "float32", "shape": [1], "names": None},
    "frame_index": {"dtype": "int64", "shape": [1], "names": None},
    "episode_index": {"dtype": "int64", "shape": [1], "names": None},
    "index": {"dtype": "int64", "shape": [1], "names": None},
    "task_index": {"dtype": "int64", "shape": [1], "names": None},
}

STATE = "observation.state"
ACTION = "action"
#: The joints' velocities (rad/s, m/s), resampled like the state (lerobot's name for it in
#: e.g. the ALOHA datasets).
VELOCITY = "observation.velocity"
IMAGE_PREFIX = "observation.images."
#: Where an episode's video is encoded before it joins the dataset's file (not part of the
#: format: the loader never looks there; cleared when a dataset is opened).
PARTIAL_DIR = ".partial"


def video_key(camera: str) -> str:
    return IMAGE_PREFIX + camera


def next_file(chunk_index: int, file_index: int, chunks_size: int) -> tuple[int, int]:
    """The next (chunk, file) (lerobot's `update_chunk_file_indices`)."""
    if file_index == chunks_size - 1:
        return chunk_index + 1, 0
    return chunk_index, file_index + 1


def new_info(fps: int, features: dict[str, dict[str, Any]], robot_type: str | None,
             has_video: bool) -> dict[str, Any]:
    """`meta/info.json` of an empty dataset (lerobot's `DatasetInfo` with its defaults)."""
    return {
        "codebase_version": CODEBASE_VERSION,
        "robot_type": robot_type,
        "total_episodes": 0,
        "total_frames": 0,
        "total_tasks": 0,
        "chunks_size": DEFAULT_CHUNK_SIZE,
        "data_files_size_in_mb": DEFAULT_DATA_FILE_SIZE_IN_MB,
        "video_files_size_in_mb": DEFAULT_VIDEO_FILE_SIZE_IN_MB,
        "fps": fps,
        "splits": {},
        "data_path": DATA_PATH,
        "video_path": VIDEO_PATH if has_video else None,
        "features": {**features, **DEFAULT_FEATURES},
    }


def write_atomic(path: Path, data: bytes) -> None:
    """`data` as `path`: temporary file, fsync, rename, fsync of the folder."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    try:
        with open(tmp, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        replace_synced(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)  # a disk full leaves no half file behind
        raise


def replace_synced(tmp: Path, path: Path) -> None:
    """Rename a written temporary file over `path` once its bytes are on disk."""
    fd = os.open(tmp, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)
    os.replace(tmp, path)
    dfd = os.open(path.parent, os.O_RDONLY)
    try:
        os.fsync(dfd)
    finally:
        os.close(dfd)


def write_json(path: Path, obj: Any) -> None:
    write_atomic(path, (json.dumps(obj, indent=4) + "\n").encode())


def read_json(path: Path) -> Any:
    return json.loads(path.read_text())
