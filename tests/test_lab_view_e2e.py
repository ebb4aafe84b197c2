"""End to end: the lab view (app/web/static/lab.html + lab.js, its own MQTT-over-WebSocket client)
in Debian's headless Chromium, reading a real Mosquitto's websockets listener that two real
arm servers publish to (different prefixes under one root). What the tiles show is compared
with what the servers say: every arm present, online, the joints of /state, the emergency stop,
and an arm server that goes away shown offline. Test hook: `window.labView`."""

from __future__ import annotations

import contextlib
import math
from pathlib import Path
from typing import Any

import pytest
from _deps import missing_message
from _mosquitto import MOSQUITTO, Broker
from _wait import wait_until
from conftest import make_settings, serve_live
from test_dashboard_e2e import CHROMIUM, CHROMIUM_ARGS, OUT, sync_api

from tests._http import HTTP

pytestmark = pytest.mark.browser

if MOSQUITTO is None:
    pytest.skip(missing_message("mosquitto"), allow_module_level=True)


def tiles(pg: Any) -> dict[str, Any]:
    return pg.evaluate("() => window.labView ? window.labView.tiles() : {}")


def test_lab_view_shows_every_arm_of_every_server(tmp_path: Path) -> None:
    broker = Broker(tmp_path, websockets=True).start()
    cfg = tmp_path / "bench2.toml"
    cfg.write_text('[[arms]]\nprofile = "rbe3001"\nname = "lab"\ncount = 2\n')
    a_settings = make_settings(mqtt_url=broker.url, mqtt_rate=20.0)
    b_settings = make_settings(mqtt_url=broker.url, mqtt_prefix="armserver/bench2",
                               config=str(cfg), mqtt_rate=20.0)
    want = {"armserver/rbe3001", "armserver/angler", "armserver/bench2/lab-1",
            "armserver/bench2/lab-2"}
    with contextlib.ExitStack() as stack:
        stack.callback(broker.stop)
        a = stack.enter_context(serve_live(a_settings))
        b_ctx = serve_live(b_settings)
        b = b_ctx.__enter__()
        b_open = [True]

        def stop_b() -> None:
            if b_open[0]:
                b_open[0] = False
                b_ctx.__exit__(None, None, None)

        stack.callback(stop_b)
        pw = stack.enter_context(sync_api.sync_playwright())
        browser = pw.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        stack.callback(browser.close)
        pg = browser.new_page(viewport={"width": 1280, "height": 800})
        errors: list[str] = []
        pg.on("pageerror", lambda e: errors.append(str(e)))
        pg.goto(f"{a.url}/lab.html?broker=ws://127.0.0.1:{broker.ws_port}")

        wait_until(lambda: want <= {k for k, t in tiles(pg).items()
                                    if t["online"] and t["sample"]},
                   what="all four arms online")
        assert pg.evaluate("() => window.labView.broker") == "up"
        assert set(tiles(pg)) == want, "a tile that is no arm"

        # the joints shown are the server's (the arm is at rest)
        state = HTTP.get(f"{b.url}/api/v1/arms/lab-2/state", timeout=5).json()
        shown = tiles(pg)["armserver/bench2/lab-2"]["sample"]
        assert all(math.isclose(p, q, abs_tol=1e-6)
                   for p, q in zip(shown["positions"], state["positions"], strict=True))
        assert pg.locator('[data-key="armserver/bench2/lab-2"] .tip').inner_text().endswith("mm")

        # the emergency stop of one arm shows on its tile, and only there
        HTTP.post(f"{a.url}/api/v1/arms/angler/estop", timeout=5).raise_for_status()
        wait_until(lambda: pg.locator('[data-key="armserver/angler"] .estop').count() == 1,
                   what="ESTOP on the angler tile")
        assert pg.locator('[data-key="armserver/rbe3001"] .estop').count() == 0
        # the event comes on its own topic, after the hold was commanded: the latched sample
        # (the badge above) may come first
        wait_until(lambda: (tiles(pg)["armserver/angler"]["lastEvent"] or {}).get("event")
                   == "estop", what="the estop event on the angler tile")
        OUT.mkdir(exist_ok=True)
        pg.screenshot(path=str(OUT / "lab-view.png"))
        HTTP.delete(f"{a.url}/api/v1/arms/angler/estop", timeout=5).raise_for_status()

        # server B goes away: its arms go offline, server A's stay online
        stop_b()
        wait_until(lambda: not tiles(pg)["armserver/bench2/lab-1"]["online"],
                   what="bench2 arms offline")
        t = tiles(pg)
        assert not t["armserver/bench2/lab-2"]["online"]
        assert t["armserver/rbe3001"]["online"] and t["armserver/angler"]["online"]
        assert pg.locator('[data-key="armserver/bench2/lab-1"] .online').inner_text() == "offline"
        assert not errors, f"uncaught errors in the page: {errors}"

