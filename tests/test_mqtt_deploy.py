"""The shipped broker config (config/mosquitto/: mosquitto.conf and its ACL, as
docker-compose.yml mounts them) run by a real Mosquitto: the server's account writes, anyone
reads over MQTT and over WebSocket, and an anonymous client cannot write an arm's topics."""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import subprocess
from pathlib import Path

import pytest
import yaml
from _deps import missing_message
from _mosquitto import MOSQUITTO, MOSQUITTO_PASSWD, Broker, free_port
from conftest import make_settings, running_client

aiomqtt = pytest.importorskip("aiomqtt")

if MOSQUITTO is None or MOSQUITTO_PASSWD is None:
    pytest.skip(missing_message("mosquitto" if MOSQUITTO is None else "mosquitto_passwd"),
                allow_module_level=True)

ROOT = Path(__file__).resolve().parents[1]
CONF = ROOT / "config" / "mosquitto"


def test_compose_runs_mosquitto_beside_the_server() -> None:
    doc = yaml.safe_load((ROOT / "docker-compose.yml").read_text())
    server, broker = doc["services"]["armserver"], doc["services"]["mosquitto"]
    assert server["environment"]["ARMSERVER_MQTT_URL"].endswith("@mosquitto:1883")
    assert "mosquitto" in server["depends_on"]
    mounts = {v.split(":")[1] for v in broker["volumes"] if v.startswith("./")}
    assert mounts == {"/mosquitto/config/mosquitto.conf", "/mosquitto/config/acl"}
    assert {p.rsplit(":", 1)[1] for p in broker["ports"]} == {"1883", "9001"}


class ShippedBroker(Broker):
    """Mosquitto over config/mosquitto/ with its paths and ports moved into a temp dir."""

    def __init__(self, workdir: Path, password: str) -> None:
        super().__init__(workdir)
        self.ws_port = free_port()
        data = workdir / "data"
        data.mkdir()
        pw = data / "passwd"
        pw.write_text("")
        subprocess.run([MOSQUITTO_PASSWD, "-b", str(pw), "armserver", password], check=True)
        pw.chmod(0o600)
        (workdir / "acl").write_text((CONF / "acl").read_text())
        text = (CONF / "mosquitto.conf").read_text()
        text = (text.replace("/mosquitto/data/", f"{data}/")
                .replace("/mosquitto/config/acl", str(workdir / "acl"))
                .replace("listener 1883", f"listener {self.port} 127.0.0.1")
                .replace("listener 9001", f"listener {self.ws_port} 127.0.0.1"))
        if os.geteuid() == 0:
            text += "\nuser root\n"
        self.conf.write_text(text)


async def test_the_server_writes_anyone_reads_nobody_else_writes(tmp_path: Path) -> None:
    broker = ShippedBroker(tmp_path, "s3cret").start()
    try:
        url = f"mqtt://armserver:s3cret@127.0.0.1:{broker.port}"
        async with running_client(make_settings(mqtt_url=url)) as (_, client):
            for _ in range(600):  # up, and past its first ticks: the flags are retained
                mqtt = (await client.get("/api/v1/health")).json()["mqtt"]
                if mqtt["state"] == "up" and mqtt["published"] >= 10:
                    break
                await asyncio.sleep(0.05)
            async with aiomqtt.Client("127.0.0.1", broker.port) as anon, \
                    aiomqtt.Client("127.0.0.1", broker.ws_port, transport="websockets") as web:
                await anon.subscribe("armserver/#", qos=1)
                await web.subscribe("armserver/rbe3001/online", qos=1)
                # an anonymous client's publish is dropped by the ACL (MQTT 3.1.1 has no NACK)
                await anon.publish("armserver/rbe3001/online", b"false", qos=1, retain=True)
                await anon.publish("armserver/intruder/online", b"true", qos=1, retain=True)
                seen: dict[str, list[object]] = {}
                with contextlib.suppress(TimeoutError):
                    async with asyncio.timeout(1.5):
                        async for msg in anon.messages:
                            payload = json.loads(bytes(msg.payload))  # type: ignore[arg-type]
                            seen.setdefault(str(msg.topic), []).append(payload)
                async with asyncio.timeout(5):
                    async for msg in web.messages:
                        assert msg.retain and json.loads(bytes(msg.payload)) is True  # type: ignore[arg-type]
                        break
            assert seen["armserver/server/online"] == [True]
            assert seen["armserver/rbe3001/online"] == [True], "an anonymous write got through"
            assert "armserver/rbe3001/state" in seen and "armserver/rbe3001/telemetry" in seen
            assert "armserver/intruder/online" not in seen
    finally:
        broker.stop()
