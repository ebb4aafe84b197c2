"""`armserver estop [ARM ...]` (app/client/estop_cli.py): every arm of a real server (uvicorn
on a loopback port, the default simulated arms) pressed at once from the command line; what
it prints and its exit status when an arm is unknown, the token is missing, or no server
answers."""

from __future__ import annotations

import json
import socket
from typing import Any

import httpx
import pytest
from conftest import make_settings, serve_live

from app.cli import main

VIEWER = "viewer-secret"
OPERATOR = "operator-secret"


def _run(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, Any, str]:
    code = main(["estop", *argv])
    out, err = capsys.readouterr()
    return code, json.loads(out) if out else None, err


def _estops(url: str) -> dict[str, bool]:
    head = {"Authorization": f"Bearer {OPERATOR}"}
    return {a: httpx.get(f"{url}/api/v1/arms/{a}/state", headers=head).json()["estop"]
            for a in ("rbe3001", "angler")}


def test_every_arm_is_latched_at_once_by_a_viewer(capsys: pytest.CaptureFixture[str]) -> None:
    settings = make_settings(viewer_tokens=VIEWER, operator_tokens=OPERATOR)
    with serve_live(settings) as live:
        assert _estops(live.url) == {"rbe3001": False, "angler": False}
        code, out, _ = _run(capsys, "--url", live.url, "--token", VIEWER)
        assert code == 0 and out == {"latched": ["rbe3001", "angler"], "failed": []}, out
        assert _estops(live.url) == {"rbe3001": True, "angler": True}
        # named arms only, one of them unknown: the known one latched, the other said, exit 1
        for arm in ("rbe3001", "angler"):
            r = httpx.delete(f"{live.url}/api/v1/arms/{arm}/estop",
                             headers={"Authorization": f"Bearer {OPERATOR}"})
            assert r.status_code == 200, r.text
        code, out, _ = _run(capsys, "angler", "no-such-arm", "angler", "--url", live.url,
                            "--token", VIEWER)
        assert code == 1, out
        assert out["latched"] == ["angler"]
        assert [(f["arm"], f["code"], f["status"]) for f in out["failed"]] == [
            ("no-such-arm", "unknown_arm", 404)]
        assert _estops(live.url) == {"rbe3001": False, "angler": True}
        # no token: health names the arms, and each press is refused, said arm by arm
        code, out, _ = _run(capsys, "--url", live.url)
        assert code == 1 and out["latched"] == [], out
        assert [(f["arm"], f["code"]) for f in out["failed"]] == [
            ("rbe3001", "unauthorized"), ("angler", "unauthorized")]
        assert _estops(live.url) == {"rbe3001": False, "angler": True}


def test_no_server_is_exit_2(capsys: pytest.CaptureFixture[str]) -> None:
    with socket.socket() as s:  # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    code, out, err = _run(capsys, "--url", f"http://127.0.0.1:{port}", "--timeout", "2")
    # (the arms' names cannot be had: said once, with the client's code)
    assert code == 2 and out is None
    assert json.loads(err)["code"] == "connection_failed", err
    code, out, _ = _run(capsys, "rbe3001", "--url", f"http://127.0.0.1:{port}",
                        "--timeout", "2")
    assert code == 2 and out["latched"] == [], out
    assert out["failed"][0]["code"] == "connection_failed", out
