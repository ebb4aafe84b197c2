"""Which worker process hosts which arm (`armserver serve --workers N`).

An `[[arms]]` entry may name its worker (`worker = K`, 0-based, app/arms/loading.py); the other
arms go, in config order, each to the worker that has the fewest arms so far (the lowest index
on a tie). A camera goes with its arm. The front and every worker compute the same plan from
the same config, so a worker needs only its index to know its arms and cameras.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from app.arms.loading import load_arms
from app.cameras.config import CameraConfig, load_cameras
from app.config import ArmProfile, ConfigError, Settings


@dataclass(frozen=True)
class LabPlan:
    """The arms of each worker, in config order; `worker_of` maps an arm name to its worker."""

    workers: tuple[tuple[ArmProfile, ...], ...]
    #: Every arm's name, in config order.
    names: tuple[str, ...]
    #: Every camera (the config's `[[cameras]]`, else one per simulated arm), in order; a
    #: camera lives in the worker of its `arm`.
    cameras: tuple[CameraConfig, ...] = ()

    @property
    def worker_of(self) -> dict[str, int]:
        return {p.name: k for k, arms in enumerate(self.workers) for p in arms}

    @property
    def camera_worker(self) -> dict[str, int]:
        """Camera name -> the worker of its arm."""
        worker_of = self.worker_of
        return {c.name: worker_of[c.arm] for c in self.cameras if c.arm in worker_of}

    def cameras_of(self, k: int) -> list[CameraConfig]:
        names = {p.name for p in self.workers[k]}
        return [c for c in self.cameras if c.arm in names]

    def profile(self, name: str) -> ArmProfile:
        return next(p for arms in self.workers for p in arms if p.name == name)


def worker_socket(folder: Path, k: int) -> Path:
    """Worker `k`'s Unix socket in the lab's folder (the front's and the other workers' way to
    it)."""
    return folder / f"worker-{k}.sock"


def lab_workers(settings: Settings, workers: int | None) -> int:
    """How many worker processes to run: `workers` when given (1: today's single process), else
    one more than the highest `worker` the config names, else 1."""
    if workers is not None:
        return workers
    placed: dict[str, int] = {}
    load_arms(settings.config, placed)
    return max(placed.values(), default=0) + 1


def plan_lab(settings: Settings, workers: int) -> LabPlan:
    """Place the config's arms on `workers` processes (see the module doc). Raises ConfigError
    for an arm placed on a worker that does not exist, and for a simulated camera whose arm
    and the arm whose world it renders (`sim:<arm>`) are on different workers."""
    placed: dict[str, int] = {}
    profiles = load_arms(settings.config, placed)
    bins: list[list[ArmProfile]] = [[] for _ in range(workers)]
    for name, k in placed.items():
        if k >= workers:
            raise ConfigError(f"arm {name!r} names worker {k}, but the server runs {workers} "
                              f"worker(s) (0..{workers - 1}): raise --workers")
    for p in profiles:
        if p.name in placed:
            bins[placed[p.name]].append(p)
    for p in profiles:
        if p.name not in placed:
            min(bins, key=len).append(p)
    order = {p.name: i for i, p in enumerate(profiles)}
    plan = LabPlan(tuple(tuple(sorted(b, key=lambda p: order[p.name])) for b in bins),
                   tuple(p.name for p in profiles),
                   tuple(load_cameras(settings.config, profiles)))
    worker_of = plan.worker_of
    for cam in plan.cameras:
        seen = cam.source[4:] if cam.kind == "sim" else cam.arm
        if worker_of[seen] != worker_of[cam.arm]:
            raise ConfigError(f"camera {cam.name!r} renders arm {seen!r}'s simulated world "
                              f"(worker {worker_of[seen]}) but belongs to arm {cam.arm!r} "
                              f"(worker {worker_of[cam.arm]}): a world and its cameras live "
                              "in one process; give both arms the same `worker = K`")
    return plan
