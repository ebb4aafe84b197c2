"""`make check-lerobot`: a dataset recorded by armserver, loaded by lerobot's own
`LeRobotDataset` (huggingface/lerobot) and compared frame by frame with what was written.

Two steps, in two virtual environments (lerobot brings torch, several GB: not part of
`make test`):

    python tools/check_lerobot.py record OUT      # armserver's venv: records into OUT
    .venv-lerobot/bin/python tools/check_lerobot.py load OUT/recordings/check

`record` starts `armserver serve` (the simulated arms and their simulated cameras, data folder
OUT) on a free loopback port, creates the dataset `check` (every arm, the first camera, 15 fps),
records three episodes while the first arm moves, starts a fourth and kills the server with
SIGKILL in its middle, then starts it again and records one more (the killed one absent, the
others kept, the restart appending). `load` opens the folder with
`LeRobotDataset(repo_id, root=..., video_backend="pyav")`, iterates every frame and compares its
state, action, velocity, timestamp, indices and image with the parquet files and MP4s read by
pyarrow and PyAV; it exits non-zero on the first difference.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

FPS = 15
NAME = "check"


# ------------------------------------------------------------------ record (armserver's venv)

def _port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _serve(data: Path) -> tuple[subprocess.Popen[bytes], str]:
    port = _port()
    env = {k: v for k, v in os.environ.items() if not k.startswith("ARMSERVER_")}
    env["ARMSERVER_DATA_DIR"] = str(data)
    proc = subprocess.Popen([sys.executable, "-c", "from app.cli import run; run()", "serve",
                             "--port", str(port), "--log-level", "warning"], env=env)
    url = f"http://127.0.0.1:{port}"
    import httpx
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise SystemExit("armserver serve exited")
        try:
            arms = httpx.get(f"{url}/api/v1/arms", timeout=2).json()
            if arms and all(not httpx.get(f"{url}/api/v1/arms/{a['name']}/state",
                                          timeout=2).json()["stale"] for a in arms):
                return proc, url
        except httpx.TransportError:
            pass
        time.sleep(0.2)
    proc.kill()
    raise SystemExit("armserver serve did not start")


def _episode(client: Any, arm: str, joints: list[dict[str, Any]], k: int, seconds: float,
             stop: bool = True) -> None:
    client.start_episode(NAME, task=f"reach {k % 2}")
    lo = [j["min"] for j in joints]
    hi = [j["max"] for j in joints]
    frac = 0.4 + 0.2 * (k % 2)
    target = [a + frac * (b - a) for a, b in zip(lo, hi, strict=True)]
    client.move_joints(arm, target, speed=0.5, wait=True)
    time.sleep(seconds)
    if stop:
        client.stop_episode(NAME)


def record(out: Path) -> None:
    from app.client import ArmClient
    out.mkdir(parents=True, exist_ok=True)
    proc, url = _serve(out)
    try:
        with ArmClient(url) as c:
            arms = [a.name for a in c.arms()]
            cams = [x.name for x in c.cameras()][:1]
            c.create_recording(NAME, arms, cams, fps=FPS, task="reach")
            joints = [j.model_dump() for j in c.arm(arms[0]).joints]
            for k in range(3):
                _episode(c, arms[0], joints, k, 0.5)
            _episode(c, arms[0], joints, 3, 0.5, stop=False)
            print(f"recorded 3 episodes; killing the server in the 4th "
                  f"({c.recording(NAME).current})")
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(10)
        proc, url = _serve(out)
        with ArmClient(url) as c:
            d = c.recording(NAME)
            assert d.episodes == 3, d
            _episode(c, arms[0], joints, 4, 0.5)
            d = c.recording(NAME)
            print(f"after the restart: {d.episodes} episodes, {d.frames} frames in {d.path}")
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(20)
            except subprocess.TimeoutExpired:
                proc.kill()


# ------------------------------------------------------------------ load (lerobot's venv)

def load(root: Path) -> None:
    import av
    import numpy as np
    import pyarrow.parquet as pq
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    info = json.loads((root / "meta/info.json").read_text())
    ds = LeRobotDataset(f"armserver/{root.name}", root=root, video_backend="pyav")
    table = pq.read_table(sorted((root / "data").glob("chunk-*/file-*.parquet")))
    cols = table.to_pydict()
    n = info["total_frames"]
    assert len(ds) == n == len(cols["index"]), (len(ds), n, len(cols["index"]))
    assert ds.num_episodes == info["total_episodes"]
    eps = pq.read_table(root / "meta/episodes/chunk-000/file-000.parquet").to_pylist()
    video_keys = [k for k, f in info["features"].items() if f["dtype"] == "video"]
    decoded: dict[str, dict[int, np.ndarray]] = {}
    for key in video_keys:
        frames: dict[int, np.ndarray] = {}
        for e in eps:
            path = root / info["video_path"].format(
                video_key=key, chunk_index=e[f"videos/{key}/chunk_index"],
                file_index=e[f"videos/{key}/file_index"])
            t0 = e[f"videos/{key}/from_timestamp"]
            with av.open(str(path)) as f:
                vs = f.streams.video[0]
                by_t = {round(float(fr.pts * vs.time_base) * info["fps"]):
                        fr.to_ndarray(format="rgb24") for fr in f.decode(vs)}
            for k in range(e["length"]):
                frames[e["dataset_from_index"] + k] = by_t[round((t0 + k / info["fps"])
                                                                 * info["fps"])]
        decoded[key] = frames
    worst = 0.0
    for i in range(n):
        item = ds[i]
        vectors = [k for k, f in info["features"].items()
                   if f["dtype"] == "float32" and f["shape"] != [1]]
        for name in vectors:  # observation.state, action, observation.velocity
            got = item[name].numpy()
            want = np.asarray(cols[name][i], dtype=np.float32)
            assert np.array_equal(got, want), (i, name, got, want)
        assert abs(float(item["timestamp"]) - cols["timestamp"][i]) < 1e-6, i
        for name in ("frame_index", "episode_index", "index", "task_index"):
            assert int(item[name]) == cols[name][i], (i, name)
        assert item["task"] in ds.meta.tasks.index, item["task"]
        for key in video_keys:
            img = (item[key].numpy().transpose(1, 2, 0) * 255.0)
            diff = float(np.abs(img - decoded[key][i]).max())
            worst = max(worst, diff)
            assert diff <= 1.0, (i, key, diff)
    print(f"LeRobotDataset loaded {root}: {ds.num_episodes} episodes, {n} frames, "
          f"fps {ds.fps}, features {list(ds.features)}; every frame's state, action, "
          f"velocity, indices and image ({len(video_keys)} camera(s), largest difference "
          f"{worst:.3f} of 255) as written: OK")


if __name__ == "__main__":
    if len(sys.argv) != 3 or sys.argv[1] not in ("record", "load"):
        raise SystemExit(__doc__)
    (record if sys.argv[1] == "record" else load)(Path(sys.argv[2]).resolve())
