"""Every example script, run as a user runs it: a subprocess with `--url` against a real server
(`armserver serve`, as `make run` starts it, on a free port), exit status 0 and the lines that
show it did its job. `--quick` keeps the whole module under about a minute.

The examples that move different arms (pick-and-place: rbe3001, angler visit: angler) and the
workspace plot run at the same time; the others one after another.
"""

from __future__ import annotations

import csv
import os
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests._serve import served

ROOT = Path(__file__).resolve().parent.parent
EXAMPLES = ROOT / "examples"
#: Longest one example may run, s (each takes 3-15 s on an idle machine).
EXAMPLE_TIMEOUT_S = 120


def _env() -> dict[str, str]:
    env = dict(os.environ)
    for key in ("ARMSERVER_OPERATOR_TOKENS", "ARMSERVER_VIEWER_TOKENS", "ARMSERVER_CONFIG",
                "ARMSERVER_TOKEN", "ARMSERVER_URL"):
        env.pop(key, None)
    env["MPLBACKEND"] = "Agg"
    return env


@pytest.fixture(scope="module")
def url(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    """`armserver serve` as `make run` starts it (its default log level), on a free port."""
    with served(tmp_path_factory.mktemp("server") / "server.log", env=_env()) as srv:
        yield srv.url


def _start(script: str, *args: str) -> subprocess.Popen[str]:
    return subprocess.Popen([sys.executable, str(EXAMPLES / script), *args], cwd=ROOT,
                            env=_env(), stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True)


def _finish(proc: subprocess.Popen[str]) -> str:
    try:
        out, _ = proc.communicate(timeout=EXAMPLE_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, _ = proc.communicate()
        pytest.fail(f"{proc.args} timed out:\n{out}")
    assert proc.returncode == 0, f"{proc.args} exited {proc.returncode}:\n{out}"
    return out


def _run(script: str, *args: str) -> str:
    return _finish(_start(script, *args))


@pytest.fixture(scope="module")
def parallel(url: str, tmp_path_factory: pytest.TempPathFactory) -> dict[str, object]:
    """Start the examples that do not share an arm together; their outputs by name."""
    plots = tmp_path_factory.mktemp("plots")
    procs = {
        "pick_and_place": _start("pick_and_place.py", "--url", url, "--quick"),
        "angler_visit": _start("angler_visit.py", "--url", url, "--quick"),
        "workspace_plot": _start("workspace_plot.py", "--url", url, "--points", "300",
                                 "--out-dir", str(plots)),
    }
    t0 = time.monotonic()
    results: dict[str, object] = {}
    for name, p in procs.items():
        results[name] = _finish(p)
        print(f"{name}: {time.monotonic() - t0:.1f} s")
    results["plots"] = plots
    return results


def test_pick_and_place(parallel: dict[str, object]) -> None:
    out = str(parallel["pick_and_place"])
    for line in ("open claw", "approach (joint path)", "descend (line)", "close claw",
                 "lift (line)", "carry to red bin", "release", "return home", "tip force",
                 "pick and place done: 1 objects placed"):
        assert line in out, f"{line!r} missing:\n{out}"


def test_angler_visit(parallel: dict[str, object]) -> None:
    out = str(parallel["angler_visit"])
    assert "ik_case dx_zero" in out and "ik_case dx_used" in out
    # as the design document (issue 24): the origin is every joint at 0, and dx_used takes
    # theta3 = -90 deg for x > 0
    assert "origin: every joint at 0" in out
    assert "dx_used target ( +90.0,  +30.0,   +0.0) mm" in out
    assert "theta3 -90 deg (design)" in out
    assert out.count("origin   arrived:") == 3 and out.count("target   arrived:") == 2
    assert "angler visit done: 2 targets visited" in out


def test_workspace_plot(parallel: dict[str, object]) -> None:
    out = str(parallel["workspace_plot"])
    plots = Path(str(parallel["plots"]))
    assert "workspace plots done" in out
    for arm in ("rbe3001", "angler"):
        png = plots / f"workspace_{arm}.png"
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_record_then_replay(url: str, tmp_path: Path, parallel: dict[str, object]) -> None:
    run_csv, run_png = tmp_path / "run.csv", tmp_path / "run.png"
    out = _run("record.py", "--url", url, "--demo", "--quick", "--rate", "20",
               "--csv", str(run_csv), "--png", str(run_png))
    assert "record done" in out and " 0 gaps" in out, out
    with run_csv.open() as f:
        rows = list(csv.DictReader(f))
    assert list(rows[0])[:6] == ["seq", "time", "t", "base", "shoulder", "elbow"]
    seqs = [int(r["seq"]) for r in rows]
    assert len(rows) > 100 and seqs == sorted(set(seqs))
    assert run_png.read_bytes()[:4] == b"\x89PNG"

    out = _run("replay.py", str(run_csv), "--url", url, "--arm", "rbe3001", "--points", "6")
    assert "waypoint" in out and "replay done" in out, out


def test_scripted_session(url: str, parallel: dict[str, object]) -> None:
    out = _run("scripted_session.py", "--url", url, "--quick")
    for line in ("arms: rbe3001", "422 unreachable", "409 estop_latched", "no gaps",
                 "stopped (stopped by instructor (open server)", "scripted session passed"):
        assert line in out, f"{line!r} missing:\n{out}"
