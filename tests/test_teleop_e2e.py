"""End to end: the dashboard's teleoperation bar (app/web/static/teleop.js) in headless Chromium
against a real server of two simulated OpenManipulator-X arms (config/teleop_omx.toml): pick
leader, follower and rate, Start, the bar says running with the latency, the follower follows
the leader; the leader's samples going stale make it say held by the deadman; Stop ends the
session and the bar says stopped and by whom. The leader by hand: refused with its reason
until "I hold it" (`load_supported`) is ticked."""

from __future__ import annotations

from pathlib import Path

import _browser
import numpy as np
import pytest
from _wait import wait_until
from conftest import make_settings, serve_live

from app.config import FaultConfig
from app.runtime.control_thread import on_home
from tests._http import HTTP

pytestmark = pytest.mark.browser

sync_api = _browser.sync_api_or_skip()

CONFIG = Path(__file__).resolve().parents[1] / "config" / "teleop_omx.toml"
TOL = 8 * 2 * np.pi / 4096
GOAL = [0.5, -0.4, 0.3, 0.6]


def test_start_and_stop_teleop_from_the_bar() -> None:
    with serve_live(make_settings(config=str(CONFIG))) as live, \
            sync_api.sync_playwright() as pw:
        leader = live.app.state.services["leader"]
        follower = live.app.state.services["follower"]
        page, errors = _browser.open_page(pw, live.url + "/")

        def status() -> str:
            return str(page.locator("#teleop-status").text_content() or "")
        wait_until(lambda: page.locator("#teleop-follower option").count() == 2,
                   what="the arms in the bar")
        assert status() == "not running"
        page.select_option("#teleop-leader", "leader")
        page.select_option("#teleop-follower", "follower")
        page.fill("#teleop-rate", "60")
        page.click("#teleop-start")
        wait_until(lambda: status().startswith("running · ") and "latency p50 " in status()
                   and "ms · p99 " in status(), what="running with its latency shown")
        sessions = HTTP.get(f"{live.url}/api/v1/teleop").json()
        assert [(t["leader"], t["follower"], t["rate_hz"], t["status"]) for t in sessions] == [
            ("leader", "follower", 60.0, "running")]
        assert page.locator("#teleop-start").is_disabled()
        r = HTTP.post(f"{live.url}/api/v1/arms/leader/move/joints",
                      json={"positions": GOAL, "wait": True}, timeout=30)
        assert r.status_code == 200, r.text
        wait_until(lambda: np.allclose(follower.positions, GOAL, atol=TOL),
                   what="the follower at the leader's goal")

        def drop(rate: float) -> None:
            """The leader's simulated link loses its replies (injected on its control loop)."""
            async def apply() -> None:
                leader.driver.link.set_faults(FaultConfig(drop=rate))
            live.call(lambda: on_home(leader.home_loop, apply))
        drop(1.0)
        wait_until(lambda: status().startswith("held by deadman"), what="held by the deadman")
        drop(0.0)
        wait_until(lambda: status().startswith("running · "), what="running again")
        page.click("#teleop-stop")
        wait_until(lambda: status().startswith("stopped: stopped by"), what="stopped, and by whom")
        assert [t["status"] for t in HTTP.get(f"{live.url}/api/v1/teleop").json()] == ["ended"]
        assert not page.locator("#teleop-start").is_disabled()
        # the leader by hand: its shoulder, elbow and wrist fall without torque, so the bar's
        # Start is refused (its reason shown, the torque left on) until "I hold it" is ticked
        page.check("#teleop-by-hand")
        page.click("#teleop-start")
        wait_until(lambda: "fall without torque" in str(
            page.locator("#teleop-error").text_content() or ""), what="the refusal shown")
        assert len(HTTP.get(f"{live.url}/api/v1/teleop").json()) == 1  # none started
        r = HTTP.put(f"{live.url}/api/v1/arms/leader/world/hand", json={"wait": True})
        assert r.status_code == 200, r.text  # the world's hand takes hold of it first
        page.check("#teleop-holding")
        page.click("#teleop-start")
        wait_until(lambda: status().startswith("running · "), what="running, leader by hand")
        running = [t for t in HTTP.get(f"{live.url}/api/v1/teleop").json()
                   if t["status"] == "running"]
        assert [t["free_leader"] for t in running] == [True]
        assert page.locator("#teleop-holding").is_disabled()
        page.click("#teleop-stop")
        wait_until(lambda: status().startswith("stopped: stopped by"), what="stopped again")
        assert errors == []
