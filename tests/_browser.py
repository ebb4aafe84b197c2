"""What the dashboard's browser tests share: Chromium (found by tests/_deps.py, as the Makefile
finds it) and its flags, playwright's sync API, the skip when either is missing (a failure
under ARMSERVER_STRICT_SKIPS: `make test` installs both) and a page to test. Their waits are
tests/_wait.py's `wait_until`."""

from __future__ import annotations

from types import ModuleType
from typing import Any

import _deps
import pytest

CHROMIUM = _deps.CHROMIUM
#: Headless, no sandbox (CI runs as root), nothing of Chromium's own on the network.
CHROMIUM_ARGS = ["--headless=new", "--no-sandbox", "--disable-gpu", "--disable-quic",
                 "--no-first-run", "--disable-background-networking",
                 "--disable-component-update", "--disable-sync"]


def sync_api_or_skip() -> ModuleType:
    """playwright.sync_api; called at a test module's import, skips the module without
    Chromium or playwright."""
    if CHROMIUM is None:
        pytest.skip(_deps.missing_message("chromium") + "; the dashboard test needs it",
                    allow_module_level=True)
    return pytest.importorskip("playwright.sync_api",
                               reason="the playwright package is missing")


def open_page(pw: Any, url: str, viewport: dict[str, int] | None = None) -> tuple[Any, list[str]]:
    """A new Chromium page (of the playwright `pw`, which closes it as it ends) on `url`, and
    the list its uncaught errors go to."""
    browser = pw.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
    page = browser.new_page(viewport=viewport) if viewport else browser.new_page()
    errors: list[str] = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.goto(url)
    return page, errors
