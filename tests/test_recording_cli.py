"""`armserver record ...` against a real uvicorn server: a dataset created, an episode recorded
and written, one discarded, refusals on stderr with their codes, the archive downloaded."""

from __future__ import annotations

import io
import json
import tarfile
import time
from pathlib import Path

import pytest

from app.cli import main
from tests._lerobot import check_dataset
from tests.conftest import LiveServer


def run(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, dict | list | None, str]:
    rc = main(["record", *argv])
    out, err = capsys.readouterr()
    return rc, (json.loads(out) if out.strip() else None), err


def test_record_from_the_shell(live_server: LiveServer, capsys: pytest.CaptureFixture[str],
                               tmp_path: Path) -> None:
    url = ["--url", live_server.url]
    rc, d, _ = run(capsys, "create", "shell", "--arm", "rbe3001", "--fps", "10",
                   "--task", "wave", *url)
    assert rc == 0 and isinstance(d, dict) and d["episodes"] == 0
    rc, d, _ = run(capsys, "start", "shell", *url)
    assert rc == 0 and isinstance(d, dict) and d["recording"] is True
    rc, _, err = run(capsys, "start", "shell", *url)
    assert rc == 1 and json.loads(err)["code"] == "busy"
    deadline = time.monotonic() + 20
    while True:  # a few frames
        rc, d, _ = run(capsys, "show", "shell", *url)
        assert isinstance(d, dict) and time.monotonic() < deadline
        if d["current"]["frames"] >= 5:
            break
        time.sleep(0.05)
    rc, d, _ = run(capsys, "stop", "shell", *url)
    assert rc == 0 and isinstance(d, dict) and d["episodes"] == 1
    rc, d, _ = run(capsys, "start", "shell", "--task", "other", *url)
    rc, d, _ = run(capsys, "discard", "shell", *url)
    assert rc == 0 and isinstance(d, dict) and d["episodes"] == 1
    rc, d, _ = run(capsys, "list", *url)
    assert rc == 0 and isinstance(d, list) and [x["id"] for x in d] == ["shell"]
    rc, _, err = run(capsys, "create", "x", "--arm", "nope", *url)
    assert rc == 1 and json.loads(err)["code"] == "unknown_arm"
    tar = tmp_path / "shell.tar"
    rc, d, _ = run(capsys, "archive", "shell", "-o", str(tar), *url)
    assert rc == 0 and isinstance(d, dict) and d["bytes"] == tar.stat().st_size
    with tarfile.open(fileobj=io.BytesIO(tar.read_bytes())) as t:
        # (the "data" filter where the interpreter has it: 3.11.4 on, not Debian 12's 3.11.2)
        t.extractall(tmp_path / "x",
                     **({"filter": "data"} if hasattr(tarfile, "data_filter") else {}))
    read = check_dataset(tmp_path / "x" / "shell")
    assert read.tasks == {0: "wave"} and read.info["total_episodes"] == 1
