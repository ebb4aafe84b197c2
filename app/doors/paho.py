"""paho-mqtt's internals: the only module that touches them.

Checked with paho-mqtt 2.2.0 (pyproject.toml: `>=2.1,<2.3`). `check()` runs when this module is
imported (by `app.doors.aiomqtt`, from the MQTT bridge).

The MQTT bridge writes a tick's QoS 0 messages itself (`paho.Client.publish`, then
`loop_write`: public), so that they leave in the tick; aiomqtt then adds its socket writer a
loop iteration late, after paho has already asked for its removal, and that writer would be
called for ever on a writable socket (the HTTP loop at 100 % CPU, telemetry p99 0.4-0.5 s in
`bench/mqtt.py`). Whether paho still wants a writer is its private `_registered_write`; the
public `want_write()` says whether it has bytes queued, which is not the same after an SSL
read that needs a write (paho then wants a writer with nothing queued).
"""

from __future__ import annotations

import paho.mqtt.client as mqtt

from app.doors import require, uses

CHECKED = "2.2.0"


def write_registered(client: mqtt.Client) -> bool:
    """Whether paho has asked its event loop for a socket writer and not since for its removal
    (internal: `Client._registered_write`)."""
    return bool(client._registered_write)


def check() -> None:
    """Raise app.doors.DoorError naming each internal above the installed paho-mqtt lacks."""
    c = mqtt.Client
    require("app.doors.paho", "paho-mqtt", CHECKED, [
        ("Client._registered_write, set by _call_socket_register_write and cleared by "
         "_call_socket_unregister_write",
         lambda: (uses(c.__init__, "_registered_write")
                  and uses(c._call_socket_register_write, "_registered_write")
                  and uses(c._call_socket_unregister_write, "_registered_write")),
         "the MQTT bridge cannot tell a stale socket writer from a wanted one: with the bridge "
         "on, the server's HTTP loop can spin at 100 % CPU"),
    ])


check()
