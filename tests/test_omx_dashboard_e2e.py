"""End to end: the dashboard draws the OpenManipulator-X from the joint chain the API
describes, beside the other two arm types (config/three-arms.example.toml on a real uvicorn),
in Debian's headless Chromium: the drawn tip against GET /state after a move, a jog button,
and the gripper slider driving servo 15. Skips as tests/test_dashboard_e2e.py does when
/usr/bin/chromium or playwright is missing."""

from __future__ import annotations

import math
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from _wait import wait_until
from conftest import make_settings

from tests.test_dashboard_e2e import (
    CHROMIUM,
    CHROMIUM_ARGS,
    OUT,
    TIP_TOL_REST_M,
    VIEWPORT,
    Server,
    api,
    at_rest,
    dash,
    serving,
    sync_api,
    tip_error,
)

pytestmark = pytest.mark.browser

CONFIG = Path(__file__).resolve().parents[1] / "config" / "three-arms.example.toml"


@pytest.fixture(scope="module")
def server() -> Iterator[Server]:
    OUT.mkdir(exist_ok=True)
    with serving(make_settings(config=str(CONFIG))) as srv:
        yield srv


@pytest.fixture(scope="module")
def page(server: Server) -> Iterator[Any]:
    with sync_api.sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        pg = browser.new_page(viewport=VIEWPORT)
        errors: list[str] = []
        pg.on("pageerror", lambda e: errors.append(str(e)))
        pg.goto(server.url + "/")
        wait_until(lambda: all((dash(pg, a) or {}).get("lastSeq") is not None
                               for a in ("rbe3001", "angler", "omx")),
                   what="telemetry of all three")
        yield pg
        pg.close()
        browser.close()
    assert not errors, f"uncaught errors in the page: {errors}"


def _drawn_matches_state(pg: Any, server: Server) -> dict[str, Any]:
    st = at_rest(server, "omx")
    wait_until(lambda: dash(pg, "omx")["lastSeq"] > st["seq"], what="newer telemetry")
    frames = dash(pg, "omx")["frames"]
    wait_until(lambda: dash(pg, "omx")["frames"] > frames + 2, what="frames drawn")
    drawn = dash(pg, "omx")["tipDrawn"]
    assert tip_error(drawn, st["tip"]) < TIP_TOL_REST_M, (drawn, st["tip"])
    return st


def test_the_omx_is_drawn_from_its_chain(page: Any, server: Server) -> None:
    q = [0.6, -0.4, 0.3, 0.5]
    m = api(server, "POST", "/arms/omx/move/joints", json={"positions": q, "wait": True})
    assert m["status"] == "done"
    st = _drawn_matches_state(page, server)
    assert "pitch" in st["tip"]  # the server reports it; the page draws the body points
    assert "link up" in page.inner_text("#omx-link")
    page.locator("#omx-gripper").scroll_into_view_if_needed()
    page.screenshot(path=str(OUT / "dashboard-omx.png"))


def test_jog_moves_the_wrist(page: Any, server: Server) -> None:
    before = at_rest(server, "omx")["positions"]
    page.click("#omx-jog-3-plus")
    want = before[3] + math.radians(5)
    wait_until(lambda: abs(api(server, "GET", "/arms/omx/state")["positions"][3] - want) < 0.01,
               what=f"wrist at {want:.3f} rad")
    _drawn_matches_state(page, server)


def test_gripper_slider_drives_servo_15(page: Any, server: Server) -> None:
    bus = server.app.state.services["omx"].driver.link.device
    page.locator("#omx-gripper").fill("1")
    wait_until(lambda: bus.servo(15).get("goal_position") == 2483, what="gripper goal written")
    wait_until(lambda: abs(api(server, "GET", "/arms/omx/state")["gripper"] - 1.0) < 0.01,
               what="gripper closed")
    assert page.inner_text("#omx-gripper-error") == ""
