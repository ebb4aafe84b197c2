"""Profiles and server config files: the built-ins carry the design documents' values, and a
config file overrides only what it names."""

from __future__ import annotations

from pathlib import Path

import pytest
from pydantic import ValidationError

from app.config import ArmProfile, Settings, load_arms, load_profile

ROOT = Path(__file__).resolve().parents[1]


def test_builtin_profiles_carry_the_design_values():
    rbe = load_profile("rbe3001")
    assert (rbe.link.vid, rbe.link.pid, rbe.link.poll_hz) == (0x3742, 0x0007, 500.0)
    inch = 0.0254
    assert rbe.geometry == pytest.approx({"l1": 8 * inch, "l2": 6.5 * inch, "l3": 8.125 * inch})
    ang = load_profile("angler")
    assert [j.lead_m for j in ang.joints] == [0.008, 0.008, None, 0.1257]
    assert [j.operating_mode for j in ang.joints] == [4, 4, 3, 4]
    assert ang.joints[2].min == pytest.approx(-1.5708) and ang.link.poll_hz == 200.0


def test_default_server_hosts_both_simulated_arms():
    arms = load_arms(None)
    assert [(a.name, a.link.kind) for a in arms] == [("rbe3001", "sim"), ("angler", "sim")]


def test_hardware_example_overrides_only_the_link():
    arms = load_arms(ROOT / "config" / "hardware.example.toml")
    rbe, ang = arms
    assert (rbe.link.kind, rbe.link.vid, rbe.link.poll_hz) == ("hid", 0x3742, 500.0)
    assert (ang.link.kind, ang.link.address, ang.link.baudrate) == ("serial", "/dev/ttyUSB0",
                                                                    1_000_000)
    assert ang.geometry == load_profile("angler").geometry


def test_two_arms_of_one_model_need_distinct_names(tmp_path):
    cfg = tmp_path / "two.toml"
    cfg.write_text('[[arms]]\nprofile = "rbe3001"\n[[arms]]\nprofile = "rbe3001"\n')
    with pytest.raises(ValueError, match="unique"):
        load_arms(cfg)
    cfg.write_text('[[arms]]\nprofile = "rbe3001"\n[[arms]]\nprofile = "rbe3001"\nname = "left"\n')
    assert [a.name for a in load_arms(cfg)] == ["rbe3001", "left"]


def test_bad_profiles_are_refused_with_reasons():
    base = load_profile("rbe3001").model_dump()
    for patch, match in [({"geometry": {"l1": 0.2}}, "geometry needs"),
                         ({"joints": base["joints"][:2]}, "3 joints"),
                         ({"geometry": {**base["geometry"], "l2": float("nan")}}, "finite")]:
        with pytest.raises(ValidationError, match=match):
            ArmProfile.model_validate({**base, **patch})
    bad = dict(base["joints"][0], min=1.0, max=0.0)
    with pytest.raises(ValidationError, match="min must be below max"):
        ArmProfile.model_validate({**base, "joints": [bad, *base["joints"][1:]]})


def test_settings_from_environment(monkeypatch):
    monkeypatch.setenv("ARMSERVER_OPERATOR_TOKENS", "a, b ,")
    monkeypatch.setenv("ARMSERVER_PORT", "9001")
    s = Settings()
    assert s.operator_set == {"a", "b"} and s.port == 9001 and s.auth_enabled
    assert s.host == "127.0.0.1"  # loopback unless told otherwise
