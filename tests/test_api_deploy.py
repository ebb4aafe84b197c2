"""The command line (`armserver serve|devices|sim`) and the container files."""

from __future__ import annotations

import json
import urllib.request
from pathlib import Path

import pytest
import yaml

from app import cli
from tests._serve import served, start

ROOT = Path(__file__).resolve().parent.parent


def test_compose_file_parses_and_runs_the_sim_by_default() -> None:
    doc = yaml.safe_load((ROOT / "docker-compose.yml").read_text())
    svc = doc["services"]["armserver"]
    assert svc["build"] == "."
    assert any(str(p).endswith("8000:8000") for p in svc["ports"])
    assert "ARMSERVER_CONFIG" not in svc["environment"]  # default: the simulated arms
    text = (ROOT / "docker-compose.yml").read_text()
    assert "/dev/ttyUSB0:/dev/ttyUSB0" in text and "/dev/hidraw0" in text


def test_dockerfile_serves_on_all_interfaces() -> None:
    text = (ROOT / "Dockerfile").read_text()
    assert text.startswith("#") and "FROM python:3.11-slim" in text
    assert "pip install" in text
    cmd = next(line for line in text.splitlines() if line.startswith("CMD"))
    assert json.loads(cmd[3:]) == ["armserver", "serve", "--host", "0.0.0.0", "--port", "8000"]


def test_serve_flags_override_the_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("ARMSERVER_PORT", "9001")
    monkeypatch.setenv("ARMSERVER_LOG_LEVEL", "debug")
    args = cli._parser().parse_args(["serve", "--host", "0.0.0.0"])
    s = cli._settings(args)
    assert (s.host, s.port, s.log_level) == ("0.0.0.0", 9001, "debug")
    args = cli._parser().parse_args(["serve"])
    monkeypatch.delenv("ARMSERVER_PORT")
    assert cli._settings(args).host == "127.0.0.1"  # loopback unless told otherwise


def test_devices_and_sim_help(capsys: pytest.CaptureFixture[str]) -> None:
    assert cli.main(["devices"]) == 0
    assert "KIND" in capsys.readouterr().out
    with pytest.raises(SystemExit) as exc:
        cli.main(["sim", "--help"])
    assert exc.value.code == 0
    assert "armserver sim" in capsys.readouterr().out


def test_client_commands_are_registered() -> None:
    parser = cli._parser()
    helptext = parser.format_help()
    for cmd in ("serve", "devices", "sim"):
        assert cmd in helptext
    try:
        import app.client.cli  # noqa: F401
    except ImportError:
        return
    assert "call" in helptext and "watch" in helptext


def test_armserver_serve_runs_and_says_it_is_open(tmp_path: Path) -> None:
    # (the console script's entry point, `run()`, as `armserver serve` calls it)
    with served(tmp_path / "server.log", "serve", "--log-level", "info",
                command=("-c", "from app.cli import run; run()")) as srv:
        with urllib.request.urlopen(f"{srv.url}/api/v1/health", timeout=10) as r:
            body = json.loads(r.read())
        assert set(body["arms"]) == {"rbe3001", "angler"}
    out = srv.output()
    assert "the server is OPEN to anyone who can reach it" in out


def test_a_server_that_does_not_start_fails_the_test_with_its_own_words(tmp_path: Path) -> None:
    # (tests/_serve.py, which the tests of a real process use: the output is a file's, not an
    # unread pipe's, and a failure quotes it)
    with pytest.raises(AssertionError, match=r"(?s)exited \(2\).*invalid choice: 'loud'"):
        start(tmp_path / "server.log", "--log-level", "loud")
