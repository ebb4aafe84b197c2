"""bench/lab.py gives each simulator process the arms of one worker (issue 27's lab bench).

A worker's poll thread writes the due polls of all its arms at once; a simulator process that
serves only that worker's arms gets them in one wake-up a round. The bench before session 33
gave each process the config's next arms, which the placement spreads over both workers (arm-1
on worker 0, arm-2 on worker 1, ...): two wake-ups a round per process, and a 32-arm estop seen
p99 some 1.5 ms higher (docs/performance.md, "Session 33").
"""

from __future__ import annotations

import importlib.util
from pathlib import Path
from types import ModuleType

import pytest

from app.config import Settings
from app.lab.placement import plan_lab

ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="module")
def lab() -> ModuleType:
    spec = importlib.util.spec_from_file_location("bench_lab", ROOT / "bench" / "lab.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _config(tmp_path: Path, arms: int) -> Path:
    cfg = tmp_path / "lab.toml"
    cfg.write_text("\n".join(
        f'[[arms]]\nprofile = "rbe3001"\nname = "arm-{i + 1}"\n[arms.link]\nkind = "serial"\n'
        f'address = "socket://127.0.0.1:{9100 + i}"\n' for i in range(arms)))
    return cfg


def test_each_simulator_serves_the_arms_of_one_worker(lab: ModuleType, tmp_path: Path) -> None:
    cfg = _config(tmp_path, 7)
    groups = lab._sim_groups(cfg, 2, 2, False)
    plan = plan_lab(Settings(config=str(cfg)), 2)
    worker_of = {9100 + i: plan.worker_of[f"arm-{i + 1}"] for i in range(7)}
    # worker 0: arm-1, 3, 5, 7; worker 1: arm-2, 4, 6 (the fewest so far, in config order)
    assert groups == [[9100, 9102], [9104, 9106], [9101, 9103], [9105]]
    assert all(len({worker_of[port] for port in g}) == 1 for g in groups)
    assert sorted(p for g in groups for p in g) == list(range(9100, 9107))


def test_in_order_keeps_the_earlier_grouping(lab: ModuleType, tmp_path: Path) -> None:
    cfg = _config(tmp_path, 5)
    assert lab._sim_groups(cfg, 2, 2, True) == [[9100, 9101], [9102, 9103], [9104]]
    assert lab._sim_groups(cfg, 1, 16, False) == [[9100, 9101, 9102, 9103, 9104]]
