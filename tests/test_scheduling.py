"""`make test` hands tests to its workers as tests/_scheduling.py says: the serial part in two
lanes (never two browser tests or two timing tests side by side), the parallel part a file to a
worker, heaviest first. Run for real: pytest with xdist over some of the suite's own files, each
test skipped at its setup (nothing starts), and read which worker ran what. (pytest 9.2 made
xdist's own `xdist_group` lanes hand out tests as they came, and nothing failed: this is the
test that would have.)"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from collections import defaultdict
from pathlib import Path

from tests._scheduling import file_seconds, lane_of

ROOT = Path(__file__).resolve().parents[1]

SKIP_ALL = '''
import pytest

@pytest.hookimpl(tryfirst=True)
def pytest_runtest_setup(item):
    pytest.skip("scheduling only")
'''


def _workers(tmp_path: Path, *args: str) -> list[tuple[str, str]]:
    """(worker, file) of each test in the order reported, for `pytest -v *args`."""
    (tmp_path / "skip_all.py").write_text(SKIP_ALL)
    env = {k: v for k, v in os.environ.items() if not k.startswith("PYTEST_")}
    env["PYTHONPATH"] = os.pathsep.join([str(tmp_path), env.get("PYTHONPATH", "")])
    env["ARMSERVER_STRICT_SKIPS"] = "0"  # the skips are the point here
    out = subprocess.run([sys.executable, "-m", "pytest", "-v", "-p", "skip_all",
                          "-p", "no:cacheprovider", *args],
                         cwd=ROOT, env=env, capture_output=True, text=True, timeout=240)
    runs = re.findall(r"^\[(gw\d+)\] .*?SKIPPED (tests/[\w.]+)::", out.stdout, re.M)
    assert runs, out.stdout[-3000:] + out.stderr[-3000:]
    return runs


SERIAL = ["tests/test_dashboard_e2e.py", "tests/test_lab_view_e2e.py", "tests/test_replay.py",
          "tests/test_control.py", "tests/test_replan.py", "tests/test_tracking.py"]


def test_the_serial_part_runs_its_two_lanes_on_a_worker_each(tmp_path: Path) -> None:
    runs = _workers(tmp_path, "-n", "2", "--dist", "loadgroup", "-m", "serial", *SERIAL)
    lanes: dict[str, set[str]] = defaultdict(set)
    for worker, file in runs:
        lanes[worker].add(lane_of(Path(file).name))
    assert sorted(map(sorted, lanes.values())) == [["browser"], ["timing"]], runs
    assert {Path(f).name for _, f in runs} == {Path(f).name for f in SERIAL}


PARALLEL = ["tests/test_api_kinematics.py", "tests/test_fuzz_api.py", "tests/test_api_arms.py",
            "tests/test_classroom_class.py", "tests/test_rbe3001_protocol.py",
            "tests/test_config.py"]


def test_the_parallel_part_hands_out_whole_files_heaviest_first(tmp_path: Path) -> None:
    seconds = file_seconds()
    names = [Path(f).name for f in PARALLEL]
    assert all(n in seconds for n in names), "tests/file_seconds.json lacks one of them"
    runs = _workers(tmp_path, "-n", "2", "--dist", "loadfile", "-m", "not serial", *PARALLEL)
    owner: dict[str, set[str]] = defaultdict(set)
    for worker, file in runs:
        owner[file].add(worker)
    assert all(len(w) == 1 for w in owner.values()), dict(owner)  # a file to one worker
    # each worker's files in the order of their seconds (the heaviest of all first on one)
    by_worker: dict[str, list[str]] = defaultdict(list)
    for worker, file in runs:
        if not by_worker[worker] or by_worker[worker][-1] != file:
            by_worker[worker].append(file)
    for files in by_worker.values():
        weights = [seconds[Path(f).name] for f in files]
        assert weights == sorted(weights, reverse=True), by_worker
    heaviest = max(names, key=lambda n: seconds[n])
    assert any(files[0].endswith(heaviest) for files in by_worker.values()), by_worker


def test_the_file_seconds_tool_sums_a_files_tests_over_the_reports(tmp_path: Path) -> None:
    """tools/test_seconds.py: each test file's seconds summed over its test cases and over the
    reports (parallel and serial part); a report that is not there is named, rc 2."""
    for name, cases in (("parallel.xml", [("tests.test_a", 1.3), ("tests.test_a", 2.0),
                                          ("tests.test_b.TestThing", 0.5)]),
                        ("serial.xml", [("tests.test_a", 3.0)])):
        body = "".join(f'<testcase classname="{c}" name="t{k}" time="{t}"/>'
                       for k, (c, t) in enumerate(cases))
        (tmp_path / name).write_text(f'<testsuites><testsuite>{body}</testsuite></testsuites>')
    out = tmp_path / "seconds.json"
    tool = [sys.executable, str(ROOT / "tools" / "test_seconds.py"), "--out", str(out)]
    done = subprocess.run([*tool, str(tmp_path / "parallel.xml"), str(tmp_path / "serial.xml")],
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    assert json.loads(out.read_text()) == {"test_a.py": 6.3, "test_b.py": 0.5}
    missing = subprocess.run([*tool, str(tmp_path / "nope.xml")], capture_output=True,
                             text=True, timeout=60)
    assert missing.returncode == 2 and "no such report" in missing.stderr
