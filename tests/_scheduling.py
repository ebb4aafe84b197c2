"""How `make test` hands tests to pytest-xdist's workers (tests/conftest.py's
`pytest_xdist_make_scheduler` returns these for `--dist loadfile` and `--dist loadgroup`).

- The parallel part (`--dist loadfile`): a file to a worker at a time, as xdist's own, but the
  heaviest files first (each file's seconds in a `make test` run, tests/file_seconds.json,
  written by tools/test_seconds.py). xdist orders files by their number of tests, which left the
  long files of few tests (schemathesis, the fifty-student class, the sorting example) to the
  end: one worker ran on some 50 s after the other three had finished (311 s against 262 s,
  replaying one run's per-test durations in both orders). A file not in the record goes last.
- The serial part (`--dist loadgroup`): two lanes, a worker each, the tests of a lane one after
  another (`lane_of`). xdist's own loadgroup marks a test's group by appending `@group` to its
  node id, which pytest 9.2 no longer lets a plugin change (pytest-dev/pytest-xdist#1386, open):
  the group was silently lost and the serial part's tests went to both workers as they came,
  two browser tests or two timing tests side by side. The lane here is read from the test's
  file, in the controller, where the scheduler runs; nothing depends on the node id's form.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from xdist.scheduler import LoadFileScheduling, LoadScopeScheduling

#: Each test file's seconds in a `make test` run (tools/test_seconds.py writes it).
FILE_SECONDS = Path(__file__).with_name("file_seconds.json")

#: The serial part's `timing` lane: the tests that measure a speed or a hold (a joint's peak
#: speed, a held-up executor, an estop's hold, moves between link cuts, a bounded shutdown), one
#: after another, and the servo set-up's routes (no page, no measured speed: here for the lanes'
#: balance, 200 s each in a run of session 28, where the browser lane's 227 s was the part's
#: length). Every other serial test (the browser tests, and the rest) is in the `browser` lane.
#: The lab's killed worker (test_lab_workers.py) is not moved: beside two pages its other arm
#: kept 240-385 samples/s over the restart (session 26). A replayed path judged against
#: wall-clock servos (test_replay*.py, 2 mm) is in the browser lane: after a browser test, never
#: beside one (beside two browser test files its arm's samples came 10-20 ms apart instead of 5
#: and the path missed 2 mm in 10 of 23 runs, session 27).
TIMING_LANE_FILES = frozenset({
    "test_safety_machine.py", "test_passthrough_safety.py", "test_passthrough_check_poll.py",
    "test_tracking.py", "test_motion.py", "test_envelope_props.py", "test_control.py",
    "test_replan.py", "test_soak.py", "test_shutdown.py", "test_setup_servos_routes.py",
})


def lane_of(file_name: str) -> str:
    """The serial lane of the tests in the file named `file_name` (its base name)."""
    return "timing" if file_name in TIMING_LANE_FILES else "browser"


def file_seconds() -> dict[str, float]:
    """FILE_SECONDS read; empty if it is missing or unreadable (files then go as collected)."""
    try:
        data = json.loads(FILE_SECONDS.read_text())
    except (OSError, ValueError):
        return {}
    return {str(k): float(v) for k, v in data.items()} if isinstance(data, dict) else {}


def order_heaviest_first(items: list[Any]) -> None:
    """Sort a worker's collected `items` by their file's seconds, heaviest first. Stable: a
    file's tests keep their order and stay together; files not measured go last as collected.
    On the workers, not in the scheduler: a worker runs the tests it is sent by their index in
    its own collection, so the order is the collection's (and each worker sorts the same)."""
    seconds = file_seconds()
    items.sort(key=lambda item: -seconds.get(item.path.name, 0.0))


class HeaviestFileFirst(LoadFileScheduling):
    """`--dist loadfile`, the files handed out in the order the workers collected them
    (`order_heaviest_first`), not xdist's by number of tests."""

    def __init__(self, config: Any, log: Any = None) -> None:
        super().__init__(config, log)
        config.option.loadscopereorder = False


class Lanes(LoadScopeScheduling):
    """`--dist loadgroup` as the serial part means it: a lane (`lane_of`) to a worker."""

    def _split_scope(self, nodeid: str) -> str:
        return lane_of(Path(nodeid.split("::", 1)[0]).name)
