"""End to end: the dashboard (app/static) in Debian's headless Chromium against the real server
(uvicorn on a loopback port, the default simulated arms), driven through Playwright.

What the operator sees is compared with what the server says: the tip the page draws (computed
in JS from the joints and the arm's geometry) against GET /state, the newest plotted joint
positions against the telemetry, the emergency stop against GET /arms/{arm}, and refusals in
words next to the control that caused them. The page's test hook is `window.armDashboard`.

Screenshots go to test-output/ (git-ignored); with ARMSERVER_UPDATE_DOCS=1 one of
them is copied to docs/dashboard.png for the README. Never runs `playwright install`: it uses
Debian's chromium, found as tests/_deps.py finds it (the Makefile too), or skips (a failure under
ARMSERVER_STRICT_SKIPS=1, as in CI).
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import shutil
import socket
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import _browser
import pytest
import uvicorn
from _wait import wait_until
from conftest import OPERATOR, make_settings

from app.web.factory import create_app
from app.web.serving import ArmServer
from tests._http import HTTP

pytestmark = pytest.mark.browser

CHROMIUM, CHROMIUM_ARGS = _browser.CHROMIUM, _browser.CHROMIUM_ARGS
ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "test-output"
DOCS_SHOT = ROOT / "docs" / "dashboard.png"
VIEWPORT = {"width": 1440, "height": 1000}

#: The drawn tip may lag the server by one telemetry batch (1/30 s) plus a frame; at rest the
#: only difference is float32 vs float64 rounding.
TIP_TOL_REST_M = 0.002
#: While moving, the drawn tip is judged against the server's tip of the very sample it was
#: drawn from (the page's `drawnLog`): the page's own kinematics on those positions, to the
#: rest tolerance. How far behind the page draws is judged apart: a sample drawn at most this
#: long after it was taken, nine in ten of the samples drawn. A page that fell behind for
#: good (a queue that grows) is far beyond it; a page that shares two busy cores (the serial
#: part in two lanes) was 330 ms behind once (50 mm at the rbe3001's 0.15 m/s), and beside
#: `stress-ng` (`make test-loaded`) drew one sample 2.76 s late and caught up: a stall, which
#: PAGE_STALL_MAX_S bounds for every sample.
PAGE_LAG_MAX_S = 1.0
PAGE_STALL_MAX_S = 5.0
POS_TOL_RAD = 1e-3
#: A reachable target for the rbe3001 (mm), and one a metre away.
TARGET_MM = (120.0, -180.0, 280.0)
FAR_MM = (1000.0, 0.0, 200.0)

sync_api = _browser.sync_api_or_skip()


# ---------------------------------------------------------------- server (restartable, fixed port)


class Server:
    """uvicorn in a thread over `create_app()`; can be stopped and started again on its port."""

    def __init__(self, settings: Any = None) -> None:
        self.settings = settings or make_settings()
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            self.port = s.getsockname()[1]
        self.url = f"http://127.0.0.1:{self.port}"
        self._server: uvicorn.Server | None = None
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        self.app = app = create_app(self.settings)
        config = uvicorn.Config(app, host="127.0.0.1", port=self.port, log_level="warning",
                                lifespan="on")
        self._server = server = ArmServer(config, app)  # the real server's shutdown
        self._thread = threading.Thread(target=server.run, name="dashboard-uvicorn", daemon=True)
        self._thread.start()
        wait_until(lambda: server.started, what="uvicorn to start")
        headers = {"Authorization": f"Bearer {OPERATOR}"} if self.settings.auth_enabled else {}
        wait_until(lambda: HTTP.get(f"{self.url}/api/v1/arms/rbe3001/state", headers=headers,
                                    timeout=2).status_code == 200,
                   what="a sample from the arm")

    def stop(self) -> None:
        if self._server is not None:
            self._server.should_exit = True
            assert self._thread is not None
            self._thread.join(15)
            # a dashboard's open responses (the camera's MJPEG stream) end with the server:
            # uvicorn waits for them before it stops, and the page must not hold it up
            assert not self._thread.is_alive(), "the server did not stop within 15 s"
            self._server = None


@contextlib.contextmanager
def serving(settings: Any = None) -> Iterator[Server]:
    server = Server(settings)
    server.start()
    try:
        yield server
    finally:
        server.stop()


# ---------------------------------------------------------------- fixtures


@pytest.fixture(scope="module")
def server() -> Iterator[Server]:
    OUT.mkdir(exist_ok=True)
    with serving() as srv:
        yield srv


@pytest.fixture(scope="module")
def browser() -> Iterator[Any]:
    with sync_api.sync_playwright() as pw:
        b = pw.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        yield b
        b.close()


@pytest.fixture(scope="module")
def page(server: Server, browser: Any) -> Iterator[Any]:
    pg = browser.new_page(viewport=VIEWPORT)
    errors: list[str] = []
    pg.on("pageerror", lambda e: errors.append(str(e)))
    pg.goto(server.url + "/")
    wait_until(lambda: dash(pg, "rbe3001") and dash(pg, "rbe3001")["lastSeq"] is not None
               and dash(pg, "angler")["lastSeq"] is not None,
               what="telemetry on the page")
    yield pg
    pg.close()
    assert not errors, f"uncaught errors in the page: {errors}"


def dash(pg: Any, arm: str) -> dict[str, Any] | None:
    return pg.evaluate("(a) => window.armDashboard && window.armDashboard.state(a)", arm)


def api(server: Server, method: str, path: str, **kw: Any) -> Any:
    r = HTTP.request(method, f"{server.url}/api/v1{path}", timeout=10, **kw)
    r.raise_for_status()
    return r.json()


def at_rest(server: Server, arm: str = "rbe3001") -> dict[str, Any]:
    def still() -> dict[str, Any] | None:
        st = api(server, "GET", f"/arms/{arm}/state")
        m = st["motion"]
        busy = m is not None and m["status"] in ("queued", "running")
        return None if busy or max(map(abs, st["velocities"])) > 1e-3 else st
    return wait_until(still, what=f"{arm} at rest")


def tip_error(drawn: dict[str, float], tip: dict[str, float]) -> float:
    return math.dist([drawn[k] for k in "xyz"], [tip[k] for k in "xyz"])


def assert_page_matches_server(pg: Any, server: Server) -> None:
    """At rest: the drawn tip and the newest plotted positions equal the server's state."""
    # an arm card out of sight is not drawn: the rbe3001's in view (a click on another arm's
    # card scrolls the page, and the cards are taller since the camera and calibration panels)
    pg.locator("#rbe3001-card").scroll_into_view_if_needed()
    wait_until(lambda: dash(pg, "rbe3001")["visible"], what="the rbe3001 card in sight")
    st = at_rest(server)
    frames = dash(pg, "rbe3001")["frames"]
    # wait for telemetry newer than the state read, then for a frame drawn from it
    wait_until(lambda: dash(pg, "rbe3001")["lastSeq"] > st["seq"], what="newer telemetry")
    wait_until(lambda: dash(pg, "rbe3001")["frames"] > frames + 2, what="frames drawn")
    d = dash(pg, "rbe3001")
    assert tip_error(d["tipDrawn"], st["tip"]) < TIP_TOL_REST_M, (d["tipDrawn"], st["tip"])
    for plotted, actual in zip(d["plotted"]["positions"], st["positions"], strict=True):
        assert plotted is not None and abs(plotted - actual) < POS_TOL_RAD, (d["plotted"], st)


def shot(pg: Any, name: str, full_page: bool = False) -> Path:
    path = OUT / f"dashboard-{name}.png"
    pg.screenshot(path=str(path), full_page=full_page)
    return path


def answering(asked: list[str], yes: bool) -> Any:
    """A page's dialog handler that notes the question in `asked` and answers it."""
    def on_dialog(dialog: Any) -> None:
        asked.append(dialog.message)
        dialog.accept() if yes else dialog.dismiss()
    return on_dialog


# ---------------------------------------------------------------- tests (in order, one page)


def test_page_draws_and_plots_the_telemetry(page: Any, server: Server) -> None:
    d0 = dash(page, "rbe3001")
    assert d0["ws"] == "live"
    time.sleep(1.0)  # the window the counts below are judged over (at least a second)
    # a loaded machine may draw and deliver less in a second: wait for the counts, bounded
    d1 = wait_until(lambda: (d := dash(page, "rbe3001"))["lastSeq"] - d0["lastSeq"] > 50
                    and d["frames"] - d0["frames"] > 3 and d,
                    what="samples and frames")
    # drawn once per animation frame, not once per sample: 500 Hz of samples, ~60 frames a second
    # (the bounds are loose: a loaded two-core test machine runs slower than a laptop)
    samples = d1["lastSeq"] - d0["lastSeq"]
    frames = d1["frames"] - d0["frames"]
    assert samples > 50, "telemetry is not flowing at the arm's rate"
    assert 3 < frames < samples
    # a break in the plotted line is a real gap: lost samples or a stall of the device's clock
    for b in d1["breaks"]:
        assert b["seq"] != b["prevSeq"] + 1 or b["dt"] > 0.19, b
    assert_page_matches_server(page, server)
    # both arms are drawn, and the sensed torques and tip force are plotted
    assert dash(page, "angler")["tipDrawn"] is not None
    assert len(d1["plotted"]["torques"]) == 3 and len(d1["plotted"]["tip_force"]) == 3
    assert "estop clear" in page.inner_text("#rbe3001-estop")
    assert "link up" in page.inner_text("#rbe3001-link")


def test_jog_buttons_move_the_joint(page: Any, server: Server) -> None:
    before = at_rest(server)["positions"]
    page.click("#rbe3001-jog-0-plus")
    page.click("#rbe3001-jog-0-plus")  # a quick second click adds to the first
    want = before[0] + 2 * math.radians(5)
    wait_until(lambda: abs(api(server, "GET", "/arms/rbe3001/state")["positions"][0] - want) < 0.01,
               what=f"base at {want:.3f} rad")
    after = at_rest(server)["positions"]
    assert abs(after[0] - want) < 0.01 and all(abs(a - b) < 0.01 for a, b in
                                               zip(after[1:], before[1:], strict=True))
    assert page.inner_text("#rbe3001-jog-error") == ""
    assert_page_matches_server(page, server)


def test_plan_shows_the_path_then_run_moves_the_arm(page: Any, server: Server) -> None:
    x, y, z = TARGET_MM
    page.fill("#rbe3001-target-x", str(x))
    page.fill("#rbe3001-target-y", str(y))
    page.fill("#rbe3001-target-z", str(z))
    page.select_option("#rbe3001-path", "line")
    page.click("#rbe3001-plan")
    wait_until(lambda: dash(page, "rbe3001")["plannedPath"] > 1, what="planned path drawn")
    assert page.is_enabled("#rbe3001-run")
    assert "straight line" in page.inner_text("#rbe3001-plan-text")
    shot(page, "01-planned")

    hub = server.app.state.services["rbe3001"].hub
    sub = hub.subscribe(backlog=20_000)  # every sample of the move (40 s at 500 Hz), by seq
    page.click("#rbe3001-run")
    # while it moves, the page draws the server's samples, not far behind them: judged from
    # the page's own log of what it drew and when (`drawnLog`), not from reads of the page
    # while it moves (beside two busy cores such reads came too seldom to see it draw)
    moving_seen = False
    readme_shot = None
    try:
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline:
            st = api(server, "GET", "/arms/rbe3001/state")
            if st["motion"] and st["motion"]["status"] == "running":
                moving_seen = True
                if readme_shot is None and st["motion"]["progress"] > 0.45:
                    readme_shot = shot(page, "02-running")  # path ahead, trail behind, plots
            elif moving_seen:
                break
            time.sleep(0.05)
        samples = {s["seq"]: s for s in map(json.loads, sub.take()[0])}
    finally:
        sub.close()
    assert moving_seen, "the motion was never seen running"
    # each entry: the sample's seq, the tip drawn from it, and when (the page's clock: this
    # machine's); those of samples before the subscription are not judged
    drawn = [(seq, {"x": x, "y": y, "z": z}, at)
             for seq, x, y, z, at in dash(page, "rbe3001")["drawnLog"] if seq in samples]
    assert len(drawn) >= 3, f"the page drew {len(drawn)} samples of the move"
    lags = []
    for seq, tip, at in drawn:
        s = samples[seq]
        assert tip_error(tip, s["tip"]) < TIP_TOL_REST_M, (seq, tip, s["tip"])
        lag = at - s["time"]
        assert lag < PAGE_STALL_MAX_S, f"the page drew sample {seq} " \
            f"{lag * 1000:.0f} ms after it was taken"
        lags.append(lag)
    late = sum(lag >= PAGE_LAG_MAX_S for lag in lags)
    assert late * 10 <= len(lags), f"the page drew {late} of {len(lags)} samples " \
        f"{PAGE_LAG_MAX_S * 1000:.0f} ms or more after they were taken (longest " \
        f"{max(lags) * 1000:.0f} ms)"
    st = at_rest(server)
    assert st["motion"]["status"] == "done"
    assert tip_error({"x": x / 1000, "y": y / 1000, "z": z / 1000}, st["tip"]) < 0.005
    assert_page_matches_server(page, server)
    shot(page, "03-after-run")
    if readme_shot is not None and os.environ.get("ARMSERVER_UPDATE_DOCS"):
        DOCS_SHOT.parent.mkdir(exist_ok=True)
        shutil.copyfile(readme_shot, DOCS_SHOT)


def test_unreachable_target_is_refused_in_words(page: Any) -> None:
    x, y, z = FAR_MM
    page.fill("#rbe3001-target-x", str(x))
    page.fill("#rbe3001-target-y", str(y))
    page.fill("#rbe3001-target-z", str(z))
    page.click("#rbe3001-plan")
    err = page.locator("#rbe3001-pose-error")
    wait_until(lambda: err.inner_text() != "", what="error shown")
    assert err.get_attribute("data-code") == "unreachable"
    text = err.inner_text()
    assert text.startswith("Out of reach:") and len(text) > len("Out of reach: ") + 10, text
    assert page.is_disabled("#rbe3001-run")
    shot(page, "04-unreachable")


def test_emergency_stop_latches_shows_and_releases(page: Any, server: Server) -> None:
    arms = [a["name"] for a in api(server, "GET", "/arms")]
    assert {"rbe3001", "angler"} <= set(arms)
    page.click("#estop-button")
    # the page presses each arm's estop at once, one request each: they land one by one
    wait_until(lambda: all(api(server, "GET", f"/arms/{a}")["estop"] for a in arms),
               what="estop latched on the server, on every arm")
    wait_until(lambda: "LATCHED" in page.inner_text("#rbe3001-estop"),
               what="estop shown on the arm")
    assert "rbe3001" in page.inner_text("#estop-status")
    # a move while latched is refused, in words, next to the control
    page.click("#rbe3001-jog-1-minus")
    err = page.locator("#rbe3001-jog-error")
    wait_until(lambda: err.get_attribute("data-code") == "estop_latched",
               what="estop refusal shown")
    assert "Emergency stop latched" in err.inner_text()
    shot(page, "05-estop")

    page.click("#estop-release")
    wait_until(lambda: not any(api(server, "GET", f"/arms/{a}")["estop"] for a in arms),
               what="estop released on every arm")
    wait_until(lambda: "estop clear" in page.inner_text("#rbe3001-estop"), what="release shown")
    assert page.inner_text("#estop-status") == "not latched"
    # the estop panel is fixed: still on screen when the page is scrolled to the end
    page.mouse.wheel(0, 5000)
    wait_until(lambda: page.evaluate("window.scrollY") > 0, what="the page scrolled")
    box = page.locator("#estop-button").bounding_box()
    assert box is not None and 0 <= box["y"] < VIEWPORT["height"]


def test_faults_and_homing_shown_reboot_and_home_clear_them(page: Any, server: Server) -> None:
    """A servo fault injected in the simulator appears on the page with its advice and a reboot
    button; reboot clears it and leaves x not homed; Home makes every joint homed again."""
    panel = page.locator("#angler-faults-panel")
    assert panel.is_visible() and page.locator("#angler-faults").get_attribute("data-count") == "0"
    assert page.locator("#rbe3001-tare").count() == 1  # the rbe3001 senses force
    bus = server.app.state.services["angler"].driver.link.device
    bus.inject_hardware_error(2, "overload")  # servo 2 drives x
    wait_until(lambda: page.locator("#angler-faults").get_attribute("data-count") == "1",
               what="fault shown")
    text = page.inner_text("#angler-faults")
    assert "Servo 2 (x): overload" in text and "reboot" in text
    # a move is refused in words while the fault stands
    page.click("#angler-jog-2-plus")
    err = page.locator("#angler-jog-error")
    wait_until(lambda: err.get_attribute("data-code") == "fault", what="fault refusal shown")
    assert "Servo fault" in err.inner_text()
    shot(page, "07-fault")
    page.click("#angler-reboot-2")
    wait_until(lambda: page.locator("#angler-faults").get_attribute("data-count") == "0",
               what="fault cleared")
    wait_until(lambda: page.locator("#angler-homed").get_attribute("data-homed")
               == "[false,true,true,true]",
               what="x not homed after the reboot")
    assert api(server, "GET", "/arms/angler")["homed"] == [False, True, True, True]
    assert "x ✗" in page.inner_text("#angler-homed")
    page.click("#angler-home")
    wait_until(lambda: page.locator("#angler-homed").get_attribute("data-homed")
               == "[true,true,true,true]",
               what="homed shown")
    assert api(server, "GET", "/arms/angler")["homed"] == [True] * 4
    assert page.inner_text("#angler-faults-error") == ""
    shot(page, "08-homed")


def test_survives_a_server_restart(page: Any, server: Server) -> None:
    gaps = dash(page, "rbe3001")["gaps"]
    server.stop()
    wait_until(lambda: dash(page, "rbe3001")["ws"] == "reconnecting", what="reconnecting shown")
    assert "reconnecting" in page.inner_text("#rbe3001-ws")
    time.sleep(1.0)  # not before an assert: a second of the reconnecting page, for the shot
    shot(page, "06-reconnecting")
    server.start()
    wait_until(lambda: dash(page, "rbe3001")["ws"] == "live", what="live again")
    wait_until(lambda: dash(page, "rbe3001")["gaps"] > gaps, what="the gap is marked in the plots")
    assert_page_matches_server(page, server)


def test_asks_for_a_token_when_the_server_needs_one(browser: Any) -> None:
    with serving(make_settings(operator_tokens=OPERATOR)) as srv:
        pg = browser.new_page(viewport=VIEWPORT)
        try:
            pg.goto(srv.url + "/")
            pg.wait_for_selector("#token-dialog[open]", timeout=10_000)
            pg.fill("#token-input", OPERATOR)
            pg.click("#token-form button[type=submit]")
            wait_until(lambda: (dash(pg, "rbe3001") or {}).get("ws") == "live",
                       what="live with token")
            assert pg.evaluate("sessionStorage.getItem('armserver.token')") == OPERATOR
            # an operator request from the page carries the token
            with pg.expect_response(lambda r: r.url.endswith("/arms/rbe3001/stop")) as answer:
                pg.click("#rbe3001-stop")
            assert answer.value.status == 200, answer.value.status
            assert pg.inner_text("#rbe3001-stop-error") == ""
        finally:
            pg.close()


def test_a_refusal_of_a_request_sent_before_the_token_does_not_ask_again(browser: Any) -> None:
    """Requests that left without a token and are refused after one was entered are sent again
    with it; the form stays closed. (A late refusal once opened the form again over the page,
    and the form took the next click: a CI failure.)"""
    with serving(make_settings(operator_tokens=OPERATOR)) as srv:
        pg = browser.new_page(viewport=VIEWPORT)
        held: list[Any] = []

        def hold_tokenless(route: Any) -> None:
            if route.request.headers.get("authorization") is None:
                held.append(route)  # answered (401) only once the token is in
            else:
                route.continue_()

        try:
            pg.route("**/api/v1/**", hold_tokenless)
            pg.goto(srv.url + "/")
            wait_until(lambda: pg.evaluate("1") == 1
                       and any(r.request.url.endswith("/api/v1/arms") for r in held),
                       what="the page's first GET /arms held")
            assert not pg.evaluate("document.querySelector('#token-dialog').open")
            pg.click("#token-button")
            pg.fill("#token-input", OPERATOR)
            pg.click("#token-form button[type=submit]")
            n_held = len(held)
            with pg.expect_response(lambda r: r.url.endswith("/api/v1/arms")
                                    and r.request.headers.get("authorization")
                                    == f"Bearer {OPERATOR}", timeout=10_000) as again:
                for route in held[:n_held]:
                    route.continue_()  # each refused by the server: it carries no token
            assert again.value.status == 200
            wait_until(lambda: (dash(pg, "rbe3001") or {}).get("ws") == "live",
                       what="live with token")
            assert len(held) == n_held  # nothing was sent without the token since
            assert not pg.evaluate("document.querySelector('#token-dialog').open")
            with pg.expect_response(lambda r: r.url.endswith("/arms/rbe3001/stop")) as answer:
                pg.click("#rbe3001-stop")
            assert answer.value.status == 200, answer.value.status
        finally:
            pg.close()


def test_safety_zones_are_drawn_and_the_speed_slider_changes_the_override(browser: Any,
                                                                          tmp_path: Path) -> None:
    with serving(make_settings(data_dir=str(tmp_path))) as srv:
        zone = {"name": "camera", "min": {"x": 0.15, "y": -0.25, "z": 0.35},
                "max": {"x": 0.25, "y": -0.15, "z": 0.45}}
        api(srv, "PUT", "/arms/rbe3001/safety", json={"zones": [zone], "floor_z": -0.05})
        pg = browser.new_page(viewport=VIEWPORT)
        errors: list[str] = []
        pg.on("pageerror", lambda e: errors.append(str(e)))
        try:
            pg.goto(srv.url + "/")

            def safety() -> dict[str, Any] | None:
                return pg.evaluate("(a) => window.armDashboard && window.armDashboard.safety(a)",
                                   "rbe3001")

            wait_until(lambda: (safety() or {}).get("drawn", {}).get("side") == 1,
                       what="the zone drawn in the side view")
            st = safety()
            assert st is not None and st["zones"] == ["camera"] and st["floor_z"] == -0.05
            assert st["drawn"] == {"top": 1, "side": 1, "floor": True}
            assert not st["sliderDisabled"]  # an open server: everyone may change it
            assert "1 zone, floor -50 mm, speed 100%" in pg.inner_text("#rbe3001-safety-summary")
            # the slider: the instructor sets the override, the server takes it
            pg.eval_on_selector("#rbe3001-speed-override",
                                "(el) => { el.value = '0.5'; "
                                "el.dispatchEvent(new Event('change')); }")
            wait_until(lambda: api(srv, "GET", "/arms/rbe3001/safety")["speed_override"] == 0.5,
                       what="override set on the server")
            wait_until(lambda: "speed 50%" in pg.inner_text("#rbe3001-safety-summary"),
                       what="override shown")
            # a change from elsewhere (a "safety" event on the socket) reaches the page
            api(srv, "PUT", "/arms/rbe3001/safety", json={"zones": []})
            wait_until(lambda: (safety() or {}).get("zones") == [],
                       what="zones cleared on the page")
            wait_until(lambda: (safety() or {})["drawn"]["top"] == 0, what="zone no longer drawn")
            # a move into a zone is refused in words next to the control
            api(srv, "PUT", "/arms/rbe3001/safety", json={"zones": [zone]})
            pg.fill("#rbe3001-target-x", "200")
            pg.fill("#rbe3001-target-y", "-200")
            pg.fill("#rbe3001-target-z", "400")
            pg.select_option("#rbe3001-path", "line")
            pg.click("#rbe3001-plan")
            err = pg.locator("#rbe3001-pose-error")
            wait_until(lambda: err.get_attribute("data-code") == "keep_out", what="refusal shown")
            assert err.inner_text().startswith("Keep-out zone:")
            assert "'camera'" in err.inner_text() and "tip" in err.inner_text()
            shot(pg, "07-safety")
        finally:
            pg.close()
        assert not errors, f"uncaught errors in the page: {errors}"


def test_rebooting_a_servo_whose_joint_falls_asks_whether_its_load_is_supported(
        page: Any, server: Server) -> None:
    """z's winch falls without torque and a reboot switches the torque off: with the servo
    holding torque (an input-voltage alert does not shut it down) the reboot button's first
    answer is 409 `in_use`; the page asks, and only a yes reboots it, saying so."""
    bus = server.app.state.services["angler"].driver.link.device
    bus.inject_hardware_error(4, "input_voltage")
    wait_until(lambda: page.locator("#angler-faults").get_attribute("data-count") == "1",
               what="fault shown")
    assert bus.servo(4).torque  # not in the Shutdown mask: it still holds
    asked: list[str] = []

    page.once("dialog", answering(asked, False))
    page.click("#angler-reboot-4")
    err = page.locator("#angler-faults-error")
    wait_until(lambda: err.get_attribute("data-code") == "in_use", what="the refusal shown")
    wait_until(lambda: len(asked) == 1, what="the question asked")
    assert "load_supported" in asked[0] and "z falls" in asked[0], asked
    assert page.locator("#angler-faults").get_attribute("data-count") == "1"
    assert api(server, "GET", "/arms/angler")["homed"] == [True] * 4  # no REBOOT went out
    page.once("dialog", answering(asked, True))
    page.click("#angler-reboot-4")
    wait_until(lambda: page.locator("#angler-faults").get_attribute("data-count") == "0",
               what="fault cleared")
    assert len(asked) == 2 and bus.servo(4).torque
    assert api(server, "GET", "/arms/angler")["homed"] == [True, True, True, False]
    # (the samples can show the fault cleared before the page has the POST's answer)
    wait_until(lambda: "load supported" in page.inner_text("#angler-faults-note"),
               what="the reboot's note")
    page.click("#angler-home")
    wait_until(lambda: api(server, "GET", "/arms/angler")["homed"] == [True] * 4,
               what="homed again")


def test_torque_off_by_hand_asks_for_the_winch_then_on_again_holding(
        page: Any, server: Server) -> None:
    """The angler's panel switches the joints' torque off (PUT /arms/angler/torque): z's winch
    falls without torque, so the first answer is 409 `in_use` and the page asks; only a yes
    switches it off, and Torque on switches it on again. The rbe3001's firmware has no torque
    switch: no buttons. The world's hand holds the simulated arm meanwhile, so nothing falls
    and the module's other tests find the angler where it was."""
    bus = server.app.state.services["angler"].driver.link.device
    servos = [bus.servo(i) for i in (1, 2, 3, 4)]
    assert page.locator("#rbe3001-torque-off").count() == 0
    api(server, "PUT", "/arms/angler/world/hand", json={"wait": True})  # hold where it is
    asked: list[str] = []

    try:
        page.once("dialog", answering(asked, False))
        page.click("#angler-torque-off")
        err = page.locator("#angler-faults-error")
        # (a wait that calls the page: the sync API dispatches the dialog only then)
        wait_until(lambda: err.get_attribute("data-code") == "in_use", what="the refusal shown")
        wait_until(lambda: page.evaluate("1") and len(asked) == 1, what="the question asked")
        assert "load_supported" in asked[0] and "z falls" in asked[0], asked
        assert all(sv.torque for sv in servos)  # a no switched nothing
        page.once("dialog", answering(asked, True))
        page.click("#angler-torque-off")
        wait_until(lambda: page.locator("#angler-torque").get_attribute("data-on") == "false",
                   what="torque off shown")
        assert not any(sv.torque for sv in servos) and len(asked) == 2
        assert "load supported" in page.inner_text("#angler-faults-note")
        page.locator("#angler-torque").scroll_into_view_if_needed()
        shot(page, "09-torque-off")
        page.click("#angler-torque-on")
        wait_until(lambda: page.locator("#angler-torque").get_attribute("data-on") == "true",
                   what="torque on shown")
        assert all(sv.torque for sv in servos)
        assert page.inner_text("#angler-faults-error") == ""
        # another client's switch shows too (the `torque` event, then the arm's detail)
        api(server, "PUT", "/arms/angler/torque", json={"on": False, "load_supported": True})
        wait_until(lambda: page.locator("#angler-torque").get_attribute("data-on") == "false",
                   what="another client's torque off shown")
        assert "theta3" in page.inner_text("#angler-torque")
        api(server, "PUT", "/arms/angler/torque", json={"on": True})
        wait_until(lambda: page.locator("#angler-torque").get_attribute("data-on") == "true",
                   what="another client's torque on shown")
    finally:
        api(server, "PUT", "/arms/angler/torque", json={"on": True})
        HTTP.delete(f"{server.url}/api/v1/arms/angler/world/hand", timeout=10)
