"""The OpenManipulator-X profile parses as TOML and agrees with kinematics/omx.py and the
XM430-W350 data (tests/test_omx_arm.py loads it through the arm-type registry)."""

from __future__ import annotations

import math
import tomllib
from pathlib import Path
from typing import Any

import pytest

from app.config import JointConfig
from kinematics import omx
from protocol import xm430

PROFILE = (Path(__file__).resolve().parents[1] / "app" / "arms" / "openmanipulator_x"
           / "openmanipulator_x.toml")


@pytest.fixture(scope="module")
def prof() -> dict[str, Any]:
    with PROFILE.open("rb") as f:
        return tomllib.load(f)


def test_geometry_is_the_kinematics_default(prof: dict[str, Any]) -> None:
    g = omx.OMX()
    assert prof["geometry"] == {k: getattr(g, k) for k in ("bx", "bz", "d1", "a2x", "a2z",
                                                           "l3", "l4")}
    assert omx.OMX(**prof["geometry"]) == g


def test_joints_limits_ids_and_home(prof: dict[str, Any]) -> None:
    joints = [JointConfig(**j) for j in prof["joints"]]  # every key is a known joint key
    assert [j.name for j in joints] == ["waist", "shoulder", "elbow", "wrist"]
    assert [j.min for j in joints] == pytest.approx(omx.LOWER, abs=1e-6)
    assert [j.max for j in joints] == pytest.approx(omx.UPPER, abs=1e-6)
    assert [j.motor_id for j in joints] + [prof["gripper"]["motor_id"]] == list(omx.IDS)
    assert all(j.ticks_per_rev == xm430.TICKS_PER_REV and j.offset_ticks == 2048
               for j in joints)
    assert all(j.operating_mode in xm430.OPERATING_MODES for j in joints)
    assert prof["home"] == list(omx.HOME)
    assert all(j.min <= h <= j.max for j, h in zip(joints, prof["home"], strict=True))


def test_speeds_under_the_xm430_no_load_speed(prof: dict[str, Any]) -> None:
    no_load = xm430.no_load_rpm(12.0) * 2 * math.pi / 60  # 46 rpm at 12 V: 4.82 rad/s
    assert no_load == pytest.approx(4.817, abs=1e-3)
    for j in prof["joints"]:
        assert 0 < j["max_velocity"] < no_load
        assert j["stall_torque_nm"] == 4.1


def test_gripper(prof: dict[str, Any]) -> None:
    gr = prof["gripper"]
    assert (gr["min"], gr["max"]) == (omx.GRIPPER_MIN, omx.GRIPPER_MAX)
    assert gr["operating_mode"] in xm430.OPERATING_MODES
    assert gr["rad_per_m"] == pytest.approx(1 / -0.015, rel=1e-5)
