"""Profiles and server config files: the built-ins carry the design documents' values, and a
config file overrides only what it names."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
from pydantic import ValidationError

from app.arms.loading import check_profile, load_arms, load_profile
from app.config import ArmProfile, ConfigError, Settings

ROOT = Path(__file__).resolve().parents[1]


def test_builtin_profiles_carry_the_design_values():
    rbe = load_profile("rbe3001")
    assert (rbe.link.vid, rbe.link.pid, rbe.link.poll_hz) == (0x3742, 0x0007, 500.0)
    inch = 0.0254
    assert rbe.geometry == pytest.approx({"l1": 8 * inch, "l2": 6.5 * inch, "l3": 8.125 * inch})
    ang = load_profile("angler")
    assert [j.lead_m for j in ang.joints] == [0.008, 0.008, None, 0.1257]
    # theta3 in extended position mode: the MATLAB's -90 deg is tick -1024 (issue 24)
    assert [j.operating_mode for j in ang.joints] == [4, 4, 4, 4]
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
    """The models' own checks and the arm type's (check_profile, where profiles are read)
    refuse with the reason and where; the plain model knows no arm type."""
    base = load_profile("rbe3001").model_dump()
    for patch, match in [({"geometry": {"l1": 0.2}}, "geometry needs"),
                         ({"joints": base["joints"][:2]}, "3 joints"),
                         ({"model": "scara"}, 'unknown arm type .scara.*"angler"'),
                         ({"geometry": {**base["geometry"], "l2": float("nan")}}, "finite")]:
        with pytest.raises(ConfigError, match=match):
            check_profile({**base, **patch}, "test profile")
    bad = dict(base["joints"][0], min=1.0, max=0.0)
    with pytest.raises(ConfigError, match="(?s)test profile.*min must be below max"):
        check_profile({**base, "joints": [bad, *base["joints"][1:]]}, "test profile")
    with pytest.raises(ValidationError, match="min must be below max"):
        ArmProfile.model_validate({**base, "joints": [bad, *base["joints"][1:]]})


def test_settings_from_environment(monkeypatch):
    monkeypatch.setenv("ARMSERVER_OPERATOR_TOKENS", "a, b ,")
    monkeypatch.setenv("ARMSERVER_PORT", "9001")
    s = Settings()
    assert s.operator_set == {"a", "b"} and s.port == 9001 and s.auth_enabled
    assert s.host == "127.0.0.1"  # loopback unless told otherwise


# ---------------------------------------------------------------- issue 11.5 and 11.11

@pytest.mark.parametrize(("over", "says"), [
    ({"lease_ttl_s": float("nan")}, "ARMSERVER_LEASE_TTL_S=nan: must be a finite number"),
    ({"lease_ttl_s": float("inf")}, "ARMSERVER_LEASE_TTL_S=inf: must be a finite number"),
    ({"lease_ttl_s": 0}, "ARMSERVER_LEASE_TTL_S=0.0: must be > 0"),
    ({"lease_ttl_s": -5}, "ARMSERVER_LEASE_TTL_S=-5.0: must be > 0"),
    ({"max_body_bytes": 0}, "ARMSERVER_MAX_BODY_BYTES=0"),
    ({"max_ws_message_bytes": -1}, "ARMSERVER_MAX_WS_MESSAGE_BYTES=-1"),
    ({"port": 70000}, "ARMSERVER_PORT=70000"),
    ({"log_level": "loud"}, "ARMSERVER_LOG_LEVEL='loud'"),
])
def test_every_setting_is_validated(over, says):
    with pytest.raises(ValidationError, match=says.replace("(", r"\(").replace("+", r"\+")):
        Settings(**over)


def _serve(tmp_path, *args, **env):
    """`armserver serve` in a subprocess that must exit at once (bad settings or config)."""
    full = {k: v for k, v in os.environ.items() if not k.startswith("ARMSERVER_")}
    full.update(env)
    return subprocess.run([sys.executable, "-m", "app.cli", "serve", *args], cwd=ROOT, env=full,
                          capture_output=True, text=True, timeout=60)


@pytest.mark.parametrize("ttl", ["nan", "inf", "0", "-5"])
def test_serve_refuses_a_bad_lease_ttl_with_one_clear_message(tmp_path, ttl):
    r = _serve(tmp_path, ARMSERVER_LEASE_TTL_S=ttl)
    assert r.returncode == 2
    assert "Traceback" not in r.stderr
    assert f"ARMSERVER_LEASE_TTL_S={float(ttl)!r}" in r.stderr, r.stderr


def test_unknown_profile_lists_the_builtins(tmp_path):
    cfg = tmp_path / "arms.toml"
    cfg.write_text('[[arms]]\nprofile = "ur5"\n')
    with pytest.raises(ConfigError) as info:
        load_arms(cfg)
    msg = str(info.value)
    assert str(cfg) in msg and "'ur5'" in msg and '"rbe3001", "angler"' in msg
    r = _serve(tmp_path, "--config", str(cfg))
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert "'ur5'" in r.stderr and "rbe3001" in r.stderr and len(r.stderr.splitlines()) <= 3


def test_malformed_toml_says_where(tmp_path):
    cfg = tmp_path / "arms.toml"
    cfg.write_text('[[arms]\nprofile = "rbe3001"\n')
    with pytest.raises(ConfigError, match=r"malformed TOML.*line 1"):
        load_arms(cfg)
    r = _serve(tmp_path, "--config", str(cfg))
    assert r.returncode == 2 and "Traceback" not in r.stderr and "malformed TOML" in r.stderr
    r = _serve(tmp_path, "--config", str(tmp_path / "missing.toml"))
    assert r.returncode == 2 and "Traceback" not in r.stderr and "no such file" in r.stderr


def test_invalid_values_in_a_config_name_the_arm_and_the_key(tmp_path):
    cfg = tmp_path / "arms.toml"
    cfg.write_text('[[arms]]\nprofile = "rbe3001"\n[arms.link]\npoll_hz = -1\n')
    with pytest.raises(ConfigError, match=r"\[\[arms\]\] #1.*\n  link.poll_hz: "):
        load_arms(cfg)
