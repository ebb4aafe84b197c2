"""README "On real hardware", the block after `<!-- README-SETUP-SERVOS -->`, run as written in
bash against a live server (a free loopback port instead of 8000): the practice bus started,
its factory servo scanned, set up as the angler's x, the next servo plugged in, the bus
stopped."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

from conftest import serve_live

ROOT = Path(__file__).resolve().parents[1]
MARKER = "<!-- README-SETUP-SERVOS -->"


def readme_block() -> str:
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    return text[text.index(MARKER):].split("```sh\n", 1)[1].split("```", 1)[0]


def answers(out: str) -> list[dict[str, object]]:
    """The JSON answers curl printed one after the other (no newline between them)."""
    decoder, found, at = json.JSONDecoder(), [], 0
    while at < len(out):
        if out[at].isspace():
            at += 1
            continue
        value, at = decoder.raw_decode(out, at)
        found.append(value)
    return found


def test_the_readme_block_runs_as_written() -> None:
    block = readme_block()
    assert "localhost:8000" in block
    with serve_live() as live:
        script = "set -eu\n" + block.replace("localhost:8000", live.url.removeprefix("http://"))
        run = subprocess.run(["bash", "-c", script], capture_output=True, text=True,
                             timeout=120, cwd=ROOT)
    assert run.returncode == 0, run.stderr
    scan, assign, plugged, stopped = answers(run.stdout)
    assert len(scan["servos"]) == 1, json.dumps(scan)  # all of it: collisions, garbled rates
    [servo] = scan["servos"]
    assert (servo["id"], servo["baudrate"], servo["factory"]) == (1, 57_600, True)
    assert assign.get("joint") == "x", assign
    assert (assign["servo"]["id"], assign["servo"]["baudrate"]) == (2, 1_000_000)
    assert plugged["servos"] == [{"id": 2, "baudrate": 1_000_000},
                                 {"id": 1, "baudrate": 57_600}]
    assert stopped == {"running": False, "port": None, "servos": []}
