"""Issue 13's narrow interfaces: no import cycle between motion and the service or between the
console entry point and the app factory; the safety guard holds the estop latch and the checks;
the Driver contract carries what motion and the service call; samples get their estop and
motion fields from the arm's hub, in the wire order of the Sample schema."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from _wait import new_samples, wait_for

from app import schemas as s
from app.arms.loading import load_profile
from app.arms.rbe3001.driver import Rbe3001Driver
from app.config import homed_at_start
from app.device.driver import Driver
from app.device.factory import make_sim_device
from app.errors import EstopLatched, InvalidRequest, JointLimit, NotSupported
from app.links.sim import SimLink
from app.safety.guard import SafetyGuard
from app.service import ArmService
from app.telemetry.arm_hub import ArmHub
from app.telemetry.hub import TelemetryHub

APP = Path(__file__).resolve().parents[1] / "app"

#: The Sample schema's field order on the wire (API.md "Telemetry").
SAMPLE_KEYS = ["seq", "time", "positions", "velocities", "torques", "tip", "tip_velocity",
               "tip_force", "gripper", "motion", "estop", "link", "stale", "faults", "homed",
               "calibrated"]


def _imports(path: Path, top_level_only: bool) -> set[str]:
    tree = ast.parse(path.read_text())
    nodes = tree.body if top_level_only else list(ast.walk(tree))
    out: set[str] = set()
    for node in nodes:
        if isinstance(node, ast.If):  # `if TYPE_CHECKING:` imports count as imports too
            nodes.extend(node.body)
        if isinstance(node, ast.ImportFrom) and node.module:
            out.add(node.module)
            out.update(f"{node.module}.{a.name}" for a in node.names)
        elif isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
    return out


def test_motion_and_the_guard_do_not_import_the_service() -> None:
    files = [*(APP / "motion").glob("*.py"), *(APP / "safety").glob("*.py"),
             APP / "telemetry" / "arm_hub.py"]
    assert len(files) >= 4
    for path in files:
        assert "app.service" not in _imports(path, top_level_only=False), path.name


def test_the_app_factory_does_not_import_the_cli_and_the_cli_imports_it_only_when_serving() -> None:
    assert not any(m.startswith("app.cli") for m in _imports(APP / "web" / "factory.py", False))
    assert "app.web.factory" not in _imports(APP / "cli.py", top_level_only=True)
    code = "import sys, app.cli; print('app.web.factory' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=60, check=True)
    assert out.stdout.strip() == "False"


def test_the_console_entry_point_is_the_cli() -> None:
    text = (APP.parent / "pyproject.toml").read_text()
    assert 'armserver = "app.cli:run"' in text
    out = subprocess.run([sys.executable, "-c", "from app.cli import run; run()", "--help"],
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 0 and "serve" in out.stdout


def test_the_driver_contract_names_what_motion_calls() -> None:
    for name in ("command_joints", "set_gripper", "settle_state", "reboot"):
        assert hasattr(Driver, name), name
    assert {"command_joints", "set_gripper"} <= Driver.__abstractmethods__


async def test_a_device_without_reboot_answers_not_supported() -> None:
    profile = load_profile("rbe3001")
    driver = Rbe3001Driver(profile, SimLink(make_sim_device(profile)), TelemetryHub("rbe3001"))
    with pytest.raises(NotSupported) as err:
        await driver.reboot(1)
    assert err.value.code == "not_supported" and err.value.status_code == 409


def test_the_guard_latches_and_refuses_motion() -> None:
    profile = load_profile("rbe3001")
    driver = Rbe3001Driver(profile, SimLink(make_sim_device(profile)), TelemetryHub("rbe3001"))
    guard = SafetyGuard(profile, driver.model, driver)
    guard.require_motion_allowed()
    assert guard.latch() is True and guard.latch() is False  # the second press changes nothing
    with pytest.raises(EstopLatched) as err:
        guard.require_motion_allowed()
    assert err.value.code == "estop_latched"
    assert guard.release() is True and guard.release() is False
    guard.require_motion_allowed()
    with pytest.raises(JointLimit):
        guard.check_joint_target(np.array([10.0, 0.0, 0.0]))
    with pytest.raises(InvalidRequest):
        guard.check_joint_target(np.array([np.nan, 0.0, 0.0]))
    guard.closing = True
    with pytest.raises(Exception) as closing:
        guard.require_motion_allowed()
    assert getattr(closing.value, "code", None) == "shutting_down"


def test_a_driver_publishes_faults_and_homed_itself() -> None:
    profile = load_profile("rbe3001")
    hub = TelemetryHub("rbe3001")
    driver = Rbe3001Driver(profile, SimLink(make_sim_device(profile)), hub)
    driver._publish(np.array([0.1, 0.6, 0.3]), np.zeros(3), None, stale=False)
    assert hub.latest is not None
    assert list(hub.latest) == SAMPLE_KEYS
    assert hub.latest["homed"] == list(driver.homed) and hub.latest["faults"] == []


async def test_the_arm_hub_stamps_estop_and_motion_in_wire_order() -> None:
    svc = ArmService(homed_at_start(load_profile("rbe3001")))
    assert isinstance(svc.hub, ArmHub)
    await svc.start()
    try:
        assert await svc.driver.wait_connected(5.0)
        await svc.latch_estop()
        await new_samples(svc.hub, 2)
        latest = svc.hub.latest
        assert latest is not None and latest["estop"] is True
        assert list(latest) == SAMPLE_KEYS
        assert s.Sample.model_validate(latest).estop is True
        await svc.release_estop()
        rec = await svc.motion.move_joints(s.MoveJoints(positions=[0.05, 0.3, 0.2]))
        latest = await wait_for(lambda: (x := svc.hub.latest) is not None
                                and x["motion"] is not None and x, what="a sample with the motion")
        assert latest is not None and latest["estop"] is False
        assert latest["motion"]["id"] == rec.id
        assert svc.hub.latest_bytes is not None and b'"estop":false' in svc.hub.latest_bytes
    finally:
        await svc.close()
