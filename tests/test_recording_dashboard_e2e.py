"""End to end: the dashboard's recording bar (app/web/static/recording.js) in headless Chromium
against a real server on the simulated arms: Record starts an episode, the bar shows its
length, Stop writes it and the episode count goes up."""

from __future__ import annotations

import re

import _browser
import pytest
from _wait import wait_until
from conftest import serve_live

from tests._http import HTTP

pytestmark = pytest.mark.browser

sync_api = _browser.sync_api_or_skip()


def test_record_and_stop_from_the_bar() -> None:
    with serve_live() as live, sync_api.sync_playwright() as pw:
        r = HTTP.post(f"{live.url}/api/v1/recordings",
                      json={"name": "bar", "arms": ["rbe3001"], "fps": 10})
        assert r.status_code == 201, r.text
        page, errors = _browser.open_page(pw, live.url + "/")

        def status() -> str:
            return str(page.locator("#recording-status").text_content() or "")
        wait_until(lambda: status() == "0 episodes", what="the bar with the dataset")
        page.click("#recording-record")
        wait_until(lambda: re.search(r"recording (\d+\.\d) s", status()) and
                   float(re.search(r"recording (\d+\.\d) s", status()).group(1)) >= 0.5,
                   what="the episode's length shown")
        assert page.locator("#recording-record").text_content() == "■ Stop"
        page.click("#recording-record")
        wait_until(lambda: status() == "1 episode", what="the episode written")
        assert HTTP.get(f"{live.url}/api/v1/recordings/bar").json()["episodes"] == 1
        assert errors == []
