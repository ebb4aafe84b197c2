"""aiomqtt's internals: the only module that touches them.

Checked with aiomqtt 2.5.1 (pyproject.toml: `>=2.0,<2.6`). `check()` runs when this module is
imported (by `app.telemetry.mqtt`).

The MQTT bridge publishes a tick's QoS 0 messages (telemetry and state, two per arm) straight
to the paho client aiomqtt holds, in one synchronous pass, not one aiomqtt coroutine each (a
gathered coroutine is a Task: two thirds of the bridge's CPU went there; `bench/mqtt.py`'s
28 us per message is with this door). aiomqtt < 3 gives no public way to its paho client.
"""

from __future__ import annotations

import asyncio
import contextlib

import aiomqtt
import paho.mqtt.client as mqtt

from app.doors import paho as paho_door
from app.doors import require, uses

CHECKED = "2.5.1"


def paho_client(client: aiomqtt.Client) -> mqtt.Client:
    """The paho client under `client` (internal: `aiomqtt.Client._client`)."""
    return client._client


def retrieve_disconnection(client: aiomqtt.Client | None) -> None:
    """Read the exception of `client`'s ended connection, if it holds one: aiomqtt keeps it in
    a future that nobody awaits unless they iterate messages (the bridge subscribes to
    nothing), and asyncio would log it as never retrieved (internal: `Client._disconnected`)."""
    gone = getattr(client, "_disconnected", None)
    if isinstance(gone, asyncio.Future) and gone.done() and not gone.cancelled():
        gone.exception()


def drop_late_writer_soon(paho: mqtt.Client, fd: int) -> None:
    """After writing paho's queue ourselves (`loop_write`), remove the writer aiomqtt adds
    late on paho's socket `fd`, if paho has nothing left to write.

    paho's publish asks aiomqtt for a writer, and aiomqtt adds it with `call_soon_threadsafe`,
    a loop iteration later; our `loop_write` has by then written everything and paho has asked
    for the (not yet added) writer's removal. The writer then added stays: paho, thinking none
    is registered, never asks again, and the loop calls it for ever on a writable socket (the
    HTTP loop at 100 % CPU, telemetry latency p99 0.4-0.5 s in bench/mqtt.py). Scheduled with
    `call_soon`, the removal runs after that late addition."""
    asyncio.get_running_loop().call_soon(_drop_late_writer, paho, fd)


def _drop_late_writer(paho: mqtt.Client, fd: int) -> None:
    if not paho_door.write_registered(paho):  # no writer wanted (paho asks again when it does)
        with contextlib.suppress(ValueError, OSError):  # the socket closed meanwhile
            asyncio.get_running_loop().remove_writer(fd)


def check() -> None:
    """Raise app.doors.DoorError naming each internal above the installed aiomqtt lacks."""
    c = aiomqtt.Client
    require("app.doors.aiomqtt", "aiomqtt", CHECKED, [
        ("Client._client, the paho client",
         lambda: uses(c.__init__, "_client"),
         "the MQTT bridge cannot publish its QoS 0 messages"),
        ("Client._disconnected, the future of the connection's end",
         lambda: uses(c.__init__, "_disconnected"),
         "asyncio logs 'Future exception was never retrieved' after each lost connection"),
    ])


check()
