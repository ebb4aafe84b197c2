"""End to end: the dashboard's camera panel (app/web/static/camera.js) in headless Chromium
against a real server on the simulated arms: the simulated camera's stream is drawn with its
detections; the camera is calibrated in the panel (the tip moved onto four table points, each
clicked in the picture, then Fit); and a click on the picture moves the arm's tip above that
point of the table through the move route."""

from __future__ import annotations

from typing import Any

import _browser
import numpy as np
import pytest
from _wait import wait_until
from conftest import serve_live

from app.sim.camera import SimView
from tests._http import HTTP

pytestmark = pytest.mark.browser

sync_api = _browser.sync_api_or_skip()

ARM = "rbe3001"
#: Where the tip is put for the calibration: four table points (m), at a height above the
#: table (the simulated table is at z = 0; the calibration's plane is the tip's).
MARKS = [(0.12, -0.12), (0.12, 0.12), (0.25, 0.10), (0.25, -0.10)]
MARK_Z = 0.03
#: The table point clicked to reach, and how close the tip must come above it, m.
TARGET = (0.16, 0.05)
TOL_M = 0.005


def test_camera_panel_calibrate_by_clicks_then_click_to_reach() -> None:
    with serve_live() as live, sync_api.sync_playwright() as pw:
        svc = live.app.state.services[ARM]
        view = SimView.default_for(svc.profile, 640, 480)
        page, errors = _browser.open_page(pw, live.url + "/", {"width": 1440, "height": 1000})

        def state() -> Any:
            return page.evaluate(f"window.armCameras && window.armCameras.state('{ARM}')")
        wait_until(lambda: state() is not None and state()["status"] == "not calibrated",
                   what="the camera panel")
        wait_until(lambda: len(state()["detections"]) == len(svc.world.scene().objects),
                   what="the world's objects detected on the page")
        canvas = page.locator(f"#camera-{ARM}-view")

        def click(u: float, v: float) -> None:  # a pixel of the picture, however it is shown
            canvas.scroll_into_view_if_needed()
            box = canvas.bounding_box()
            canvas.click(position={"x": u * box["width"] / 640, "y": v * box["height"] / 480})

        page.click(f"#camera-{ARM}-calibrate")
        for k, (x, y) in enumerate(MARKS):
            r = HTTP.post(f"{live.url}/api/v1/arms/{ARM}/move/pose",
                          json={"x": x, "y": y, "z": MARK_Z, "wait": True}, timeout=60)
            assert r.status_code == 200 and r.json()["status"] == "done", r.text

            def there(x: float = x, y: float = y) -> Any:
                tip, now = state()["tip"], svc.state()["tip"]
                near = tip is not None and np.hypot(tip["x"] - x, tip["y"] - y) < 0.01
                same = near and all(abs(tip[a] - now[a]) < 5e-4 for a in "xyz")
                return tip if same else None
            def seen(k: int = k) -> str:  # at the deadline: what the page had
                dash = page.evaluate(f"window.armDashboard.state('{ARM}')")
                link = {key: dash.get(key) for key in ("ws", "lastSeq", "gaps", "dropped")}
                return (f"the page's tip at mark {k + 1}: the panel's {state()['tip']}, the "
                        f"server's {svc.state()['tip']} (seq {svc.hub.latest['seq']}), the "
                        f"page's telemetry {link}")
            tip = wait_until(there, what=seen)
            # the marker is where the tip is: click its pixel
            u, v = view.project(np.array([tip["x"], tip["y"], tip["z"]]))
            click(float(u), float(v))
            wait_until(lambda k=k: state()["points"] == k + 1)
        page.click(f"#camera-{ARM}-fit")
        wait_until(lambda: state()["calibrated"], what="the panel's fit")
        cal = HTTP.get(f"{live.url}/api/v1/cameras/{ARM}/calibration").json()
        assert cal["points"] == 4 and abs(cal["z"] - MARK_Z) < 0.003
        # the fitted plane's map agrees with the simulated camera's own, to a few pixels
        fitted = np.array(cal["homography"])
        truth = view.table_homography(cal["z"])
        grid = np.array([[0.14, -0.08, 1.0], [0.2, 0.0, 1.0], [0.22, 0.08, 1.0]])
        a, b = grid @ fitted.T, grid @ truth.T
        assert np.abs(a[:, :2] / a[:, 2:] - b[:, :2] / b[:, 2:]).max() < 3.0

        # click-to-reach: the tip goes above the clicked table point
        target = np.array([*TARGET, 1.0]) @ truth.T
        click(float(target[0] / target[2]), float(target[1] / target[2]))

        def tip_error() -> float:
            tip = svc.state()["tip"]
            return float(np.hypot(tip["x"] - TARGET[0], tip["y"] - TARGET[1])
                         + abs(tip["z"] - (cal["z"] + 0.05)))
        wait_until(lambda: tip_error() < TOL_M, timeout=20, what="the tip above the clicked point")
        assert errors == [] and state()["error"] == ""
