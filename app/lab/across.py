"""The lab-wide routes that are not one arm's, placed by the arms they name: teleoperation and
recordings through the front (app/lab/front.py) when the arms live on several workers.

- `POST /teleop` goes to the follower's worker: the session runs on the follower's control loop
  as ever, and a leader on another worker is read there over its worker's telemetry socket
  (app/teleop/remote.py). `GET /teleop` merges every worker's sessions (running first);
  `DELETE /teleop/{id}` goes to the worker that has the session (each is asked in turn until
  one knows the id).
- `POST /recordings` goes to the worker of its arms and cameras; arms or cameras on different
  workers are refused, 409 `different_workers`, before anything is made: a recording's grid
  samples its arms' hubs and cameras in one process (app/recording/session.py), and the way out
  is the config's (`worker = K` on the arms recorded together; their cameras follow their arm).
  `/recordings/{id}/...` goes to the worker of the dataset's arms, read once from its
  `armserver.json` in the shared data folder; `GET /recordings` merges the lists, each dataset
  as its arms' worker describes it (every worker opens the folder's datasets at its start, but
  only the one recording it knows its current episode).
"""

from __future__ import annotations

import asyncio
import json
import re
from pathlib import Path
from typing import Any

from app.errors import DifferentWorkers
from app.lab.placement import LabPlan
from app.recording.feeds import RECORDINGS_DIR
from app.recording.manager import CONFIG as DATASET_CONFIG
from app.web.middleware import API_PREFIX

TELEOP = API_PREFIX + "/teleop"
RECORDINGS = API_PREFIX + "/recordings"
#: A dataset's id as app/recording/manager.py allows it (no path separator, no leading dot).
DATASET_ID = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")


def handles(path: str) -> bool:
    return any(path == p or path.startswith(p + "/") for p in (TELEOP, RECORDINGS))


def _json(body: bytes) -> dict[str, Any]:
    try:
        data = json.loads(body)
    except (ValueError, UnicodeDecodeError):
        return {}
    return data if isinstance(data, dict) else {}


class Across:
    """Which worker serves a teleoperation or recordings request (see the module doc)."""

    def __init__(self, plan: LabPlan, data_dir: str) -> None:
        self.plan = plan
        self.worker_of = plan.worker_of
        self.camera_worker = plan.camera_worker
        self.datasets = Path(data_dir) / RECORDINGS_DIR
        #: Dataset id -> the worker of its arms (a dataset's arms never change).
        self._owner: dict[str, int] = {}

    async def place(self, method: str, path: str, body: bytes) -> int | None:
        """The worker index for this request; None: any (the first ready one answers, e.g.
        its 404 or 422). Raises DifferentWorkers for a recording across workers."""
        if path == TELEOP:
            follower = _json(body).get("follower") if method == "POST" else None
            return self.worker_of.get(follower) if isinstance(follower, str) else None
        if path == RECORDINGS:
            return self._new_recording(body) if method == "POST" else None
        if path.startswith(RECORDINGS + "/"):
            return await self.dataset_owner(path[len(RECORDINGS) + 1:].split("/", 1)[0])
        return None

    def _new_recording(self, body: bytes) -> int | None:
        data = _json(body)
        arms = [a for a in data.get("arms") or [] if isinstance(a, str)]
        cams = [c for c in data.get("cameras") or [] if isinstance(c, str)]
        where: dict[int, list[str]] = {}
        for name in arms:
            if name in self.worker_of:
                where.setdefault(self.worker_of[name], []).append(f"arm {name}")
        for name in cams:
            if name in self.camera_worker:
                where.setdefault(self.camera_worker[name], []).append(f"camera {name}")
        if len(where) > 1:
            split = "; ".join(f"worker {k}: {', '.join(v)}" for k, v in sorted(where.items()))
            raise DifferentWorkers("a recording's arms and cameras must live "
                          f"on one worker process, and these do not ({split}): give the arms "
                          "recorded together the same `worker = K` in the config (a camera "
                          "goes with its arm)")
        return next(iter(where), None)

    async def dataset_owner(self, rid: str) -> int | None:
        """The worker of dataset `rid`'s arms (from its settings file), None when unknown."""
        if rid in self._owner:
            return self._owner[rid]
        if not DATASET_ID.match(rid):
            return None
        try:
            text = await asyncio.to_thread(
                (self.datasets / rid / DATASET_CONFIG).read_text, encoding="utf-8")
            arms = json.loads(text).get("arms") or []
        except (OSError, ValueError, AttributeError):
            return None
        k = next((self.worker_of[a] for a in arms if a in self.worker_of), None)
        if k is not None:
            self._owner[rid] = k
        return k

    def merge_recordings(self, answers: dict[int, Any]) -> list[Any]:
        """Every dataset once, as its arms' worker lists it (else as the first lists it), by
        id."""
        out: dict[str, Any] = {}
        for k, listed in sorted(answers.items()):
            for entry in listed:
                owner = next((self.worker_of[a] for a in entry.get("arms", [])
                              if a in self.worker_of), None)
                if entry["id"] not in out or owner == k:
                    out[entry["id"]] = entry
        return [out[rid] for rid in sorted(out)]

    @staticmethod
    def merge_teleop(answers: dict[int, Any]) -> list[Any]:
        """Every worker's sessions: running ones first, each part by its start."""
        every = [t for _, listed in sorted(answers.items()) for t in listed]
        return sorted(every, key=lambda t: (t.get("status") != "running", t.get("started", 0)))
