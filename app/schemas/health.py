"""The server's health: links, store, MQTT bridge."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from app.schemas.arms import LinkStatus
from app.schemas.cameras import CameraStatus
from app.schemas.common import Model


class StoreStatus(Model):
    ok: bool
    path: str
    pending: int = Field(description="changes kept in memory until the database takes them")
    error: str | None = None


class MqttStatus(Model):
    """The MQTT bridge (API.md "Lab-wide telemetry over MQTT")."""

    state: Literal["connecting", "up", "down", "refused"] = Field(
        description="`refused`: the broker refused our credentials or client id")
    broker: str = Field(description="the broker's URL, without the password")
    prefix: str
    rate_hz: float
    last_error: str | None = None
    connects: int = Field(description="successful connections since the server started")
    published: int = Field(description="messages handed to the broker")
    dropped_samples: int = Field(description="samples not sent (broker away or too slow)")
    dropped_events: int
    tick_cpu_s: float = Field(0.0, description="CPU time the bridge spent publishing (its "
                              "ticks: collect, build, queue, write), s")


class Health(Model):
    status: Literal["ok", "degraded"]
    arms: dict[str, LinkStatus]
    auth: bool
    store: StoreStatus | None = None
    mqtt: MqttStatus | None = Field(None, description="present when ARMSERVER_MQTT_URL is set")
    cameras: dict[str, CameraStatus] = Field(
        default_factory=dict, description="each camera: up, or down with its last error (a "
        "camera does not make `status` degraded: the arms serve without it)")
