"""End to end: the dashboard's servo set-up panel (app/web/static/setup.js) walks through the
factory state on the practice bus, in Debian's headless Chromium against a real server: start
the practice bus, scan (one factory servo), assign it as the angler's x and see it verified,
plug in the next servo and set it up as y; two new servos at once are refused in words
(several_servos)."""

from __future__ import annotations

import json
from typing import Any

import _browser
import pytest
from _wait import wait_until
from conftest import serve_live

pytestmark = pytest.mark.browser


sync_api = _browser.sync_api_or_skip()


#: A bound, not a time, for a wait that spans an assignment: its verifying scan of the bus took
#: over 20 s beside the parallel part's other workers on two cores (10 s for the whole test
#: alone); the file now runs in the serial part (tests/conftest.py SERIAL_FILES). The other
#: waits have `_wait.TIMEOUT_S`. A wait that ends says what the panel said.
ASSIGN_S = 60.0


def _panel(page: Any, what: str) -> Any:
    """`what` for a wait on the panel: at its deadline, with what the panel found and said."""
    return lambda: (f"{what}; the panel found "
                    f"{page.locator('#setup-found').get_attribute('data-servos')!r}, said "
                    f"{page.locator('#setup-said').inner_text()!r}, error "
                    f"{page.locator('#setup-error').inner_text()!r}")


def _assigned(page: Any, cond: Any, what: str) -> None:
    """Wait up to ASSIGN_S for an assignment's outcome."""
    wait_until(cond, what=_panel(page, what), timeout=ASSIGN_S)


def test_the_panel_walks_factory_servos_through_scan_and_assign() -> None:
    with serve_live() as live, sync_api.sync_playwright() as pw:
        page, errors = _browser.open_page(pw, live.url + "/", {"width": 1440, "height": 1000})
        page.click("#setup-details summary")
        wait_until(lambda: "angler" in page.locator("#setup-profile").inner_text(),
                   what="the profiles listed")
        page.select_option("#setup-profile", "angler")
        page.fill("#setup-rates", "57600, 1000000")  # the rates the servos here run at
        page.click("#setup-practice-start")
        wait_until(lambda: page.locator("#setup-port").input_value().endswith("ttyDXL"),
                   what="the practice bus's port filled in")
        assert "ID 1 @ 57,600 bps" in page.locator("#setup-practice").inner_text()
        found = page.locator("#setup-found")
        page.click("#setup-scan")
        wait_until(lambda: found.get_attribute("data-servos") == "[[1,57600,null]]",
                   what=_panel(page, "the factory servo found"))
        steps = page.locator("#setup-steps").inner_text()
        assert "Connect only the servo for joint x" in steps and "factory state" in steps
        assert page.locator("#setup-joint").input_value() == "x"

        page.click("#setup-assign")
        _assigned(page, lambda: found.get_attribute("data-servos") == '[[2,1000000,"x"]]',
                  "x set up and verified by the scan after it")
        assert "joint x: set up and verified: ID 2 at 1,000,000 bps" in \
            page.locator("#setup-said").inner_text()
        assert page.locator("#setup-steps").get_attribute("data-next") == "y"
        assert page.locator("#setup-joint").input_value() == "y"

        # the next servo, alone with x's: y
        page.click("#setup-practice-plug")
        wait_until(lambda: "ID 1 @ 57,600 bps" in page.locator("#setup-practice").inner_text(),
                   what="one more factory servo")
        page.click("#setup-scan")
        wait_until(lambda: len(json.loads(found.get_attribute("data-servos") or "[]")) == 2,
                   what=_panel(page, "two servos found"))
        page.click("#setup-assign")
        _assigned(page, lambda: page.locator("#setup-steps").get_attribute("data-next") == "theta3",
                  "y set up; theta3 next")
        assert sorted(json.loads(found.get_attribute("data-servos") or "[]")) == \
            [[1, 1_000_000, "y"], [2, 1_000_000, "x"]]

        # two new servos at once: refused in words, nothing written
        page.click("#setup-practice-plug")
        wait_until(lambda: page.locator("#setup-practice").inner_text().count("57,600") == 1,
                   what="a third servo")
        page.click("#setup-practice-plug")
        wait_until(lambda: page.locator("#setup-practice").inner_text().count("57,600") == 2,
                   what="a fourth servo")
        page.click("#setup-assign")
        error = page.locator("#setup-error")
        wait_until(lambda: error.get_attribute("data-code") == "several_servos",
                   what=_panel(page, "the refusal shown"))
        assert "connect one servo at a time" in error.inner_text()
        state = page.evaluate("() => window.armServoSetup.state()")
        assert state["errorCode"] == "several_servos"
        assert not errors, f"uncaught errors in the page: {errors}"
