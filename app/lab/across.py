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
        #: Dataset id -> where its arms and cameras live (a dataset's arms never change).
        self._datasets: dict[str, dict[int, list[str]]] = {}

    async def place(self, method: str, path: str, body: bytes) -> int | None:
        """The worker index for this request; None: any (the first ready one answers, e.g.
        its 404 or 422). Raises DifferentWorkers for a recording across workers: a new one,
        or an episode of one made so elsewhere (a single server's dataset, a changed config)."""
        if path == TELEOP:
            follower = _json(body).get("follower") if method == "POST" else None
            return self.worker_of.get(follower) if isinstance(follower, str) else None
        if path == RECORDINGS:
            if method != "POST":
                return None
            data = _json(body)
            return self._one_worker(self._where(data.get("arms"), data.get("cameras")))
        if path.startswith(RECORDINGS + "/"):
            rid, _, rest = path[len(RECORDINGS) + 1:].partition("/")
            where = await self._dataset(rid)
            if not where:  # no such dataset, or none of its arms here
                return None
            if method == "POST" and rest.startswith("episodes"):
                return self._one_worker(where)
            return min(where)  # to read it, any of them: the folder is shared
        return None

    def _where(self, arms: Any, cameras: Any) -> dict[int, list[str]]:
        """Worker -> the named arms and cameras it hosts (names it does not know left out:
        the worker answers them with its 404)."""
        where: dict[int, list[str]] = {}
        for kind, names, of in (("arm", arms, self.worker_of),
                                ("camera", cameras, self.camera_worker)):
            for name in names if isinstance(names, list) else []:
                if isinstance(name, str) and name in of:
                    where.setdefault(of[name], []).append(f"{kind} {name}")
        return where

    @staticmethod
    def _one_worker(where: dict[int, list[str]]) -> int | None:
        if len(where) > 1:
            split = "; ".join(f"worker {k}: {', '.join(v)}" for k, v in sorted(where.items()))
            raise DifferentWorkers(
                f"a recording's arms and cameras must live on one worker process, and these "
                f"do not ({split}): give the arms recorded together the same `worker = K` in "
                "the config (a camera goes with its arm)")
        return next(iter(where), None)

    async def _dataset(self, rid: str) -> dict[int, list[str]] | None:
        """Where dataset `rid`'s arms and cameras live (from its settings file, read once);
        None when there is no such dataset."""
        if rid in self._datasets:
            return self._datasets[rid]
        if not DATASET_ID.match(rid):
            return None
        try:
            text = await asyncio.to_thread(
                (self.datasets / rid / DATASET_CONFIG).read_text, encoding="utf-8")
            config = json.loads(text)
            where = self._where(config.get("arms"), config.get("cameras"))
        except (OSError, ValueError, AttributeError):
            return None
        self._datasets[rid] = where
        return where

    async def dataset_owner(self, rid: str) -> int | None:
        """The worker that serves dataset `rid` (of its arms), None when unknown."""
        where = await self._dataset(rid)
        return min(where) if where else None

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
