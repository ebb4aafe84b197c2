"""Config for a lab: many simulated arms from one `[[arms]]` entry (`count`), and the MQTT
settings (broker URL with credentials, prefix, rate), refused at start-up when malformed."""

from __future__ import annotations

from pathlib import Path

import pytest
from conftest import make_settings, running_client
from pydantic import ValidationError

from app.arms.loading import load_arms
from app.config.settings import parse_broker_url


def test_count_hosts_numbered_copies(tmp_path: Path) -> None:
    cfg = tmp_path / "lab.toml"
    cfg.write_text('[[arms]]\nprofile = "rbe3001"\nname = "bench"\ncount = 3\n'
                   '[arms.link]\npoll_hz = 50.0\n\n'
                   '[[arms]]\nprofile = "angler"\n')
    arms = load_arms(cfg)
    assert [a.name for a in arms] == ["bench-1", "bench-2", "bench-3", "angler"]
    assert all(a.link.poll_hz == 50.0 and a.model == "rbe3001" for a in arms[:3])
    assert arms[3].link.poll_hz != 50.0


@pytest.mark.parametrize("count", ["0", "257", '"3"', "2.5", "true"])
def test_bad_count_is_refused(tmp_path: Path, count: str) -> None:
    cfg = tmp_path / "lab.toml"
    cfg.write_text(f'[[arms]]\nprofile = "rbe3001"\ncount = {count}\n')
    with pytest.raises(ValueError, match="count must be an integer 1..256"):
        load_arms(cfg)


def test_copies_that_collide_with_another_arm_are_refused(tmp_path: Path) -> None:
    cfg = tmp_path / "lab.toml"
    cfg.write_text('[[arms]]\nprofile = "rbe3001"\nname = "a"\ncount = 2\n\n'
                   '[[arms]]\nprofile = "rbe3001"\nname = "a-2"\n')
    with pytest.raises(ValueError, match="unique"):
        load_arms(cfg)


async def test_a_server_runs_every_copy(tmp_path: Path) -> None:
    cfg = tmp_path / "lab.toml"
    cfg.write_text('[[arms]]\nprofile = "rbe3001"\nname = "lab"\ncount = 4\n')
    async with running_client(make_settings(config=str(cfg))) as (_, client):
        arms = (await client.get("/api/v1/arms")).json()
        assert [a["name"] for a in arms] == ["lab-1", "lab-2", "lab-3", "lab-4"]
        for a in arms:
            assert (await client.get(f"/api/v1/arms/{a['name']}/state")).status_code == 200


def test_broker_url_parsing() -> None:
    b = parse_broker_url("mqtt://srv:p%40ss@broker.lab:1884")
    assert (b.host, b.port, b.username, b.password, b.tls) == ("broker.lab", 1884, "srv",
                                                               "p@ss", False)
    assert b.public == "mqtt://srv@broker.lab:1884"
    assert parse_broker_url("mqtt://h").port == 1883
    assert parse_broker_url("mqtts://h").port == 8883 and parse_broker_url("mqtts://h").tls


@pytest.mark.parametrize("over", [{"mqtt_url": "http://h"}, {"mqtt_url": "mqtt://"},
                                  {"mqtt_url": "mqtt://h:99999"}, {"mqtt_rate": 0},
                                  {"mqtt_rate": 1000}, {"mqtt_prefix": "a/+/b"},
                                  {"mqtt_prefix": "lab/#"}, {"mqtt_prefix": "/x"}])
def test_bad_mqtt_settings_are_refused(over: dict[str, object]) -> None:
    with pytest.raises(ValidationError):
        make_settings(**over)


def test_mqtt_settings_from_the_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("ARMSERVER_MQTT_URL", "mqtt://u:pw@127.0.0.1:1883")
    monkeypatch.setenv("ARMSERVER_MQTT_PREFIX", "lab/bench3")
    monkeypatch.setenv("ARMSERVER_MQTT_RATE", "5")
    s = make_settings()
    assert (s.mqtt_url, s.mqtt_prefix, s.mqtt_rate) == ("mqtt://u:pw@127.0.0.1:1883",
                                                        "lab/bench3", 5.0)
    monkeypatch.setenv("ARMSERVER_MQTT_URL", "")
    assert make_settings().mqtt_url is None
