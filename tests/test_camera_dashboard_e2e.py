"""End to end: the dashboard's camera panel (app/web/static/camera.js) in headless Chromium
against a real server on the simulated arms: the simulated camera's stream is drawn with its
detections, and a click on the calibrated picture moves the arm's tip above that point of the
table through the move route."""

from __future__ import annotations

from typing import Any

import _deps
import httpx
import numpy as np
import pytest
from _wait import wait_until
from conftest import serve_live

from app.sim.camera import SimView

pytestmark = pytest.mark.browser

CHROMIUM = _deps.CHROMIUM
CHROMIUM_ARGS = ["--headless=new", "--no-sandbox", "--disable-gpu", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update"]
if CHROMIUM is None:
    pytest.skip(_deps.missing_message("chromium") + "; the dashboard test needs it",
                allow_module_level=True)
sync_api = pytest.importorskip("playwright.sync_api", reason="the playwright package is missing")

ARM = "rbe3001"
#: The table point clicked, base frame (m), and how close the tip must come above it.
TARGET = (0.16, 0.05)
TOL_M = 0.005


def test_camera_panel_stream_detections_and_click_to_reach() -> None:
    with serve_live() as live, sync_api.sync_playwright() as pw:
        svc = live.app.state.services[ARM]
        truth = SimView.default_for(svc.profile, 640, 480).table_homography()
        xy = np.array([[0.08, -0.15], [0.08, 0.15], [0.28, 0.15], [0.28, -0.15]])
        q = np.c_[xy, np.ones(4)] @ truth.T
        uv = q[:, :2] / q[:, 2:3]
        body = {"points": [{"pixel": {"u": float(u), "v": float(v)},
                            "position": {"x": float(x), "y": float(y), "z": 0.0}}
                           for (u, v), (x, y) in zip(uv, xy, strict=True)]}
        r = httpx.post(f"{live.url}/api/v1/cameras/{ARM}/calibration", json=body)
        assert r.status_code == 200, r.text
        browser = pw.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        page = browser.new_page(viewport={"width": 1440, "height": 1000})
        errors: list[str] = []
        page.on("pageerror", lambda e: errors.append(str(e)))
        page.goto(live.url + "/")

        def state() -> Any:
            return page.evaluate(f"window.armCameras && window.armCameras.state('{ARM}')")
        wait_until(lambda: (state() or {}).get("calibrated"), what="the panel, calibrated")
        wait_until(lambda: len(state()["detections"]) == len(svc.world.scene().objects),
                   what="the world's objects detected on the page")
        canvas = page.locator(f"#camera-{ARM}-view")
        box = canvas.bounding_box()
        target = np.array([*TARGET, 1.0]) @ truth.T
        u, v = target[:2] / target[2]
        page.mouse.click(box["x"] + u * box["width"] / 640, box["y"] + v * box["height"] / 480)

        def tip_error() -> float:
            tip = svc.state()["tip"]
            return float(np.hypot(tip["x"] - TARGET[0], tip["y"] - TARGET[1])
                         + abs(tip["z"] - 0.05))
        wait_until(lambda: tip_error() < TOL_M, timeout=20, what="the tip above the clicked point")
        assert errors == []
        browser.close()
