"""A LeRobot v3.0 dataset on disk: `Dataset.create` / `Dataset.open`, `append` (write one
finished episode) and the read side (`episodes`, `load_episode`), with pyarrow only.

Columns and rules are lerobot's (huggingface/lerobot `src/lerobot/datasets/dataset_writer.py`
`save_episode` / `_save_episode_data`, `dataset_metadata.py` `save_episode` /
`_save_episode_metadata` / `save_episode_tasks`, `feature_utils.py`
`get_hf_features_from_features`, `io_utils.py` `write_tasks`):

- `data/chunk-CCC/file-FFF.parquet`: one row per frame, the features (a vector is a
  fixed-size list, lerobot's `datasets.Sequence(length=n)`), then `timestamp` (float32,
  `frame_index / fps`), `frame_index`, `episode_index`, `index` (over the dataset),
  `task_index` (int64); a file grows by whole episodes up to `data_files_size_in_mb`.
- `meta/episodes/chunk-000/file-000.parquet`: one row per episode: `episode_index`, `tasks`,
  `length`, `data/chunk_index`, `data/file_index`, `dataset_from_index`, `dataset_to_index`,
  `videos/<key>/chunk_index`, `.../file_index`, `.../from_timestamp`, `.../to_timestamp`,
  `meta/episodes/chunk_index`, `meta/episodes/file_index` and `stats/<feature>/<stat>`.
- `meta/tasks.parquet`: the tasks as pandas writes a frame indexed by `task` with a
  `task_index` column (lerobot reads it with `pandas.read_parquet`).

`append` writes the videos, the frames, the tasks and the episode's row in that order, then
`meta/stats.json` and last `meta/info.json`, each atomically (app/recording/layout.py). The
episodes table is the record of what is complete: `open` makes the rest agree with it (a data
file's rows past its last episode are cut, a video file longer than its episodes is left for
a new file, the totals and stats are made again), so a server killed while writing leaves a
dataset that loads with every episode written before.
"""

from __future__ import annotations

import io
import json
import logging
import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa  # type: ignore[import-untyped]
import pyarrow.parquet as pq  # type: ignore[import-untyped]

from app.recording import layout as L
from app.recording import stats as S
from app.recording.video import append_episode

log = logging.getLogger(__name__)

INT_COLUMNS = ("frame_index", "episode_index", "index", "task_index")


@dataclass(frozen=True)
class ArmLayout:
    """One arm's part of the state and action vectors: its joints, then its gripper."""
    arm: str
    joints: tuple[str, ...]
    gripper: bool

    @property
    def names(self) -> list[str]:
        out = [f"{self.arm}.{j}.pos" for j in self.joints]
        return out + ([f"{self.arm}.gripper.pos"] if self.gripper else [])

    @property
    def velocity_names(self) -> list[str]:
        return [f"{self.arm}.{j}.vel" for j in self.joints]


@dataclass
class EpisodeFrames:
    """A finished episode to write: `states` and `actions` (frames, d), one task, per camera
    its encoded MP4 (as many frames) and a few frames (RGB) for its stats, and the joints'
    velocities (frames, joints) where the dataset has them."""
    states: np.ndarray
    actions: np.ndarray
    task: str
    videos: dict[str, Path] = field(default_factory=dict)
    samples: dict[str, np.ndarray] = field(default_factory=dict)
    velocities: np.ndarray | None = None


@dataclass(frozen=True)
class EpisodeInfo:
    index: int
    length: int
    tasks: list[str]
    from_index: int
    to_index: int


@dataclass(frozen=True)
class Episode:
    """One episode as recorded: per frame its time (s from the episode's start, on the grid),
    state and action (SI: rad, m; grippers 0 open .. 1 closed), in the dataset's layout."""
    index: int
    fps: int
    task: str
    timestamps: np.ndarray
    states: np.ndarray
    actions: np.ndarray
    names: list[str]
    #: (frames, joints) rad/s or m/s, None where the dataset has no `observation.velocity`.
    velocities: np.ndarray | None = None

    def arm_columns(self, arm: str) -> list[int]:
        """The columns of `states` / `actions` that are `arm`'s (its joints, then gripper)."""
        return [i for i, n in enumerate(self.names) if n.split(".", 1)[0] == arm]


def _features(arms: list[ArmLayout], cameras: dict[str, tuple[int, int]],
              velocity: bool) -> dict[str, Any]:
    names = [n for a in arms for n in a.names]
    vec = {"dtype": "float32", "shape": [len(names)], "names": names}
    feats: dict[str, Any] = {L.STATE: dict(vec), L.ACTION: dict(vec)}
    if velocity:
        vnames = [n for a in arms for n in a.velocity_names]
        feats[L.VELOCITY] = {"dtype": "float32", "shape": [len(vnames)], "names": vnames}
    for cam, (w, h) in cameras.items():
        feats[L.video_key(cam)] = {"dtype": "video", "shape": [h, w, 3],
                                   "names": ["height", "width", "channels"], "info": None}
    return feats


class Dataset:
    """One dataset folder. Not thread-safe: one writer at a time (the recording manager's)."""

    def __init__(self, root: Path, info: dict[str, Any]) -> None:
        self.root = root
        self.info = info
        self.rows: list[dict[str, Any]] = self._read_episodes()
        self.tasks: list[str] = self._read_tasks()
        #: Per video key: start its next episode in a new file (the last one is longer than
        #: its episodes: a write was cut short).
        self._roll: set[str] = set()

    # ------------------------------------------------------------ create, open

    @classmethod
    def create(cls, root: Path, fps: int, arms: list[ArmLayout],
               cameras: dict[str, tuple[int, int]], robot_type: str | None,
               velocity: bool = False) -> Dataset:
        """A new dataset; `velocity`: with `observation.velocity` (the joints' rad/s, m/s)."""
        root.mkdir(parents=True, exist_ok=False)
        info = L.new_info(fps, _features(arms, cameras, velocity), robot_type, bool(cameras))
        L.write_json(root / L.INFO_PATH, info)
        return cls(root, info)

    @classmethod
    def open(cls, root: Path) -> Dataset:
        info = L.read_json(root / L.INFO_PATH)
        if info.get("codebase_version") != L.CODEBASE_VERSION:
            raise ValueError(f"{root}: not a LeRobot {L.CODEBASE_VERSION} dataset")
        ds = cls(root, info)
        shutil.rmtree(root / L.PARTIAL_DIR, ignore_errors=True)
        ds._repair()
        return ds

    @property
    def fps(self) -> int:
        return int(self.info["fps"])

    @property
    def features(self) -> dict[str, Any]:
        return dict(self.info["features"])

    @property
    def video_keys(self) -> list[str]:
        return [k for k, f in self.info["features"].items() if f["dtype"] == "video"]

    @property
    def names(self) -> list[str]:
        return list(self.info["features"][L.STATE]["names"])

    @property
    def has_velocity(self) -> bool:
        return L.VELOCITY in self.info["features"]

    @property
    def total_frames(self) -> int:
        return int(self.rows[-1]["dataset_to_index"]) if self.rows else 0

    def _read_episodes(self) -> list[dict[str, Any]]:
        folder = self.root / "meta" / "episodes"
        rows: list[dict[str, Any]] = []
        for path in sorted(folder.glob("chunk-*/file-*.parquet")):
            rows.extend(pq.read_table(path).to_pylist())
        return sorted(rows, key=lambda r: int(r["episode_index"]))

    def _read_tasks(self) -> list[str]:
        path = self.root / L.TASKS_PATH
        if not path.exists():
            return []
        t = pq.read_table(path).to_pydict()
        return [task for _, task in sorted(zip(t["task_index"], t["task"], strict=True))]

    def _repair(self) -> None:
        """Make the files agree with the episodes table (see the module doc)."""
        self.tasks = self._read_tasks()
        if self.rows:
            last = self.rows[-1]
            path = self._data_file(last["data/chunk_index"], last["data/file_index"])
            t = pq.read_table(path)
            first = int(pq.read_table(path, columns=["index"]).column("index")[0].as_py())
            keep = int(last["dataset_to_index"]) - first
            if t.num_rows > keep:
                log.warning("%s: %d frames past the last episode cut", path, t.num_rows - keep)
                self._write_table(path, t.slice(0, keep))
        for key in self.video_keys:
            last_row = next((r for r in reversed(self.rows) if r.get(f"videos/{key}/chunk_index")
                             is not None), None)
            if last_row is None:
                continue
            vpath = self._video_file(key, last_row)
            if vpath.exists() and _duration(vpath) > last_row[f"videos/{key}/to_timestamp"] + 1e-6:
                self._roll.add(key)
        n = len(self.rows)
        if self.info["total_episodes"] != n or self.info["total_frames"] != self.total_frames \
                or self.info["total_tasks"] != len(self.tasks):
            log.warning("%s: the metadata said %s episodes, the episodes table %s: rewritten",
                        self.root, self.info["total_episodes"], n)
            self._write_stats()
            self._write_info()

    # ------------------------------------------------------------ paths

    def _data_file(self, chunk: int, file: int) -> Path:
        return self.root / str(self.info["data_path"]).format(chunk_index=chunk, file_index=file)

    def _video_file(self, key: str, row: dict[str, Any]) -> Path:
        return self.root / str(self.info["video_path"]).format(
            video_key=key, chunk_index=row[f"videos/{key}/chunk_index"],
            file_index=row[f"videos/{key}/file_index"])

    def partial_dir(self) -> Path:
        return self.root / L.PARTIAL_DIR

    # ------------------------------------------------------------ write

    def append(self, ep: EpisodeFrames) -> EpisodeInfo:
        """Write one finished episode (blocking: run it in a worker thread). An OSError
        (ENOSPC) leaves the dataset as it was: every file is replaced whole or not at all, and
        what was written of this episode before the failure is set right as `open` would."""
        try:
            return self._append(ep)
        except OSError:
            try:
                self._repair()
            except OSError as exc:  # still failing: `open` repairs it next time
                log.warning("%s: cannot repair after a failed write now: %s", self.root, exc)
            raise

    def _append(self, ep: EpisodeFrames) -> EpisodeInfo:
        n = len(ep.states)
        if n == 0:
            raise ValueError("an episode needs at least one frame")
        if ep.states.shape != ep.actions.shape or ep.states.shape[1] != len(self.names):
            raise ValueError(f"states {ep.states.shape} / actions {ep.actions.shape} do not "
                             f"match the dataset's {len(self.names)} names")
        if self.has_velocity and ep.velocities is not None:
            nv = self.info["features"][L.VELOCITY]["shape"][0]
            if ep.velocities.shape != (n, nv):
                raise ValueError(f"velocities {ep.velocities.shape}: the dataset has {nv} "
                                 "per frame")
        index = len(self.rows)
        prev = self.rows[-1] if self.rows else None
        row: dict[str, Any] = {"episode_index": index, "tasks": [ep.task], "length": n}
        stats: dict[str, S.Stats] = {}
        for key in self.video_keys:
            cam = key[len(L.IMAGE_PREFIX):]
            row.update(self._append_video(key, ep.videos[cam], n, prev))
            stats[key] = S.image_stats(ep.samples[cam])
        new_task = ep.task not in self.tasks
        tasks = self.tasks + [ep.task] if new_task else self.tasks
        task_index = tasks.index(ep.task)
        table, data_at = self._append_data(ep, index, task_index, prev)
        row.update(data_at)
        stats[L.STATE] = S.feature_stats(np.asarray(ep.states, np.float32))
        stats[L.ACTION] = S.feature_stats(np.asarray(ep.actions, np.float32))
        if self.has_velocity:
            stats[L.VELOCITY] = S.feature_stats(np.asarray(table.column(L.VELOCITY)
                                                           .combine_chunks().flatten())
                                                .reshape(n, -1))
        for name in ("timestamp", *INT_COLUMNS):
            stats[name] = S.feature_stats(np.asarray(table.column(name)))
        if new_task:
            self._write_tasks(tasks)
        row["meta/episodes/chunk_index"] = 0
        row["meta/episodes/file_index"] = 0
        for feat, st in stats.items():
            for k, v in st.items():
                row[f"stats/{feat}/{k}"] = v.tolist()
        rows = self.rows + [row]
        buf = io.BytesIO()
        pq.write_table(pa.Table.from_pylist(rows), buf)
        L.write_atomic(self.root / L.EPISODES_PATH.format(chunk_index=0, file_index=0),
                       buf.getvalue())
        self.rows, self.tasks = rows, tasks
        self._write_stats()
        if index == 0 or any(self.info["features"][k].get("info") is None
                             for k in self.video_keys):
            self._video_info()
        self._write_info()
        return self._episode_info(row)

    def _append_video(self, key: str, episode: Path, n: int,
                      prev: dict[str, Any] | None) -> dict[str, Any]:
        chunk, file, offset = 0, 0, 0.0
        if prev is not None and prev.get(f"videos/{key}/chunk_index") is not None:
            chunk = int(prev[f"videos/{key}/chunk_index"])
            file = int(prev[f"videos/{key}/file_index"])
            offset = float(prev[f"videos/{key}/to_timestamp"])
            path = self._video_file(key, prev)
            limit = self.info["video_files_size_in_mb"] * 1024 * 1024
            if key in self._roll or (path.exists() and path.stat().st_size
                                     + episode.stat().st_size >= limit):
                chunk, file = L.next_file(chunk, file, self.info["chunks_size"])
                offset = 0.0
        dest = self.root / self.info["video_path"].format(video_key=key, chunk_index=chunk,
                                                          file_index=file)
        append_episode(dest, episode, offset)
        self._roll.discard(key)
        return {f"videos/{key}/chunk_index": chunk, f"videos/{key}/file_index": file,
                f"videos/{key}/from_timestamp": offset,
                f"videos/{key}/to_timestamp": offset + n / self.fps}

    def _append_data(self, ep: EpisodeFrames, index: int, task_index: int,
                     prev: dict[str, Any] | None) -> tuple[pa.Table, dict[str, Any]]:
        n, fps = len(ep.states), self.fps
        start = self.total_frames
        frame_index = np.arange(n, dtype=np.int64)
        d = ep.states.shape[1]
        cols = {
            L.STATE: _vectors(ep.states, d),
            L.ACTION: _vectors(ep.actions, d),
            "timestamp": pa.array((frame_index / fps).astype(np.float32)),
            "frame_index": pa.array(frame_index),
            "episode_index": pa.array(np.full(n, index, np.int64)),
            "index": pa.array(np.arange(start, start + n, dtype=np.int64)),
            "task_index": pa.array(np.full(n, task_index, np.int64)),
        }
        if self.has_velocity:
            nv = self.info["features"][L.VELOCITY]["shape"][0]
            vel = ep.velocities if ep.velocities is not None else np.zeros((n, nv))
            cols = {L.STATE: cols[L.STATE], L.ACTION: cols[L.ACTION],
                    L.VELOCITY: _vectors(vel, nv),
                    **{k: v for k, v in cols.items() if k not in (L.STATE, L.ACTION)}}
        table = pa.table(cols)
        chunk, file = 0, 0
        old: pa.Table | None = None
        if prev is not None:
            chunk, file = int(prev["data/chunk_index"]), int(prev["data/file_index"])
            path = self._data_file(chunk, file)
            limit = self.info["data_files_size_in_mb"] * 1024 * 1024
            if path.stat().st_size >= limit:
                chunk, file = L.next_file(chunk, file, self.info["chunks_size"])
            else:
                old = pq.read_table(path)
        path = self._data_file(chunk, file)
        self._write_table(path, table if old is None else pa.concat_tables([old, table]))
        return table, {"data/chunk_index": chunk, "data/file_index": file,
                       "dataset_from_index": start, "dataset_to_index": start + n}

    @staticmethod
    def _write_table(path: Path, table: pa.Table) -> None:
        buf = io.BytesIO()
        pq.write_table(table, buf, compression="snappy")
        L.write_atomic(path, buf.getvalue())

    def _write_tasks(self, tasks: list[str]) -> None:
        table = pa.table({"task_index": pa.array(range(len(tasks)), pa.int64()),
                          "task": pa.array(tasks, pa.string())})
        table = table.replace_schema_metadata({b"pandas": json.dumps(_PANDAS_TASKS).encode()})
        self._write_table(self.root / L.TASKS_PATH, table)

    def _write_stats(self) -> None:
        per: dict[str, list[S.Stats]] = {}
        for i, row in enumerate(self.rows):
            for col, v in row.items():
                if col.startswith("stats/"):
                    feat, k = col[6:col.rindex("/")], col[col.rindex("/") + 1:]
                    per.setdefault(feat, [{} for _ in self.rows])[i][k] = np.asarray(v)
        agg = {feat: S.aggregate(lst) for feat, lst in per.items() if all(lst)}
        L.write_json(self.root / L.STATS_PATH, S.to_json(agg))

    def _video_info(self) -> None:
        import av
        for key in self.video_keys:
            row = next((r for r in self.rows if r.get(f"videos/{key}/chunk_index") is not None),
                       None)
            if row is None:
                continue
            with av.open(str(self._video_file(key, row))) as f:
                vs = f.streams.video[0]
                self.info["features"][key]["info"] = {
                    "video.height": vs.height, "video.width": vs.width,
                    "video.codec": vs.codec_context.codec.canonical_name,
                    "video.pix_fmt": vs.pix_fmt, "video.is_depth_map": False,
                    "video.fps": self.fps, "video.channels": 3, "has_audio": False}

    def _write_info(self) -> None:
        self.info["total_episodes"] = len(self.rows)
        self.info["total_frames"] = self.total_frames
        self.info["total_tasks"] = len(self.tasks)
        self.info["splits"] = {"train": f"0:{len(self.rows)}"} if self.rows else {}
        L.write_json(self.root / L.INFO_PATH, self.info)

    # ------------------------------------------------------------ read

    @staticmethod
    def _episode_info(row: dict[str, Any]) -> EpisodeInfo:
        return EpisodeInfo(index=int(row["episode_index"]), length=int(row["length"]),
                           tasks=list(row["tasks"]), from_index=int(row["dataset_from_index"]),
                           to_index=int(row["dataset_to_index"]))

    def episodes(self) -> list[EpisodeInfo]:
        return [self._episode_info(r) for r in self.rows]

    def load_episode(self, index: int) -> Episode:
        """One episode's frames (IndexError: no such episode)."""
        if not 0 <= index < len(self.rows):
            raise IndexError(f"no episode {index}: the dataset has {len(self.rows)}")
        row = self.rows[index]
        path = self._data_file(row["data/chunk_index"], row["data/file_index"])
        t = pq.read_table(path, filters=[("episode_index", "=", index)])
        d = len(self.names)
        states = np.asarray(t.column(L.STATE).combine_chunks().flatten()).reshape(-1, d)
        actions = np.asarray(t.column(L.ACTION).combine_chunks().flatten()).reshape(-1, d)
        vel = None
        if self.has_velocity:
            vel = np.asarray(t.column(L.VELOCITY).combine_chunks().flatten(),
                             dtype=np.float64).reshape(len(states), -1)
        return Episode(index=index, fps=self.fps, task=list(row["tasks"])[0],
                       timestamps=np.asarray(t.column("timestamp"), dtype=np.float64),
                       states=states.astype(np.float64), actions=actions.astype(np.float64),
                       names=self.names, velocities=vel)


def _vectors(values: np.ndarray, d: int) -> pa.Array:
    """(frames, d) as lerobot's `datasets.Sequence(Value("float32"), length=d)` stores it: a
    fixed-size list whose field is `item`."""
    flat = pa.array(np.asarray(values, np.float32).ravel())
    return pa.FixedSizeListArray.from_arrays(flat, type=pa.list_(pa.float32(), d))


def _duration(path: Path) -> float:
    """Seconds of video in an MP4: the last frame's time plus one period."""
    import av
    with av.open(str(path)) as f:
        vs = f.streams.video[0]
        tb, rate = vs.time_base, vs.average_rate or vs.base_rate
        assert tb is not None and rate is not None
        last = max((p.pts for p in f.demux(vs) if p.pts is not None), default=None)
        return 0.0 if last is None else float(last * tb) + 1.0 / float(rate)


#: The `pandas` schema metadata `DataFrame.to_parquet` writes for lerobot's tasks frame (index
#: `task`, column `task_index`), so that `pandas.read_parquet` gives it back indexed by task.
_PANDAS_TASKS: dict[str, Any] = {
    "index_columns": ["task"],
    "column_indexes": [{"name": None, "field_name": None, "pandas_type": "unicode",
                        "numpy_type": "object", "metadata": {"encoding": "UTF-8"}}],
    "columns": [
        {"name": "task_index", "field_name": "task_index", "pandas_type": "int64",
         "numpy_type": "int64", "metadata": None},
        {"name": "task", "field_name": "task", "pandas_type": "unicode",
         "numpy_type": "object", "metadata": None},
    ],
    "creator": {"library": "pyarrow", "version": pa.__version__},
    "pandas_version": "2.2.3",
}
