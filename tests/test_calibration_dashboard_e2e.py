"""End to end: the dashboard's Calibration panel (app/web/static/calibration.js) leads a student
through the rbe3001's day-one calibration, in Debian's headless Chromium against a real server
on the simulated board as it ships (not calibrated, powered on in its jig)."""

from __future__ import annotations

import json
from pathlib import Path

import _browser
import pytest
from _wait import wait_until
from conftest import serve_live

from app.arms.loading import load_arms
from tests._http import HTTP

pytestmark = pytest.mark.browser

CONFIG = Path(__file__).resolve().parents[1] / "config" / "rbe3001-day-one.example.toml"

sync_api = _browser.sync_api_or_skip()


def test_the_panel_leads_through_declaring_the_jig_pose() -> None:
    with serve_live(profiles=load_arms(str(CONFIG))) as live, \
            sync_api.sync_playwright() as pw:
        page, errors = _browser.open_page(pw, live.url + "/", {"width": 1440, "height": 1000})
        joints = page.locator("#rbe3001-cal-joints")
        wait_until(lambda: joints.get_attribute("data-calibrated") == "[false,false,false]",
                   what="the panel shows no joint calibrated")
        steps = page.locator("#rbe3001-cal-steps").inner_text()
        assert "Not calibrated on this hardware: base, shoulder, elbow" in steps
        assert "jig" in steps
        assert page.locator("#rbe3001-cal-pose").input_value() == "jig"

        page.click("#rbe3001-cal-declare")
        wait_until(lambda: joints.get_attribute("data-calibrated") == "[true,true,true]",
                   what="the panel shows every joint calibrated")
        # the note comes with the POST's answer; the joints' flags may come first, with a sample
        wait_until(lambda: "calibrated" in page.locator("#rbe3001-cal-note").inner_text(),
                   what="the panel's note that the pose was declared")
        cal = HTTP.get(f"{live.url}/api/v1/arms/rbe3001/calibration", timeout=5).json()
        assert [j["source"] for j in cal["joints"]] == ["declared"] * 3 and cal["stored"]
        state = page.evaluate("() => window.armCalibration.state('rbe3001')")
        assert json.dumps(state["calibrated"]) == "[true, true, true]"
        assert not errors, f"uncaught errors in the page: {errors}"
